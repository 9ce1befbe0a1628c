"""Offline closed loop: plant + sensor + loop delay + the control core, as fast as the machine allows.

One control period per iteration: measure -> core.step -> delay line -> plant.advance. The
neighbour's incoming interaction variable is formed from the load profile exactly as the daemon
forms it from the neighbour's messages (P^{r,in} = -P_l, dP^{r,in}/dt = -dP_l/dt).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from schemas.scenario import AcceptanceConfig, Scenario, ScenarioError
from service.core import effective_gain, make_core
from service.core.feasibility import FeasibilityMonitor, Violation, incoming_range, load_box, tau_prime
from service.core.types import Incoming
from service.forecast import OutgoingForecast, forecast_outgoing
from service.metrics import compute_metrics
from service.plant.profiles import Profile
from service.plant.rig import RigModel

I_DIVERGED_A = 1e4  # a source current beyond this (A) is a divergence whatever v does

TRACE_FIELDS = (
    "t", "i", "v", "u", "i_load", "P_l",  # true plant state at the sample instant
    "i_meas", "v_meas", "u_meas", "i_load_meas",  # what the controller saw
    "du_dt", "du_dt_next", "du_dt_applied", "u_z", "y_z_true", "y_ref_true", "y_z", "y_ref",
    "E", "E_t", "p", "y_z_balance", "eta", "P_r_out", "Qdot_r_out", "z_out0", "z_out1",
    "P_r_in", "P_r_in_dot",  # what the core was given (replay input)
)


MAX_TRACE_BYTES = 1 << 30  # what a run's trace may hold (float64 columns): 1 GiB
CHUNK = 8192  # samples collected as Python tuples before they go into the trace's columns


def check_trace_size(samples: int, columns: int, what: str = "scenario") -> None:
    """A ScenarioError when a run of that many samples of that many columns would hold more than MAX_TRACE_BYTES:
    refused before it starts rather than ending in a MemoryError (3600 s at 100 kHz grew ~230 MB/s)."""
    need = samples * columns * 8
    if need > MAX_TRACE_BYTES:
        most = MAX_TRACE_BYTES // (columns * 8)
        raise ScenarioError(f"{what}: timing.duration_s x timing.control_rate_hz = {samples:,} samples of {columns} "
                            f"values would hold {need / 2**30:.1f} GiB, over the {MAX_TRACE_BYTES >> 30} GiB a run's "
                            f"trace may (at most {most:,} samples): shorten duration_s or lower control_rate_hz")


@dataclass
class SimResult:
    scenario: Scenario
    trace: dict[str, np.ndarray]
    metrics: dict
    violations: list[Violation] = field(default_factory=list)
    windows: list = field(default_factory=list)
    delay_compensation: int = 0
    forecasts: list[OutgoingForecast] = field(default_factory=list)  # per window, when feasibility.forecast is on


def run(scn: Scenario, stop_on_divergence: bool = True, impl: str | None = None) -> SimResult:
    """Closed loop offline. impl: the core implementation (core.make_core; default: compiled if built)."""
    tm = scn.timing
    T = 1.0 / tm.control_rate_hz
    N = int(round(tm.duration_s / T))
    check_trace_size(N, len(TRACE_FIELDS), scn.name)
    # the plant side (plant, load, sensor, loop delay, command loss/lateness/outages, schedule) as the lockstep
    # stand-in runs it
    rig = RigModel.of_scenario(scn, impl or "auto")
    plant, load, dist = rig.plant, rig.load, rig.dist
    sample, command, advance = rig.sample, rig.path.command, rig.advance
    core = make_core(scn.controller, scn.model, T, tm.delay_samples, impl)

    feas = FeasibilityMonitor(scn.feasibility.window_s)
    tp = tau_prime(scn.model.L_H, scn.model.R_ohm, effective_gain(scn.controller, scn.model))
    fs = scn.feasibility
    n_win = max(1, math.ceil(tm.duration_s / fs.window_s - 1e-9))
    forecasts: list[OutgoingForecast] = []
    for k in range(n_win):
        t0 = k * fs.window_s
        box = load_box(*load.range_over(t0, min(t0 + fs.window_s, tm.duration_s)), fs.forecast_margin)
        feas.set_range(k, incoming_range(*box, tp, fs.literal_paper_range))
        if fs.forecast.enabled:  # the feed-forward check, before the window runs
            forecasts.append(forecast_outgoing(scn.controller, scn.model, T, tm.delay_samples, box, tp,
                                               steps=fs.forecast.load_steps, settle_s=fs.forecast.settle_s,
                                               max_ramp_s=fs.window_s, literal=fs.literal_paper_range, impl=impl))

    t_warm = 5.0 * scn.controller.deriv_tau_s  # derivative estimates need ~5 tau of history
    y_ref_of = core.y_ref_of  # the controller's own reference map, evaluated on the true state
    cols = np.empty((len(TRACE_FIELDS), N))  # pages are taken as they are written: a diverged run's stay free
    done = 0  # samples moved into cols
    rows: list[tuple] = []
    row = rows.append
    R_true, v_ref = scn.plant.R_ohm, scn.controller.v_ref_V
    acc = scn.acceptance
    dev_max = acc.diverge_dev_pct / 100 * v_ref  # leaving v_ref +- this counts as divergence
    inc = Incoming(0.0, 0.0)
    diverged = None  # (t, why) once it diverged
    for k in range(N):
        t = plant.t
        s = sample(k)
        P_l, i2 = rig.P_l, rig.i_load
        inc.P_r_in = -P_l
        inc.P_r_in_dot = -load.rate(t)
        out = core.step(s, inc)
        r_apply = command(k, t, out.du_dt, out.du_dt_next)
        est = out.est
        if t >= t_warm:
            feas.update(t, est.P_r_out_port, est.Qdot_r_out_port)
        um = plant.u_m(t)
        pi, pv, pu = plant.i, plant.v, plant.u
        row((t, pi, pv, pu, i2, P_l, s.i, s.v, s.u, s.i_load, out.du_dt, out.du_dt_next, r_apply, out.u_z,
             R_true * pi * pi - (pu + um) * pi, y_ref_of(-P_l, pv), out.y_z, out.y_ref,
             est.E, est.E_t, est.p, est.y_z_balance, est.eta, est.P_r_out_port, est.Qdot_r_out_port,
             out.z_out0, out.z_out1, inc.P_r_in, inc.P_r_in_dot))
        advance()
        if len(rows) == CHUNK:
            cols[:, done:done + CHUNK] = np.asarray(rows, dtype=float).T
            done += CHUNK
            rows.clear()
        if diverged is None and (not abs(plant.v - v_ref) <= dev_max or not abs(plant.i) <= I_DIVERGED_A):
            diverged = (plant.t, divergence_why(plant.v, plant.i, v_ref, acc))
            if stop_on_divergence:
                break
    if rows:
        cols[:, done:done + len(rows)] = np.asarray(rows, dtype=float).T
        done += len(rows)
    trace = {f: cols[k, :done] for k, f in enumerate(TRACE_FIELDS)}  # each a contiguous row of cols
    metrics = compute_metrics(trace, v_ref, tm.duration_s, diverged, feas.count, acc, profile_events(load, dist))
    metrics["forecast_infeasible_windows"] = (sum(not f.feasible for f in forecasts) if fs.forecast.enabled
                                              else None)
    return SimResult(scn, trace, metrics, feas.violations, list(feas.windows.values()), core.d, forecasts)


def profile_events(load: Profile, dist: Profile | None) -> list[float]:
    """When the load or the disturbance jumps (s): the events acceptance.recover_s counts from."""
    return sorted({*load.event_times(), *(dist.event_times() if dist is not None else ())})


def divergence_why(v: float, i: float, v_ref: float, acc: AcceptanceConfig, node: str = "v") -> str:
    """Why a state counts as diverged (AcceptanceConfig.diverge_dev_pct, I_DIVERGED_A), in words."""
    if not (math.isfinite(v) and math.isfinite(i)):
        return "the state is not finite"
    if abs(i) > I_DIVERGED_A:
        return f"|i| = {abs(i):.4g} A, beyond {I_DIVERGED_A:g} A"
    return f"{node} = {v:.2f} V, outside +-{acc.diverge_dev_pct:g} % of {v_ref:g} V"


def trace_divergence(t: np.ndarray, v: np.ndarray, v_ref: float, acc: AcceptanceConfig) -> tuple[float, str] | None:
    """(t, why) at the first sample of a trace whose v is further than acc.diverge_dev_pct from v_ref (or not
    finite); None if there is none."""
    bad = np.nonzero(~(np.abs(v - v_ref) <= acc.diverge_dev_pct / 100 * v_ref))[0]
    return (float(t[bad[0]]), divergence_why(float(v[bad[0]]), 0.0, v_ref, acc)) if len(bad) else None
