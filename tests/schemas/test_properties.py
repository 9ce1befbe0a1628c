"""Property-based tests (hypothesis): decoding and config parsing fail only in the documented way."""

from __future__ import annotations

import math

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas.codec import CMD, EST, LOOP, MEAS, TICK_IN, DecodeError, Z
from schemas.component import ComponentConfig, config_from_dict
from schemas.scenario import ScenarioError, scenario_from_dict

CODECS = [MEAS, CMD, Z, TICK_IN, EST, LOOP]
FAST = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FAST
@given(st.sampled_from(CODECS), st.binary(max_size=200))
def test_any_bytes_decode_or_raise_decode_error_naming_a_field(codec, payload):
    try:
        vals = codec.decode(payload)
    except DecodeError as e:
        assert e.message == codec.name and e.field and e.reason
        return
    assert len(vals) == len(codec.fields)
    assert all(math.isfinite(vals[k]) for k in codec.floats)


@FAST
@given(st.sampled_from(CODECS), st.data())
def test_finite_values_round_trip_exactly(codec, data):
    fmt = codec.struct.format.lstrip("<")[2:]
    vals = []
    for c in fmt:
        if c == "Q":
            vals.append(data.draw(st.integers(0, 2**64 - 1)))
        elif c == "d":
            vals.append(data.draw(st.floats(allow_nan=False, allow_infinity=False)))
        else:
            vals.append(data.draw(st.booleans()))
    assert codec.decode(codec.encode(*vals)) == tuple(vals)


@FAST
@given(st.sampled_from(CODECS), st.data())
def test_one_non_finite_float_is_rejected_by_name(codec, data):
    fmt = codec.struct.format.lstrip("<")[2:]
    vals = [0 if c == "Q" else (1.0 if c == "d" else False) for c in fmt]
    k = data.draw(st.sampled_from(codec.floats))
    vals[k] = data.draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    try:
        codec.decode(codec.encode(*vals))
    except DecodeError as e:
        assert e.field == codec.fields[k]
    else:
        raise AssertionError("accepted a non-finite value")


JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=8), children, max_size=3),
    max_leaves=10,
)
SECTIONS = st.sampled_from(["plant", "model", "load", "sensor", "timing", "controller", "feasibility", "seed", "x"])


@FAST
@given(st.dictionaries(SECTIONS, JSONISH, max_size=4))
def test_scenario_parsing_only_raises_scenario_error(data):
    try:
        scenario_from_dict(data)
    except ScenarioError as e:
        assert "invalid scenario" in str(e)


@FAST
@given(st.dictionaries(st.sampled_from(["id", "loop", "controller", "zenoh", "neighbours", "delay_samples"]),
                       JSONISH, max_size=4))
def test_component_config_parsing_only_raises_scenario_error(data):
    try:
        config_from_dict(ComponentConfig, data)
    except ScenarioError as e:
        assert "invalid config" in str(e)


@FAST
@given(st.lists(st.text(max_size=30), max_size=4))
def test_overrides_only_raise_scenario_error(overrides):
    try:
        scenario_from_dict({}, overrides)
    except ScenarioError:
        pass


def test_finite_values_whose_sum_overflows_still_decode_and_the_first_non_finite_is_named():
    """decode checks finiteness with one sum first; a sum that overflows (finite values) must not reject, and
    opposite infinities (their sum NaN) are named by the first of them in field order."""
    big = MEAS.encode(1, 0.5, 1e308, 1e308, 1e308, 1e308)
    assert MEAS.decode(big)[2:] == (1e308, 1e308, 1e308, 1e308)
    try:
        MEAS.decode(MEAS.encode(1, 0.5, math.inf, 80.0, 80.0, -math.inf))
    except DecodeError as e:
        assert e.field == "i"
    else:
        raise AssertionError("inf accepted")
