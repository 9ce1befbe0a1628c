"""Property-based tests (hypothesis): decoding and config parsing fail only in the documented way."""

from __future__ import annotations

import math
import operator

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas.codec import ALLOC, CMD, EST, GRID, LOOP, MEAS, TICK_IN, WINDOW, DecodeError, Z, admits
from schemas.component import ComponentConfig, config_from_dict
from schemas.scenario import ScenarioError, scenario_from_dict

CODECS = [MEAS, CMD, Z, TICK_IN, EST, LOOP, ALLOC, WINDOW]
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
    assert all(admits(r, vals[codec.fields.index(name)]) for name, r in codec.ranges.items())


def admissible(codec, data) -> list:
    """Values for every field of the codec, each anywhere in its admissible range (what its type holds, else)."""
    fmt = codec.struct.format.lstrip("<")[2:]
    vals = []
    for name, c in zip(codec.fields, fmt, strict=True):
        lo, _, hi, hi_op, _ = codec.ranges.get(name, (None, None, None, None, ""))
        if c == "Q":
            top = 2**64 - 1 if hi is None else hi - 1 if hi_op is operator.lt else hi
            vals.append(data.draw(st.integers(lo or 0, top)))
        elif c == "d":
            vals.append(data.draw(st.floats(lo, hi, allow_nan=False, allow_infinity=False,
                                            exclude_max=hi_op is operator.lt)))
        else:
            vals.append(data.draw(st.booleans()))
    return vals


@FAST
@given(st.sampled_from(CODECS), st.data())
def test_admissible_values_round_trip_exactly(codec, data):
    vals = admissible(codec, data)
    assert codec.decode(codec.encode(*vals)) == tuple(vals)


# the boundary values a u64 and a time stamp can take on the wire, inside and outside the admissible ranges
U64_EDGES = [0, 1, 2**31, 2**32, 2**53 - 1, 2**53, 2**63, 2**64 - 1]
T_EDGES = [0.0, -0.0, 5e-324, -5e-324, -1.0, 2.0**32 - 2.0**-20, 2.0**32, 2.0**53, 2.0**63, 2.0**64,
           1.7976931348623157e308, -1.7976931348623157e308]
BOOL_EDGES = [0, 1, 2, 255]  # a bool's u8: 0 or 1, nothing else


@FAST
@given(st.sampled_from([c for c in CODECS if c.ranges]), st.data())
def test_each_field_at_its_edges_is_taken_inside_its_range_and_rejected_by_name_outside(codec, data):
    """seq and window in [0, 2^53), t in [0, 2^32) (schemas.messages), a bool 0 or 1: every boundary of the wire type
    is either decoded to itself or rejected naming that field and its range, whatever the other fields hold."""
    vals = admissible(codec, data)
    name = data.draw(st.sampled_from(sorted(codec.ranges)))
    k = codec.fields.index(name)
    x = data.draw(st.sampled_from(BOOL_EDGES if isinstance(vals[k], bool) else U64_EDGES if isinstance(vals[k], int)
                                  else T_EDGES))
    vals[k] = x
    inside = admits(codec.ranges[name], x)
    try:
        got = codec.decode(codec.encode(*vals))
    except DecodeError as e:
        assert not inside
        assert (e.field, e.reason) == (name, f"{x!r} not in {codec.ranges[name][4]}")
    else:
        assert inside and got[k] == x


def test_the_ranges_are_what_the_code_after_the_decoder_holds():
    """seq below 2^53 is exact as a double (the compiled tick carries it as one) and fits an int64 (numpy, the
    loop-delay history); t below 2^32 s gives a u64 of nanoseconds (an MCAP log time) and resolves 1 us."""
    for codec in (MEAS, CMD, Z, ALLOC):
        assert (codec.ranges["seq"][4], codec.ranges["t"][4]) == ("[0, 2^53)", "[0, 2^32)"), codec.name
        assert admits(codec.ranges["seq"], 2**53 - 1) and not admits(codec.ranges["seq"], 2**53)
    assert MEAS.half_open_ranges() == {"seq": (0, 2**53), "t": (0.0, 2.0**32)}  # what the compiled tick checks
    assert float(2**53 - 1) == 2**53 - 1 and float(2**53 + 1) != 2**53 + 1
    assert round(2.0**32 * 1e9) < 2**64 and math.ulp(2.0**32) == 2.0**-20
    assert Z.ranges["window"][4] == ALLOC.ranges["window"][4] == "[0, 2^53)"
    assert CMD.ranges["limited"][4] == "[0, 1]"
    assert GRID.ranges["seq"] == MEAS.ranges["seq"] and GRID.ranges["t"] == MEAS.ranges["t"]


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
