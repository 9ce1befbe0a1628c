"""Offline closed loop: plant + sensor + loop delay + the control core, as fast as the machine allows.

One control period per iteration: measure -> core.step -> delay line -> plant.advance. The
neighbour's incoming interaction variable is formed from the load profile exactly as the daemon
forms it from the neighbour's messages (P^{r,in} = -P_l, dP^{r,in}/dt = -dP_l/dt).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from schemas.scenario import AcceptanceConfig, Scenario, ScenarioError
from service.core import effective_gain, make_core
from service.core.feasibility import FeasibilityMonitor, Violation, incoming_range, load_box, tau_prime
from service.core.types import Incoming
from service.forecast import OutgoingForecast, forecast_outgoing
from service.plant.profiles import Profile
from service.plant.rlc import CommandChannel, CommandSchedule, RLCPlant, Sensor, load_current

ACCEPTANCE = AcceptanceConfig()  # the default criteria (a scenario's [acceptance] sets its own)
BAND_SETTLE = ACCEPTANCE.band_pct / 100  # +-2 % of v_ref
HOLD_FROM_S = ACCEPTANCE.hold_from_s  # "holds" metric looks at t >= this
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


def substeps(period_s: float, plant_step_s: float) -> int:
    return max(1, math.ceil(period_s / plant_step_s - 1e-9))


def run(scn: Scenario, stop_on_divergence: bool = True, impl: str | None = None) -> SimResult:
    """Closed loop offline. impl: the core implementation (core.make_core; default: compiled if built)."""
    tm = scn.timing
    T = 1.0 / tm.control_rate_hz
    n_sub = substeps(T, tm.plant_step_s)
    N = int(round(tm.duration_s / T))
    check_trace_size(N, len(TRACE_FIELDS), scn.name)
    load = Profile(scn.load, scn.base_dir)
    dist = Profile(scn.disturbance, scn.base_dir) if scn.disturbance is not None else None
    plant = RLCPlant(scn.plant, load, dist, impl or "auto")
    sensor = Sensor(scn.sensor, scn.seed)
    core = make_core(scn.controller, scn.model, T, tm.delay_samples, impl)
    delay: deque[tuple[float, float]] = deque([(0.0, 0.0)] * tm.delay_samples)
    sched = CommandSchedule(0)  # after the delay line, as the lockstep HIL plant: a lost command never arrives
    channel = CommandChannel(tm, [scn.seed])  # loss, lateness, outages on the way to the plant

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
        P_l = load.value(t)
        i2 = load_current(P_l, plant.v, plant.v_min)
        s = sensor.measure(k, t, plant.i, plant.v, plant.u, i2)
        inc.P_r_in = -P_l
        inc.P_r_in_dot = -load.rate(t)
        out = core.step(s, inc)
        if tm.delay_samples:
            delay.append((out.du_dt, out.du_dt_next))
            cmd = delay.popleft()
        else:
            cmd = (out.du_dt, out.du_dt_next)
        r_apply = channel.deliver(sched, k, t, cmd)
        est = out.est
        if t >= t_warm:
            feas.update(t, est.P_r_out_port, est.Qdot_r_out_port)
        um = plant.u_m(t)
        pi, pv, pu = plant.i, plant.v, plant.u
        row((t, pi, pv, pu, i2, P_l, s.i, s.v, s.u, s.i_load, out.du_dt, out.du_dt_next, r_apply, out.u_z,
             R_true * pi * pi - (pu + um) * pi, y_ref_of(-P_l, pv), out.y_z, out.y_ref,
             est.E, est.E_t, est.p, est.y_z_balance, est.eta, est.P_r_out_port, est.Qdot_r_out_port,
             out.z_out0, out.z_out1, inc.P_r_in, inc.P_r_in_dot))
        plant.advance(r_apply, T, n_sub)
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


def outside_time(t: np.ndarray, outside: np.ndarray, keep: np.ndarray) -> float:
    """Time (s) over the samples in ``keep`` that are ``outside``: each counts until the next sample (the last one
    for as long as the step before it)."""
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2] if len(t) > 1 else 0.0))
    return float(dt[outside & keep].sum())


def settle_time(t: np.ndarray, err: np.ndarray, bound: float, t0: float = 0.0) -> float | None:
    """Seconds from t0 until err stays at or below bound to the end of t (None: not by then): settle_s, a network's
    back-in-band times, the report's and the recovery bench's."""
    if len(t) == 0:
        return None
    above = np.nonzero(err > bound)[0]
    if len(above) == 0:
        return 0.0
    if above[-1] == len(t) - 1:
        return None
    return float(t[above[-1] + 1] - t0)


def band_must_hold(t: np.ndarray, acc: AcceptanceConfig, events: Iterable[float] = ()) -> np.ndarray:
    """The samples where the band must hold: from acc.hold_from_s on (HOLD_FROM_S when the band is not required,
    for the hold_* metrics), except acc.recover_s after each event time (s)."""
    hold = t >= (acc.hold_from_s if acc.hold_from_s is not None else HOLD_FROM_S)
    if acc.recover_s > 0.0:
        for e in events:
            hold &= ~((t >= e) & (t < e + acc.recover_s))
    return hold


def hold_metrics(t: np.ndarray, dev: np.ndarray, hold: np.ndarray, band: float, rows: list[str] | None = None) -> dict:
    """Over the samples in ``hold`` of the relative deviations ``dev`` (|v - ref| / ref; or one row per node, named
    by ``rows``, where the worst node counts at each sample): the largest deviation (%), when it happened (s), and
    the time outside +-band (s; one excursion in a 10-minute run fails the band as much as a run that never
    settles); with rows, also which node deviated most (hold_max_dev_node)."""
    m: dict = {"hold_max_dev_pct": None, "hold_max_dev_t_s": None, "hold_outside_band_s": None}
    if rows is not None:
        m["hold_max_dev_node"] = None
    if not hold.any() or dev.size == 0:
        return m
    worst = dev.max(axis=0) if rows is not None else dev
    k = int(np.argmax(np.where(hold, worst, -np.inf)))
    m.update(hold_max_dev_pct=float(worst[k] * 100), hold_max_dev_t_s=float(t[k]),
             hold_outside_band_s=outside_time(t, worst > band, hold))
    if rows is not None:
        m["hold_max_dev_node"] = rows[int(np.argmax(dev[:, k]))]
    return m


def trace_divergence(t: np.ndarray, v: np.ndarray, v_ref: float, acc: AcceptanceConfig) -> tuple[float, str] | None:
    """(t, why) at the first sample of a trace whose v is further than acc.diverge_dev_pct from v_ref (or not
    finite); None if there is none."""
    bad = np.nonzero(~(np.abs(v - v_ref) <= acc.diverge_dev_pct / 100 * v_ref))[0]
    return (float(t[bad[0]]), divergence_why(float(v[bad[0]]), 0.0, v_ref, acc)) if len(bad) else None


def compute_metrics(tr: dict[str, np.ndarray], v_ref: float, duration_s: float,
                    diverged: bool | tuple[float, str] | None, n_violations: int, acc: AcceptanceConfig = ACCEPTANCE,
                    events: Iterable[float] = ()) -> dict:
    """The run's metrics (energyctl sim --help says what each is) and its acceptance verdict (``verdict``); the
    band (acc.band_pct) and where it must hold (band_must_hold over the profiles' event times, s) are the
    scenario's acceptance criteria. diverged: (t, why) when and why the run diverged (or a bare True), else None
    or False."""
    at, why = diverged if isinstance(diverged, tuple) else (None, "diverged" if diverged else None)
    t, v = tr["t"], tr["v"]
    band = acc.band_pct / 100
    dev = np.abs(v - v_ref)
    settle = None if diverged else settle_time(t, dev, band * v_ref)  # None: still outside at the end
    n = len(t)
    tail = slice(int(n * 0.9), n) if n else slice(0, 0)
    err = tr["y_z_true"] - tr["y_ref_true"]
    m = {
        "settle_s": settle,
        "v_min": float(v.min()) if n else None,
        "v_max": float(v.max()) if n else None,
        "ss_error": float(dev[tail].mean()) if n else None,
        # where the band must hold: the largest deviation, when, and the time spent outside the band
        **hold_metrics(t, dev / v_ref, band_must_hold(t, acc, events), band),
        "rms_du_dt": float(np.sqrt(np.mean(tr["du_dt_applied"] ** 2))) if n else None,
        "max_abs_du_dt": float(np.abs(tr["du_dt_applied"]).max()) if n else None,
        "rms_tracking_error": float(np.sqrt(np.mean(err ** 2))) if n else None,
        "feasibility_violations": int(n_violations),
        "diverged": bool(diverged),
        "diverged_at_s": at,
        "diverged_why": why,
        "t_end": float(t[-1]) if n else 0.0,
        "duration_s": duration_s,
    }
    m.update(verdict(m, acc))
    return m


def verdict(m: dict, acc: AcceptanceConfig) -> dict:
    """The acceptance verdict on a run's metrics (a one-source run's or a network's): {"accepted": bool,
    "failures": [{"criterion": "divergence" | "band", "detail": what failed, in words}]}. A diverged run fails on
    divergence alone (it stopped there); the band is judged where it must hold (hold_outside_band_s), not at all
    when acc.hold_from_s is unset or the run ended before it."""
    failures = []
    if m["diverged"]:
        at = m.get("diverged_at_s")
        failures.append({"criterion": "divergence", "detail": (m.get("diverged_why") or "diverged") + (
            f" at t = {at:.4f} s" if at is not None else "")})
    elif acc.hold_from_s is not None and m.get("hold_outside_band_s") is not None and \
            m["hold_outside_band_s"] > acc.max_outside_band_s:
        where = m.get("hold_max_dev_node") or "v"
        grace = f", except {acc.recover_s * 1e3:g} ms after each event" if acc.recover_s > 0 else ""
        failures.append({"criterion": "band", "detail": (
            f"{where} outside +-{acc.band_pct:g} % for {m['hold_outside_band_s'] * 1e3:.1f} ms from "
            f"{acc.hold_from_s:g} s on{grace} (allowed {acc.max_outside_band_s * 1e3:g} ms); largest deviation "
            f"{m['hold_max_dev_pct']:.2f} % at t = {m['hold_max_dev_t_s']:.4f} s")})
    return {"accepted": not failures, "failures": failures}
