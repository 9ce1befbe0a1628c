"""service.metrics on synthetic signals with known answers: settle and back-in-band times, the band's hold metrics,
a step's metrics, smoothing, the sharing error, inrush and bus move, steady windows, and a network's metrics on a
hand-made result."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from schemas.scenario import AcceptanceConfig
from service import metrics as M

T = 1e-3
t = np.arange(1000) * T  # 0 .. 0.999 s


def test_settle_time_is_the_first_sample_after_the_last_excursion():
    err = np.zeros_like(t)
    err[:300] = 5.0  # outside until 0.299 s, inside from 0.300 s
    err[120] = 0.0  # a dip inside before the last exit does not count
    assert M.settle_time(t, err, 1.0) == pytest.approx(0.300)
    assert M.settle_time(t, err, 1.0, t0=0.1) == pytest.approx(0.200)


def test_settle_time_inside_from_the_start_is_zero_and_never_settling_is_none():
    assert M.settle_time(t, np.zeros_like(t), 1.0) == 0.0
    never = np.zeros_like(t)
    never[-1] = 2.0  # out at the last sample: not settled by the end
    assert M.settle_time(t, never, 1.0) is None
    assert M.settle_time(t[:0], t[:0], 1.0) is None
    # at the bound counts as inside
    assert M.settle_time(t, np.ones_like(t), 1.0) == 0.0


def test_back_in_band_looks_only_at_its_window_and_is_relative_to_the_target():
    v = np.full_like(t, 80.0)
    v[(t >= 0.4) & (t < 0.45)] = 70.0  # a dip after a step at 0.4 s, back at 0.45 s
    v[t >= 0.8] = 60.0  # something else later, outside the window [0.4, 0.8)
    assert M.back_in_band(t, v, 0.4, 0.8, 80.0, 0.02) == pytest.approx(0.05)
    assert M.back_in_band(t, v, 0.4, math.inf, 80.0, 0.02) is None  # to the end: it never came back
    # +-2 % of 80 V is 1.6 V: 81.5 V is inside, 81.7 V is not; a negative target uses its magnitude
    assert M.back_in_band(t, np.full_like(t, 81.5), 0.0, 1.0, 80.0, 0.02) == 0.0
    assert M.back_in_band(t, np.full_like(t, 81.7), 0.0, 1.0, 80.0, 0.02) is None
    assert M.back_in_band(t, np.full_like(t, -81.5), 0.0, 1.0, -80.0, 0.02) == 0.0


def test_worst_back_and_max_dev():
    assert M.worst_back([0.01, 0.03, 0.02]) == 0.03
    assert M.worst_back([0.01, None]) is None
    assert M.worst_back([]) == 0.0
    v = np.full_like(t, 80.0)
    v[500] = 84.0
    assert M.max_dev_pct(t, v, 0.4, 0.6, 80.0) == pytest.approx(5.0)
    assert M.max_dev_pct(t, v, 0.6, 1.0, 80.0) == 0.0
    assert M.max_dev_pct(t, v, 2.0, 3.0, 80.0) is None


def test_hold_metrics_find_the_largest_deviation_and_the_time_outside():
    v = np.full_like(t, 80.0)
    v[(t >= 0.3) & (t < 0.31)] = 82.4  # 3 % for 10 ms
    acc = AcceptanceConfig()
    hold = M.band_must_hold(t, acc)
    assert not hold[t < acc.hold_from_s].any() and hold[t >= acc.hold_from_s].all()
    m = M.hold_metrics(t, np.abs(v - 80.0) / 80.0, hold, 0.02)
    assert m["hold_max_dev_pct"] == pytest.approx(3.0)
    assert m["hold_max_dev_t_s"] == pytest.approx(0.3)
    assert m["hold_outside_band_s"] == pytest.approx(0.010)
    # the same excursion right after an event is forgiven for recover_s
    grace = M.band_must_hold(t, AcceptanceConfig(recover_s=0.05), [0.29])
    assert M.hold_metrics(t, np.abs(v - 80.0) / 80.0, grace, 0.02)["hold_outside_band_s"] == 0.0


def test_outside_time_weights_each_sample_by_its_step():
    tt = np.array([0.0, 0.1, 0.3, 0.6])
    out = np.array([False, True, True, True])
    assert M.outside_time(tt, out, np.ones(4, bool)) == pytest.approx(0.2 + 0.3 + 0.3)  # the last: its step before


def test_regulation_and_verdict():
    v = 80.0 + 4.0 * np.exp(-t / 0.01)  # 5 % at t = 0, inside +-2 % (1.6 V) from 0.01 ln(4 / 1.6) s on
    r = M.regulation(t, v, 80.0, 0.02)
    assert r["settle_s"] == pytest.approx(math.ceil(0.01 * math.log(4 / 1.6) / T) * T)
    assert r["v_max"] == 84.0 and r["v_min"] == pytest.approx(80.0)
    assert r["ss_error"] == pytest.approx(0.0, abs=1e-15)
    assert M.regulation(t[:0], v[:0], 80.0, 0.02) == {"settle_s": None, "v_min": None, "v_max": None,
                                                       "ss_error": None}
    acc = AcceptanceConfig()
    ok = {"diverged": False, "hold_outside_band_s": 0.0}
    assert M.verdict(ok, acc) == {"accepted": True, "failures": []}
    bad = {"diverged": False, "hold_outside_band_s": 0.01, "hold_max_dev_pct": 3.0, "hold_max_dev_t_s": 0.3}
    assert M.verdict(bad, acc)["failures"][0]["criterion"] == "band"
    assert M.verdict({"diverged": True, "diverged_at_s": 0.2}, acc)["failures"][0]["criterion"] == "divergence"


def test_compute_metrics_on_a_diverged_run_has_no_settle_time():
    tr = {"t": t, "v": np.full_like(t, 80.0), "y_z_true": np.zeros_like(t), "y_ref_true": np.zeros_like(t),
          "du_dt_applied": np.ones_like(t)}
    calm = M.compute_metrics(tr, 80.0, 1.0, None, 0)
    assert calm["settle_s"] == 0.0 and calm["accepted"] and calm["rms_du_dt"] == 1.0
    gone = M.compute_metrics(tr, 80.0, 1.0, (0.5, "v left"), 0)
    assert gone["settle_s"] is None and not gone["accepted"] and gone["diverged_at_s"] == 0.5
    assert list(gone) == list(calm)  # the same keys in the same order (the JSON a command prints)


def test_step_metrics_know_the_step():
    v = np.full_like(t, 80.0)
    v[(t >= 0.2) & (t < 0.23)] = 76.0  # 5 % for 30 ms after a step at 0.2 s
    m = M.step_metrics(t, v, 80.0, 0.2)
    assert m["peak_pct"] == pytest.approx(5.0) and m["back_s"] == pytest.approx(0.03)
    assert m["outside_s"] == pytest.approx(0.03) and m["steady_pct"] == 0.0 and m["before_pct"] == 0.0
    assert not m["diverged"]
    v[-1] = 50.0  # out at the end and beyond 25 %
    late = M.step_metrics(t, v, 80.0, 0.2)
    assert late["back_s"] is None and late["diverged"]


def test_smooth_is_a_moving_average_with_a_growing_head():
    x = np.arange(6, dtype=float)
    assert M.smooth(x, 3).tolist() == [0.0, 0.5, 1.0, 2.0, 3.0, 4.0]
    assert M.smooth(x, 1).tolist() == x.tolist()
    assert M.smooth(x, 100).tolist() == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]  # n capped at the length


def test_sharing_error_against_the_shares():
    P = {"A": np.array([200.0, 100.0, 0.0]), "B": np.array([100.0, 100.0, 0.0])}
    err = M.sharing_error_pp(P, ["A", "B"], {"A": 2.0, "B": 1.0})
    # 2:1 exact, then 50/50 against 66.7/33.3, then nothing delivered (a zero total counts as 1 W)
    assert err == pytest.approx([0.0, 100 * (2 / 3 - 0.5), 100 * 2 / 3])


def test_inrush_bus_move_and_steady_windows():
    i = np.zeros_like(t)
    i[(t >= 0.5) & (t < 0.52)] = -12.0
    i[t >= 0.6] = 30.0  # after the 50 ms window
    assert M.inrush_A(t, {"L": i, "M": np.zeros_like(t)}, ["L", "M"], 0.5) == 12.0
    assert M.inrush_A(t, {"L": i}, ["L"], 5.0) == 0.0
    v = np.full_like(t, 80.0)
    v[(t >= 0.5) & (t < 0.51)] = 78.5
    assert M.bus_move_V(t, {"bus": v}, 0.5)["bus"] == pytest.approx(1.5)
    assert M.bus_move_V(t, {"bus": v}, 0.0)["bus"] is None  # nothing before it
    w = M.steady_windows(t, [0.5], T)
    assert len(w) == 2
    assert t[w[0]][0] == pytest.approx(0.4) and t[w[0]][-1] == pytest.approx(0.499)
    assert t[w[1]][0] == pytest.approx(0.9) and t[w[1]][-1] == pytest.approx(0.999)
    assert len(M.steady_windows(t, [0.5, 0.52], T)) == 2  # 20 ms after an event is not steady


def _net_result(P1, P2, buses, events=()):
    """A hand-made NetworkResult: two sources with shares 2:1, one bus, one line from S2."""
    n = len(t)
    net = SimpleNamespace(
        acceptance=AcceptanceConfig(hold_from_s=0.2), nominal_v_V=80.0, timing=SimpleNamespace(control_rate_hz=1e3),
        layer=SimpleNamespace(idle_power_W=0.0),
        sources={"S1": SimpleNamespace(share=2.0), "S2": SimpleNamespace(share=1.0)},
        lines={"L2": SimpleNamespace(a="S2", b="bus")})
    sources = {s: {"v": np.full(n, 80.0), "P": P, "mode": np.zeros(n)} for s, P in (("S1", P1), ("S2", P2))}
    return SimpleNamespace(net=net, t=t, sources=sources, buses={"bus": buses}, lines={"L2": np.zeros(n)},
                           events=list(events), violations={})


def test_network_metrics_on_a_hand_made_run():
    P1, P2 = np.full_like(t, 1600.0), np.full_like(t, 800.0)
    bus = np.full_like(t, 80.0)
    bus[(t >= 0.5) & (t < 0.56)] = 77.0  # a load step at 0.5 s: 3.75 % down, back 60 ms later
    ev = SimpleNamespace(t=0.5, kind="load", target="P", accepted=True, reason="")
    m = M.network_metrics(_net_result(P1, P2, bus, [ev]), None, None)
    assert m["sources"]["S1"]["share_pct"] == pytest.approx(200 / 3)
    assert m["sources"]["S1"]["sharing_error_pp"] == pytest.approx(0.0, abs=1e-12)
    assert m["sources"]["S1"]["mode_switches"] is None  # a live rig's trace: the daemons know them
    e = m["events"][0]
    assert e["bus_back_in_band_s"]["bus"] == pytest.approx(0.06)
    assert e["bus_min_V"]["bus"] == 77.0
    assert e["sharing_in_band_s"] == 0.0
    assert m["hold_max_dev_pct"] == pytest.approx(3.75) and m["hold_max_dev_node"] == "bus"
    assert not m["accepted"] and m["failures"][0]["criterion"] == "band"
    # the sharing off by 100/3 pp: the steady error says so, and the sharing is never back in its band
    off = M.network_metrics(_net_result(np.full_like(t, 1200.0), np.full_like(t, 1200.0), bus, [ev]), None, None)
    assert off["sources"]["S2"]["sharing_error_pp"] == pytest.approx(100 * (0.5 - 1 / 3))
    assert off["events"][0]["sharing_in_band_s"] is None


def test_network_metrics_of_a_close_report_the_inrush_of_its_lines():
    res = _net_result(np.full_like(t, 1600.0), np.full_like(t, 800.0), np.full_like(t, 80.0),
                      [SimpleNamespace(t=0.5, kind="close", target="S2", accepted=True, reason="")])
    res.lines["L2"][(t >= 0.5) & (t < 0.502)] = 15.0
    e = M.network_metrics(res, None, None)["events"][0]
    assert e["inrush_A"] == 15.0 and e["bus_move_V"] == {"bus": 0.0}
