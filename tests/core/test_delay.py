"""The measured loop delay (service/core/delay.py): identified from u and the commands, in sim, a log and the daemon."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SCENARIOS

from schemas.scenario import load_scenario
from service.core.delay import estimate_loop_delay, on_seq_grid
from service.sim import run


@pytest.mark.parametrize("delay", [0, 1, 3, 5])
def test_delay_is_identified_from_the_measured_source_voltage(delay):
    """u_{k+1} - u_k = T r_{k-d}: the least-squares fit picks d through sensor noise (0.05 V on u)."""
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml", [f"timing.delay_samples={delay}",
                                                                "timing.duration_s=0.15"])
    tr = run(scn).trace
    est = estimate_loop_delay(tr["u_meas"][500:], tr["du_dt"][500:], 1.0 / scn.timing.control_rate_hz)
    assert est["samples"] == delay
    assert est["contrast"] > 0.5 and est["explained"] > 0.4


def test_a_wrong_compensation_is_seen_and_steady_commands_say_unknown():
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.delay_samples=3", "timing.duration_s=0.1",
                                                                "controller.delay_compensation_samples=2"])
    tr = run(scn).trace
    assert estimate_loop_delay(tr["u_meas"], tr["du_dt"], 1e-4)["samples"] == 3  # the plant's delay, not 2
    flat = np.full(800, 80.0) + 1e-3 * np.sin(np.arange(800))  # no command moves u: nothing to tell apart
    assert estimate_loop_delay(flat, np.zeros(800), 1e-4)["samples"] is None
    assert estimate_loop_delay(flat[:20], np.zeros(20), 1e-4)["samples"] is None  # too short


def test_missing_ticks_are_holes_not_shifts():
    """A sample the controller never answered: no Delta u there, and du/dt 0 (the plant held)."""
    rng = np.random.default_rng(1)
    r = rng.normal(0, 2000.0, 3000)
    u = 80.0 + np.concatenate(([0.0], np.cumsum(1e-4 * np.concatenate((np.zeros(2), r[:-3])))))[:3000]
    keep = rng.random(3000) > 0.3  # 30 % of ticks missing
    seq = np.arange(3000)[keep]
    ug, rg = on_seq_grid(seq, u[keep], r[keep])
    grid = np.arange(seq[0], seq[-1] + 1)
    assert len(ug) == len(grid) and np.isnan(ug[~keep[grid]]).all() and not np.isnan(ug[keep[grid]]).any()
    assert estimate_loop_delay(ug, rg, 1e-4)["samples"] == 2
    # dropping the holes instead (consecutive arrays) misaligns u and r: the fit no longer finds it
    assert estimate_loop_delay(u[keep], r[keep], 1e-4)["samples"] is None


def test_daemon_status_flags_a_delay_it_does_not_compensate(daemon_by_hand):
    """Driven by a stand-in plant with 3 samples of delay while the daemon compensates 1."""
    from schemas.codec import MEAS

    d = daemon_by_hand
    assert d.core.d == 1
    u, sent = 80.15, []
    for k in range(1500):
        d._tick(MEAS.encode(k, k * 1e-4, 15.0 + 0.2 * np.sin(k / 40), 80.0 + 0.1 * np.sin(k / 25), u, 15.0), 1)
        sent.append(d.last_cmd[2])
        u += 1e-4 * (sent[k - 3] if k >= 3 else 0.0)
    ld = d.status()["loop_delay"]
    assert ld["measured_samples"] == 3 and ld["compensated_samples"] == 1 and ld["mismatch"]
    assert ld["window"] == 1500
    # a status query soon after reuses the estimate (it costs the loop ~0.4 ms of GIL); after shutdown it is fresh
    assert d.status()["loop_delay"] is ld
    d.state = "shutdown"
    assert d.status()["loop_delay"] is not ld
