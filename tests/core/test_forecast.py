"""The outgoing range Z^{r,out}[k] forecast ahead of each window, and the feed-forward feasibility check
(paper Sec. "Feed-forward checking of feasibility conditions"; service/forecast.py)."""

from __future__ import annotations

import pytest
from conftest import SCENARIOS

from schemas.scenario import load_scenario
from service.core.control import effective_gain
from service.core.feasibility import announced_window, load_box, tau_prime
from service.forecast import forecast_outgoing, widen_to_grid
from service.plant.profiles import Profile
from service.sim import run

FEAS = SCENARIOS / "paper-feasibility.toml"
VARYING = SCENARIOS / "paper-varying-load.toml"
# noise-free and with the model equal to the plant: what the forecast assumes, so its envelope must hold
EXACT = ["sensor.noise_v_V=0.0", "sensor.noise_i_A=0.0", "model.R_ohm=0.01", "model.L_H=1.12e-3",
         "model.C_F=6.8e-3"]


def forecast_for(scn, k: int, **kw):
    W = scn.feasibility.window_s
    box = load_box(*Profile(scn.load).range_over(k * W, min((k + 1) * W, scn.timing.duration_s)),
                   scn.feasibility.forecast_margin)
    tp = tau_prime(scn.model.L_H, scn.model.R_ohm, effective_gain(scn.controller, scn.model))
    return box, forecast_outgoing(scn.controller, scn.model, 1.0 / scn.timing.control_rate_hz,
                                  scn.timing.delay_samples, box, tp, max_ramp_s=W, **kw)


def test_the_check_ahead_flags_the_proportional_controller_and_the_run_agrees():
    lqr = run(load_scenario(FEAS, ['controller.kind="lqr"']))
    fblc = run(load_scenario(FEAS))
    # ahead of window 0, before any sample: the proportional law's Qdot^{r,out} leaves Qdot^{r,in}
    assert not lqr.forecasts[0].feasible and lqr.forecasts[0].reason.startswith("Qdot^r,out")
    assert lqr.metrics["forecast_infeasible_windows"] == 2
    assert [v for v in lqr.violations if v.element == "Qdot"]  # and the run then leaves it (at ~0.35 s)
    # the energy controller passes ahead and at run time
    assert all(f.feasible for f in fblc.forecasts) and fblc.metrics["forecast_infeasible_windows"] == 0
    assert fblc.violations == []


def test_forecast_is_off_unless_asked():
    r = run(load_scenario(VARYING, ["timing.duration_s=0.01"]))
    assert r.forecasts == [] and r.metrics["forecast_infeasible_windows"] is None


@pytest.mark.parametrize(("path", "steps", "windows"), [(VARYING, False, [1, 2, 3]), (FEAS, True, [0, 1, 2, 3])])
def test_the_forecast_contains_the_outgoing_range_the_run_realises(path, steps, windows):
    """Exact model, no noise: each window's realised Z^{r,out} lies inside its forecast. (Window 0 of the
    varying load starts from 1 A, away from any equilibrium the forecast starts from.)"""
    scn = load_scenario(path, [*EXACT, "feasibility.window_s=0.25", "timing.duration_s=1.0"])
    res = run(scn)
    assert not res.metrics["diverged"]
    q_run = q_forecast = 0.0
    for w in res.windows:
        if w.k not in windows:
            continue
        box, f = forecast_for(scn, w.k, steps=steps)
        P_lo, P_hi, Q_lo, Q_hi = w.z_out
        assert (f.P_lo, f.P_hi, f.P_dot_lo, f.P_dot_hi) == (-box[1], -box[0], -box[3], -box[2])
        assert f.P_lo <= P_lo and P_hi <= f.P_hi, w.k
        assert f.Qdot_lo <= Q_lo and Q_hi <= f.Qdot_hi, (w.k, w.z_out, f.Qdot_lo, f.Qdot_hi)
        q_run, q_forecast = max(q_run, -Q_lo, Q_hi), max(q_forecast, -f.Qdot_lo, f.Qdot_hi)
    # and it is no blanket: the largest realised transient reaches a good part of the largest forecast one
    assert q_run > 0.5 * q_forecast, (q_run, q_forecast)


def test_a_forecast_that_ignores_the_load_steps_misses_the_realised_range():
    """The same check fails when the forecast leaves out what the load can do: the test can tell."""
    scn = load_scenario(FEAS, [*EXACT, "feasibility.window_s=0.25", "timing.duration_s=0.5"])
    w1 = next(w for w in run(scn).windows if w.k == 1)  # holds the step at 0.35 s
    _box, f = forecast_for(scn, 1, steps=False)
    assert not (f.Qdot_lo <= w1.z_out[2] and w1.z_out[3] <= f.Qdot_hi)


def test_local_saturation_makes_the_window_infeasible():
    scn = load_scenario(FEAS)
    # the source voltage needed at the top of the range, v_ref + R P/v_ref = 80.25 V, is beyond u_max
    _b, f = forecast_for(load_scenario(FEAS, ["controller.limits.u_max_V=80.2"]), 0)
    assert not f.feasible and f.reason.startswith("source voltage saturates") and f.saturation
    # a load step needs du/dt beyond a 1 kV/s slew limit for tens of milliseconds: the source cannot follow
    _b, f = forecast_for(load_scenario(FEAS, ["controller.limits.du_dt_max_V_per_s=1000.0"]), 0)
    assert not f.feasible and "du/dt at its limit for" in f.reason and f.limited_ticks > 0
    # the nested law rides the default slew limit for a few periods on the same steps: reported, still feasible
    _b, f = forecast_for(load_scenario(FEAS, ['controller.kind="nested"']), 0)
    assert f.feasible and 0 < f.limited_ticks * 1e-4 < 2e-3
    _b, f = forecast_for(scn, 0)
    assert f.feasible and f.saturation == "" and f.limited_ticks == 0


def test_a_widened_box_holds_the_box_and_nearby_boxes_share_it():
    box = (731.83, 1723.67, -22557.0, 20753.9)
    wide = widen_to_grid(box, 0.02)
    assert wide[0] <= box[0] and box[1] <= wide[1] and wide[2] <= box[2] and box[3] <= wide[3]
    assert wide[1] - box[1] < 0.02 * 2048 + 1e-9
    assert widen_to_grid((720.0, 1750.0, -22600.0, 20800.0), 0.02) == wide
    assert widen_to_grid((735.0, 1715.0, -22000.0, 20500.0), 0.02) != wide  # another cell: its own forecast


def test_each_window_is_announced_half_a_window_ahead():
    W = 0.25
    assert [announced_window(t, W) for t in (0.0, 0.1, 0.125, 0.2, 0.25, 0.37, 0.375)] == [0, 0, 1, 1, 1, 1, 2]


def test_the_daemons_forecast_worker_survives_its_process_being_killed():
    """A killed worker process is counted and named, and the next window is forecast by a new one."""
    import os
    import signal

    from clients.live import wait_until
    from schemas.scenario import OutgoingForecastConfig
    from service.daemon.forecast_worker import ForecastWorker

    scn = load_scenario(FEAS)
    fw = ForecastWorker(scn.model, 1e-4, 0, OutgoingForecastConfig(enabled=True), 1.0)
    fw.start()
    try:
        fw.request(0, (1100.0, 1300.0, 0.0, 0.0), scn.controller)
        assert wait_until(lambda: fw.result is not None and fw.result[0] == 0, 30.0)
        assert fw.result[1].feasible and fw.computed == 1
        for pid in list(fw._pool._processes):
            os.kill(pid, signal.SIGKILL)
        fw.request(1, (1000.0, 1400.0, 0.0, 0.0), scn.controller)
        assert wait_until(lambda: fw.errors == 1, 30.0) and "BrokenProcessPool" in fw.last_error
        fw.request(2, (1000.0, 1400.0, 0.0, 0.0), scn.controller)
        assert wait_until(lambda: fw.result[0] == 2, 60.0)
        assert fw.computed == 2 and fw.status()["window"] == 2
        fw.request(3, (1100.0, 1300.0, 0.0, 0.0), scn.controller)  # window 0's box again: from the cache
        assert wait_until(lambda: fw.result[0] == 3, 30.0) and fw.cache_hits == 1 and fw.computed == 2
    finally:
        fw.close()


@pytest.mark.parametrize("keep_recent", [None, 3])
def test_the_run_time_monitor_counts_every_excursion_and_a_daemon_keeps_only_the_newest(keep_recent):
    """Each excursion of P^{r,out} from the window's incoming range is counted; offline the first ones are kept, a
    long-running daemon (keep_recent) keeps only its newest few, so its memory stays flat."""
    from service.core.feasibility import FeasibilityMonitor

    mon = FeasibilityMonitor(1.0, keep_recent=keep_recent)
    mon.set_range(0, (-100.0, 100.0, -1e3, 1e3))
    for j in range(5):  # out, back in: five separate excursions
        mon.update(0.1 * j, 500.0, 0.0)
        mon.update(0.1 * j + 0.05, 0.0, 0.0)
    assert mon.count == 5
    starts = [0.1 * j for j in range(5)]
    assert [v.t for v in mon.violations] == (starts if keep_recent is None else starts[2:])
