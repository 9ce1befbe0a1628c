"""Load and disturbance profiles (service/plant/profiles.py): a combined profile is the sum of its parts, on/off
switching draws nothing while off, the Ornstein-Uhlenbeck term is its seed's, the rate is the value's derivative,
and range_over bounds what the profile does over a window, wherever a profile is read."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from schemas.network import network_from_dict
from schemas.scenario import ProfileConfig, ScenarioError, scenario_from_dict
from service.plant.network import NetworkPlant
from service.plant.profiles import Profile

OU = {"sigma": 150.0, "tau_s": 0.02, "seed": 7}
STEPS = [[0.1, 1800.0], [0.25, 900.0]]
SINES = [{"amplitude": 200.0, "freq_hz": 7.0}, {"amplitude": 80.0, "freq_hz": 31.0, "phase_rad": 0.4}]
COMBINED = {"kind": "combined", "value": 1200.0, "steps": STEPS, "components": SINES, "ou": OU}


def profile(**cfg) -> Profile:
    return Profile(ProfileConfig(**cfg))


def mid_segment_times(n: int, t1: float, grid_s: float = 1e-3, seed: int = 0) -> np.ndarray:
    """n times in [0, t1) at random places inside the OU grid's segments, clear of its breakpoints and of STEPS."""
    rng = np.random.default_rng(seed)
    t = (rng.integers(0, int(t1 / grid_s), n) + rng.uniform(0.1, 0.9, n)) * grid_s
    return t[np.min(np.abs(t[:, None] - np.array([s[0] for s in STEPS])[None, :]), axis=1) > grid_s]


def test_a_combined_profile_is_the_sum_of_its_parts():
    whole = profile(**COMBINED)
    steps = profile(kind="steps", value=1200.0, steps=STEPS)
    sines = profile(kind="sines", value=0.0, components=SINES)
    ou = profile(kind="constant", value=0.0, ou=OU)
    for t in np.linspace(0.0, 0.4, 997):
        parts = steps.value(t) + sines.value(t) + ou.value(t)
        assert whole.value(t) == pytest.approx(parts, rel=1e-12, abs=1e-9)
        assert whole.rate(t) == pytest.approx(steps.rate(t) + sines.rate(t) + ou.rate(t), rel=1e-12, abs=1e-6)
    assert steps.rate(0.2) == 0.0 and whole.value(0.0) == 1200.0 + sines.value(0.0)  # the OU term starts at 0


def test_every_kind_may_add_the_ou_term_and_keeps_its_own_shape():
    ou = profile(ou=OU, value=0.0)
    for base in ({"kind": "constant", "value": 500.0}, {"kind": "steps", "value": 500.0, "steps": STEPS},
                 {"kind": "sines", "value": 500.0, "components": SINES}):
        plain, noisy = profile(**base), profile(**base, ou=OU)
        for t in (0.0, 0.0123, 0.1, 0.31):
            assert noisy.value(t) == pytest.approx(plain.value(t) + ou.value(t), abs=1e-9)


def test_switched_off_it_draws_nothing_and_switched_on_it_is_the_profile_again():
    on_off = {"off_at_s": [0.1, 0.3], "on_at_s": [0.2]}
    switched, always = profile(**COMBINED, **on_off), profile(**COMBINED)
    for t in np.linspace(0.0, 0.4, 801):
        off = 0.1 <= t < 0.2 or t >= 0.3
        assert switched.value(t) == (0.0 if off else always.value(t)), t
        assert switched.rate(t) == (0.0 if off else always.rate(t)), t
    assert switched.event_times() == [0.1, 0.2, 0.25, 0.3]  # the steps' and the switches' times, sorted
    starts_off = profile(value=1200.0, off_at_s=[0.0], on_at_s=[0.05])  # a load switched in at 50 ms
    assert starts_off.value(0.0) == 0.0 and starts_off.value(0.049) == 0.0 and starts_off.value(0.05) == 1200.0


def test_the_ou_path_is_its_seeds_whatever_order_it_is_read_in():
    ts = np.linspace(0.0, 3.0, 2001)
    a, b = profile(**COMBINED), profile(**COMBINED)
    forward = [a.value(t) for t in ts]
    backward = [b.value(t) for t in ts[::-1]][::-1]  # b draws its whole path at the first question
    assert forward == backward  # to the bit
    other = profile(**{**COMBINED, "ou": {**OU, "seed": 8}})
    diff = np.abs(np.array(forward) - np.array([other.value(t) for t in ts]))
    assert diff.max() > 50.0 and np.mean(diff > 1.0) > 0.9


def test_the_ou_term_has_the_spread_and_the_correlation_time_it_was_given():
    """Read on its grid over 2 000 correlation times (one fixed seed, so the numbers cannot vary between runs)."""
    tau, h = 0.01, 1e-3
    ou = profile(value=0.0, ou={"sigma": 3.0, "tau_s": tau, "seed": 11, "grid_s": h})
    x = np.array([ou.value(k * h) for k in range(1, 20_001)])
    assert np.std(x) == pytest.approx(3.0, rel=0.1)
    lag = int(tau / h)
    rho = np.corrcoef(x[:-lag], x[lag:])[0, 1]
    assert rho == pytest.approx(math.exp(-1.0), abs=0.06)


def test_the_rate_is_the_derivative_of_the_value():
    p = profile(**COMBINED, off_at_s=[0.3], on_at_s=[0.35])
    d = 1e-7
    for t in mid_segment_times(400, 0.4):
        if abs(t - 0.3) < 2e-3 or abs(t - 0.35) < 2e-3:
            continue
        fd = (p.value(t + d) - p.value(t - d)) / (2 * d)
        assert fd == pytest.approx(p.rate(t), rel=1e-5, abs=1e-2), t


def test_range_over_bounds_the_profile_over_its_window_and_is_reached():
    """Against the profile read every 10 us: range_over's box holds every value and rate, and its ends are met
    (the piecewise-linear OU path's extremes lie on its grid, its slopes inside its segments)."""
    p = profile(**COMBINED, off_at_s=[0.3], on_at_s=[0.32])
    for t0, t1 in ((0.0, 0.1), (0.05, 0.35), (0.2, 0.4)):
        lo, hi, dlo, dhi = p.range_over(t0, t1)
        ts = np.linspace(t0, t1, int(round((t1 - t0) / 1e-5)) + 1)
        vals = [p.value(t) for t in ts]
        rates = [p.rate(t) for t in ts]
        tol = 1e-3 * (dhi - dlo)  # the sines between the points it reads (the OU segments' slopes: exact)
        assert lo <= min(vals) and max(vals) <= hi
        assert dlo - tol <= min(rates) and max(rates) <= dhi + tol
        assert min(vals) - lo < 1.0 and hi - max(vals) < 1.0  # W
        assert min(rates) - dlo < tol and dhi - max(rates) < tol
    lo, hi, _, _ = p.range_over(0.29, 0.31)
    assert lo == 0.0 and hi > 800.0  # the window holds the switch off


def test_old_kinds_keep_their_values():
    """The kinds that existed before the combined one, read as they were: value, then steps; value + sines."""
    steps = profile(kind="steps", value=1200.0, steps=STEPS)
    assert [steps.value(t) for t in (0.0, 0.0999, 0.1, 0.2, 0.25, 1.0)] == [1200.0, 1200.0, 1800.0, 1800.0, 900.0,
                                                                             900.0]
    sines = profile(kind="sines", value=1200.0, components=SINES)
    t = 0.0123
    want = 1200.0 + 200.0 * math.sin(2 * math.pi * 7.0 * t) + 80.0 * math.sin(2 * math.pi * 31.0 * t + 0.4)
    assert sines.value(t) == want and sines.event_times() == []


@pytest.mark.parametrize(("load", "words"), [
    ({"kind": "sines", "steps": STEPS}, "kind 'combined' adds steps and sines"),
    ({"kind": "steps", "components": SINES}, "kind 'combined' adds steps and sines"),
    ({"off_at_s": [0.2, 0.1]}, "off_at_s must be strictly increasing"),
    ({"off_at_s": [0.1], "on_at_s": [0.1]}, "both name 0.1 s"),
    ({"ou": {"sigma": 1.0}}, "load.ou.tau_s"),
    ({"ou": {"sigma": 1.0, "tau_s": 0.01, "grid_s": 1e-6}}, "load.ou.grid_s"),
])
def test_a_profile_that_cannot_be_meant_is_refused_with_the_field_named(load, words):
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict({"load": load}, source="x.toml")
    assert "load" in str(ei.value) and words in str(ei.value), str(ei.value)


def test_a_negative_load_is_accepted_and_feeds_the_bus():
    """Power flowing back into the bus (a regenerative drive braking, a battery discharging into it) is a load
    profile below zero: accepted, and the plant's load current is negative."""
    from service.plant.rlc import RLCPlant

    scn = scenario_from_dict({"load": {"kind": "combined", "value": -600.0, "steps": [[0.01, -900.0]]}})
    plant = RLCPlant(scn.plant, Profile(scn.load))
    v0 = plant.v
    plant.advance(0.0, 1e-4, 10)
    assert Profile(scn.load).value(0.02) == -900.0 and plant.v > v0  # it charges the capacitor


NET = {"kind": "network", "sources": {"S1": {}}, "buses": {"bus": {"C_F": 4.7e-3}},
       "lines": {"L1": {"a": "S1", "b": "bus", "R_ohm": 0.15, "L_H": 150e-6}},
       "loads": {"P": {"bus": "bus", **COMBINED, "off_at_s": [0.1], "on_at_s": [0.15]}}}


def test_a_network_load_follows_the_same_profile_and_its_switching_is_an_event():
    from service.network.netsim import run_network

    net = network_from_dict(NET)
    plant = NetworkPlant(net)
    ref = profile(**COMBINED, off_at_s=[0.1], on_at_s=[0.15])
    for t in (0.0, 0.05, 0.12, 0.2):
        assert plant.profiles[0].value(t) == ref.value(t) and plant.profiles[0].rate(t) == ref.rate(t)
    assert plant.load_power(0, 0.12) == 0.0
    res = run_network(network_from_dict({**NET, "timing": {"duration_s": 0.3}}))
    assert [(e.t, e.kind, e.target) for e in res.events] == [(t, "load", "P") for t in (0.1, 0.15, 0.25)]
    with pytest.raises(ScenarioError, match="a resistive load has no profile"):
        network_from_dict({**NET, "loads": {"R": {"bus": "bus", "type": "resistive", "R_ohm": 5.0,
                                                  "off_at_s": [0.1]}}})


def test_the_live_load_and_plant_peers_read_the_same_path():
    """The neighbour load peer publishes, and the stand-in plant draws, the same combined profile to the bit (the OU
    path is drawn from the table's own seed, not the process's), and the load announces range_over's box."""
    from clients.peers.load import LoadPeer
    from clients.peers.plant import PlantRig
    from schemas.codec import Z
    from schemas.component import LoadPeerConfig, PlantPeerConfig

    load = {**COMBINED, "off_at_s": [0.3], "on_at_s": [0.32]}
    peer = LoadPeer(LoadPeerConfig(id="load", load=load, window_s=0.1, forecast_margin=0.0), threading.Event())
    sent = []
    peer.pub = type("Pub", (), {"put": staticmethod(sent.append)})()
    rig = PlantRig(PlantPeerConfig(id="plant", controller_id="source", load=load), threading.Event())
    for k, t in enumerate(np.arange(0.0, 0.4, 1e-3)):
        peer.publish(k, float(t))
        msg = Z.decode(sent[-1])
        assert msg[2] == rig.load.value(float(t)) and msg[3] == rig.load.rate(float(t))
        assert tuple(msg[-4:]) == pytest.approx(rig.load.range_over(msg[7] * 0.1, (msg[7] + 1) * 0.1))
