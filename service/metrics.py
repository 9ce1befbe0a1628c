"""Run metrics: the one home of settle time, the band and back-in-band, hold metrics, inrush, sharing error and
smoothing, for the offline drivers (service.sim, service.network.netsim), the stand-ins' results, the report and
the benches. Pure: numpy over traces, no clocks, no I/O.

Conventions: t (s) is a trace's sample times, increasing; a band is relative (0.02 = +-2 %); a time "back in the band"
or "settled" counts from a start time t0 to the first sample after the last one outside, and is None when the last
sample is still outside (not by the end of what was looked at). The acceptance verdict on a run (``verdict``) is here
too: it reads these metrics.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from schemas.scenario import AcceptanceConfig
from service.core.source import FALLBACK, MODES

ACCEPTANCE = AcceptanceConfig()  # the default criteria (a scenario's [acceptance] sets its own)
BAND_SETTLE = ACCEPTANCE.band_pct / 100  # +-2 % of v_ref
HOLD_FROM_S = ACCEPTANCE.hold_from_s  # "holds" metric looks at t >= this

CARRY_MIN_W = 1.0  # a source carries load in the metrics from this |power| (W; and the idle power): a tripped one has 0
SHARE_BAND_PP = 2.0  # sharing counts as reached within this many percentage points of the configured shares
SHARE_SMOOTH_S = 0.005  # over powers averaged over this long (s)
SETTLED_S = 0.05  # a network's state "where it settles" before an event: the mean over this long before it (s)
INRUSH_S = 0.05  # a close's inrush: peak |i| of its lines over this long after it (s)
NEAR_S = 0.01  # a close's bus move: from the buses' mean over this long before it (s)
STEADY_S, STEADY_AFTER_S = 0.1, 0.05  # a network's steady state: this long before each event, this long after one


# ---------------------------------------------------------------- settle, band, back in band

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


def back_in_band(t: np.ndarray, v: np.ndarray, t0: float, t1: float, target: float, band: float) -> float | None:
    """Seconds from t0 until v stays within +-band x |target| for the rest of [t0, t1) (None: not by t1; t1 = inf:
    to the end of the trace)."""
    sel = (t >= t0) & (t < t1)
    return settle_time(t[sel], np.abs(v[sel] - target), band * abs(target), t0)


def worst_back(backs: Iterable[float | None]) -> float | None:
    """The slowest of several back-in-band times (s): None if any never came back, 0.0 for none at all."""
    backs = list(backs)
    return None if None in backs else max(backs, default=0.0)


def max_dev_pct(t: np.ndarray, v: np.ndarray, t0: float, t1: float, ref: float) -> float | None:
    """The largest |v - ref| / ref over [t0, t1) (%; None: no sample there)."""
    sel = (t >= t0) & (t < t1)
    return float(np.max(np.abs(v[sel] - ref)) / ref * 100) if np.any(sel) else None


def outside_time(t: np.ndarray, outside: np.ndarray, keep: np.ndarray) -> float:
    """Time (s) over the samples in ``keep`` that are ``outside``: each counts until the next sample (the last one
    for as long as the step before it)."""
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2] if len(t) > 1 else 0.0))
    return float(dt[outside & keep].sum())


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


def regulation(t: np.ndarray, v: np.ndarray, v_ref: float, band: float) -> dict:
    """One source's regulation over a trace: settle_s (from 0 until v stays within +-band x v_ref; None: not by
    the end), v_min / v_max (V) and ss_error (mean |v - v_ref| over the last 10 % of the samples, V); None each
    for an empty trace."""
    n = len(t)
    dev = np.abs(v - v_ref)
    tail = slice(int(n * 0.9), n) if n else slice(0, 0)
    return {"settle_s": settle_time(t, dev, band * v_ref),
            "v_min": float(v.min()) if n else None,
            "v_max": float(v.max()) if n else None,
            "ss_error": float(dev[tail].mean()) if n else None}


def rms(x: np.ndarray) -> float:
    """sqrt(mean(x^2))."""
    return float(np.sqrt(np.mean(x ** 2)))


def max_abs(x: np.ndarray) -> float:
    return float(np.abs(x).max())


def step_metrics(t: np.ndarray, v: np.ndarray, v_ref: float, t_step: float, band: float = BAND_SETTLE,
                 diverge: float = 0.25, tail_s: float = 0.05) -> dict:
    """A load step's metrics (the envelope's): peak deviation (%), time outside +-band (s, samples x the first
    step) and back in it for good (s after the step; None: not by the end) after t_step, steady deviation over the
    last tail_s (%), the largest deviation before the step (over 100 ms, %), and whether v left +-diverge."""
    dev = np.abs(v - v_ref) / v_ref
    after = t >= t_step
    outside = dev > band
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    before = (t >= t_step - 0.1) & ~after
    return {"diverged": bool(np.any(dev >= diverge)) or len(t) == 0,
            "peak_pct": float(dev[after].max() * 100) if after.any() else None,
            "outside_s": float(np.count_nonzero(outside & after) * dt),
            "back_s": settle_time(t[after], dev[after], band, t_step) if after.any() else 0.0,
            "steady_pct": float(dev[t >= t[-1] - tail_s].max() * 100) if len(t) else None,
            "before_pct": float(dev[before].max() * 100) if before.any() else None}


def smooth(x: np.ndarray, n: int) -> np.ndarray:
    """Moving average over n samples (the first n - 1 over what there is)."""
    n = max(1, min(n, len(x)))
    c = np.cumsum(np.insert(x, 0, 0.0))
    out = (c[n:] - c[:-n]) / n
    head = c[1:n] / np.arange(1, n)
    return np.concatenate([head, out])[:len(x)]


# ---------------------------------------------------------------- one source's run

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
    n = len(t)
    err = tr["y_z_true"] - tr["y_ref_true"]
    m = {
        **regulation(t, v, v_ref, band),
        # where the band must hold: the largest deviation, when, and the time spent outside the band
        **hold_metrics(t, np.abs(v - v_ref) / v_ref, band_must_hold(t, acc, events), band),
        "rms_du_dt": rms(tr["du_dt_applied"]) if n else None,
        "max_abs_du_dt": max_abs(tr["du_dt_applied"]) if n else None,
        "rms_tracking_error": rms(err) if n else None,
        "feasibility_violations": int(n_violations),
        "diverged": bool(diverged),
        "diverged_at_s": at,
        "diverged_why": why,
        "t_end": float(t[-1]) if n else 0.0,
        "duration_s": duration_s,
    }
    if diverged:
        m["settle_s"] = None  # it stopped there
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


# ---------------------------------------------------------------- a network's run

def sharing_error_pp(P: dict[str, np.ndarray], on: list[str], shares: dict[str, float]) -> np.ndarray:
    """At each sample, the largest |part of the total - configured share| (percentage points) among the sources
    ``on``: part_s = P_s / sum_k P_k (a zero total counts as 1 W), share_s = shares_s / sum_k shares_k."""
    tot = sum(P[s] for s in on)
    w = sum(shares[s] for s in on)
    return np.max([np.abs(100.0 * (P[s] / np.where(tot == 0, 1.0, tot) - shares[s] / w)) for s in on], axis=0)


def inrush_A(t: np.ndarray, lines: dict[str, np.ndarray], names: list[str], t0: float) -> float:
    """The peak |i| (A) of the named lines over INRUSH_S from t0 (0.0: no sample there)."""
    after = (t >= t0) & (t < t0 + INRUSH_S)
    return max(float(np.max(np.abs(lines[ln][after]))) if after.any() else 0.0 for ln in names)


def bus_move_V(t: np.ndarray, buses: dict[str, np.ndarray], t0: float) -> dict[str, float | None]:
    """Per bus, the largest |v - its mean over NEAR_S before t0| over INRUSH_S from t0 (V; None: no samples)."""
    after = (t >= t0) & (t < t0 + INRUSH_S)
    near = (t >= t0 - NEAR_S) & (t < t0)
    return {b: float(np.max(np.abs(v[after] - np.mean(v[near])))) if after.any() and near.any() else None
            for b, v in buses.items()}


def steady_windows(t: np.ndarray, event_times: Iterable[float], T: float) -> list[np.ndarray]:
    """The steady states of a run: the STEADY_S before each event and before the end, where at least
    STEADY_AFTER_S passed since the event before (masks over t; the empty ones left out)."""
    n = len(t)
    marks = sorted(set(event_times) | {float(t[-1]) + T if n else 0.0})
    steady = [(t >= b - STEADY_S) & (t < b) & (t >= a + STEADY_AFTER_S)
              for a, b in zip([0.0, *marks], marks, strict=False)]
    return [s for s in steady if s.any()]


def _source_metrics(res, s: str, tail: np.ndarray, steady_P: dict, carrying: list[str], total_P: float,
                    total_share: float, ctl, v_nom: float, T: float) -> dict:
    """One source's row of network_metrics (see there)."""
    row = res.sources[s]
    v = row["v"]
    t = res.t
    n = len(t)
    share = res.net.sources[s].share
    on = s in carrying
    fb = row["mode"] == FALLBACK if "mode" in row else None
    return {
        "v_min": float(v.min()) if n else None, "v_max": float(v.max()) if n else None,
        "P_steady_W": steady_P[s],
        "share_pct": 100.0 * steady_P[s] / total_P if on else 0.0,
        "share_target_pct": 100.0 * share / total_share if on else 0.0,
        "sharing_error_pp": 100.0 * (steady_P[s] / total_P - share / total_share) if on else None,
        "terminal_dev_pct": float(np.max(np.abs(v[tail] - v_nom)) / v_nom * 100) if n else None,
        # (a live rig's trace has no modes: the daemons know them)
        "mode_switches": ctl.switches if ctl is not None else None,
        "fallback_s": float(np.count_nonzero(fb) * T) if fb is not None else None,
        "first_fallback_t_s": float(t[np.argmax(fb)]) if fb is not None and fb.any() else None,
        "final_mode": MODES[int(row["mode"][-1])] if n and fb is not None else None,
        # null where the run cannot know them: a live rig's trace (the daemons' monitors count them, in status)
        "feasibility_violations": res.violations.get(s, 0) if ctl is not None else None,
    }


def _event_metrics(res, ev, t1: float, band: float, carry_W: float, P_s: dict, terminal_dev: dict) -> dict:
    """One event's entry of network_metrics (see there); t1: when the next event comes (or the end)."""
    net, t = res.net, res.t
    v_nom = net.nominal_v_V
    names = list(net.sources)
    settled = (t >= t1 - SETTLED_S) & (t < t1)
    window = (t >= ev.t) & (t < t1)
    # the sources that carry load when things settle (an idle one waiting to connect follows the buses, window by
    # window)
    on = [s for s in names if settled.any() and abs(float(np.mean(res.sources[s]["P"][settled]))) >= carry_W]
    e = {"t_s": ev.t, "kind": ev.kind, "target": ev.target, "accepted": ev.accepted, "reason": ev.reason,
         "bus_back_in_band_s": {b: back_in_band(t, v, ev.t, t1, v_nom, band) for b, v in res.buses.items()},
         "bus_min_V": {b: float(v[window].min()) if window.any() else None for b, v in res.buses.items()},
         "terminals_back_in_band_s": {
             s: back_in_band(t, res.sources[s]["v"], ev.t, t1, float(np.mean(res.sources[s]["v"][settled])), band)
             for s in on},
         "terminals_near_v_ref_s": {s: settle_time(t[window], terminal_dev[s][window], band, ev.t) for s in names}}
    if len(t) and settled.any() and len(on) > 1:
        err = sharing_error_pp(P_s, on, {s: net.sources[s].share for s in on})
        sel = (t >= ev.t) & (t < t1)
        e["sharing_in_band_s"] = settle_time(t[sel], err[sel], SHARE_BAND_PP, ev.t)
    if ev.kind in ("close", "connect") and ev.accepted:
        lines = [ev.target] if ev.target in net.lines else [
            ln for ln, c in net.lines.items() if ev.target in (c.a, c.b)]
        e["inrush_A"] = inrush_A(t, res.lines, lines, ev.t)
        e["bus_move_V"] = bus_move_V(t, res.buses, ev.t)
    return e


def network_metrics(res, diverged_at: float | None, ctls, unsupplied: dict | None = None,
                    diverged_why: str | None = None) -> dict:
    """Per source and for the network: bands, sharing, recovery after each event, inrush, feasibility, and the
    acceptance verdict (``verdict`` on the scenario's acceptance criteria). res: a NetworkResult
    (service.network.netsim; net, t, sources, buses, lines, events, violations); ctls: the sources' controllers
    (for mode_switches; None for a live rig's trace).

    The band is the scenario's acceptance.band_pct (+-2 % by default). After each event (a breaker, a connect
    request, a load step or switch): the time until every bus is back within the band around nominal; until each
    terminal is back within the band around where it settles (its mean over the last 50 ms before the next event:
    a terminal moves to share the load, the buses are held at nominal, not the terminals), and until it is within
    the band around its own v_ref; until the sharing stays within SHARE_BAND_PP of the configured shares; and at a
    close its line's inrush (peak |i| in 50 ms) and how far each bus moved. hold_*: the buses where the band must
    hold (from acceptance.hold_from_s on, except acceptance.recover_s after each event), the worst bus at each
    sample. unsupplied: bus -> the first time no source reached it (NetworkRigModel.diverged), reported as
    ``unsupplied_s``; diverged_why: what diverged (NetworkRigModel.why)."""
    net, t = res.net, res.t
    acc = net.acceptance
    band = acc.band_pct / 100
    v_nom = net.nominal_v_V
    n = len(t)
    T = 1.0 / net.timing.control_rate_hz
    carry_W = max(net.layer.idle_power_W, CARRY_MIN_W)
    tail, steady_P, carrying, total_P, total_share = _steady_sharing(res, carry_W)
    m: dict = {"diverged": diverged_at is not None, "diverged_at_s": diverged_at, "diverged_why": diverged_why,
               "t_end": float(t[-1]) if n else 0.0, "unsupplied_s": dict(unsupplied or {}),
               **hold_metrics(t, np.array([np.abs(v - v_nom) / v_nom for v in res.buses.values()])
                              .reshape(len(res.buses), n),
                              band_must_hold(t, acc, [e.t for e in res.events]), band, list(res.buses)),
               "sources": {s: _source_metrics(res, s, tail, steady_P, carrying, total_P, total_share,
                                              ctls[j] if ctls else None, v_nom, T) for j, s in enumerate(net.sources)},
               "buses": _bus_metrics(res, T),
               "events": _events_metrics(res, band, carry_W, T)}
    m.update(verdict(m, acc))
    return m


def _steady_sharing(res, carry_W: float) -> tuple:
    """Over the last 10 % of the run: (that mask, each source's mean power W, the sources carrying at least
    carry_W, their total power W and total share (1 where none))."""
    t, n = res.t, len(res.t)
    tail = t >= (t[-1] - 0.1 * (t[-1] - t[0]) if n else 0.0)
    steady_P = {s: float(np.mean(res.sources[s]["P"][tail])) if n else 0.0 for s in res.net.sources}
    carrying = [s for s in res.net.sources if abs(steady_P[s]) >= carry_W]
    total_P = sum(steady_P[s] for s in carrying) or 1.0
    total_share = sum(res.net.sources[s].share for s in carrying) or 1.0
    return tail, steady_P, carrying, total_P, total_share


def _bus_metrics(res, T: float) -> dict:
    """Per bus: its lowest and highest voltage (V) and its largest steady deviation from nominal (%, over
    steady_windows)."""
    t, n, v_nom = res.t, len(res.t), res.net.nominal_v_V
    steady = steady_windows(t, (e.t for e in res.events), T)
    return {b: {"v_min": float(v.min()) if n else None, "v_max": float(v.max()) if n else None,
                "ss_dev_pct": max((abs(float(np.mean(v[s])) - v_nom) / v_nom * 100 for s in steady), default=None)}
            for b, v in res.buses.items()}


def _events_metrics(res, band: float, carry_W: float, T: float) -> list[dict]:
    """Each event's entry (_event_metrics), each judged until the next event (or the end)."""
    t, n, v_nom = res.t, len(res.t), res.net.nominal_v_V
    names = list(res.net.sources)
    # the sharing over time (powers smoothed over SHARE_SMOOTH_S); each terminal against its own reference v_ref
    # (which the layer moves: where the source's law takes it; with the layer off that is nominal)
    k_smooth = max(1, int(round(SHARE_SMOOTH_S / T)))
    P_s = {s: smooth(res.sources[s]["P"], k_smooth) for s in names} if n else {}
    v_refs = {s: res.sources[s].get("v_ref", np.full(n, v_nom)) for s in names}
    terminal_dev = {s: np.abs(res.sources[s]["v"] - v_refs[s]) / v_refs[s] for s in names}
    ends = sorted({e.t for e in res.events})
    out = []
    for ev in res.events:
        t1 = next((x for x in ends if x > ev.t + 1e-9), float(t[-1]) + T if n else math.inf)
        out.append(_event_metrics(res, ev, t1, band, carry_W, P_s, terminal_dev))
    return out


# the offline issue's acceptance limits, checked by energyctl demo --network on the live run and on its logs
LIMITS = {"step_bus_back_s": 0.150, "step_bus_min_V": 75.5, "bus_ss_dev_pct": 1.0, "sharing_pp": 2.0,
          "trip_bus_back_s": 0.200, "trip_bus_min_V": 74.0, "trip_carried_pct": 95.0, "inrush_A": 20.0,
          "bus_move_V": 2.0}


def carried_by_others_pct(res, target: str, t1: float) -> float | None:
    """After source ``target`` tripped: the share (%) of what all sources deliver that the others carry, over the
    SETTLED_S before t1 (None: no samples there, or no such source)."""
    sel = (res.t >= t1 - SETTLED_S) & (res.t < t1)
    if not sel.any() or target not in res.sources:
        return None
    total = sum(abs(float(np.mean(res.sources[s]["P"][sel]))) for s in res.sources) or 1.0
    return 100.0 * (1.0 - abs(float(np.mean(res.sources[target]["P"][sel]))) / total)


def acceptance_checks(res) -> list[dict]:
    """Each check of the network acceptance criteria on a run: {"check", "value", "limit", "ok"}. After a load step:
    every bus back within +-2 % within 150 ms and never below 75.5 V; after a trip: back within 200 ms, never below
    74 V, and the sources left carry >= 95 % of what is delivered; a connect: accepted, line inrush <= 20 A, bus move
    <= 2 V; steady bus deviation <= 1 %, sharing error <= 2 percentage points; no divergence. res: a NetworkResult
    with its metrics (an offline run's, or a live rig's log read back)."""
    m, L = res.metrics, LIMITS
    out = [{"check": "no divergence", "value": m["diverged_at_s"], "limit": None, "ok": not m["diverged"]}]

    def add(name: str, value, limit, ok: bool) -> None:
        out.append({"check": name, "value": value, "limit": limit, "ok": bool(ok)})

    T = 1.0 / res.net.timing.control_rate_hz
    ends = sorted({e["t_s"] for e in m["events"]})
    for e in m["events"]:
        what = f"{e['kind']} {e['target']} at {e['t_s']:g} s"
        back = worst_back(e["bus_back_in_band_s"].values())
        low = min((v for v in e["bus_min_V"].values() if v is not None), default=None)
        if e["kind"] in ("load", "trip"):
            key = "step" if e["kind"] == "load" else "trip"
            add(f"{what}: buses back within ±2 % (s)", back, L[f"{key}_bus_back_s"],
                back is not None and back <= L[f"{key}_bus_back_s"])
            add(f"{what}: lowest bus voltage (V)", low, L[f"{key}_bus_min_V"],
                low is not None and low >= L[f"{key}_bus_min_V"])
        if e["kind"] == "trip":
            t1 = next((x for x in ends if x > e["t_s"] + 1e-9), float(res.t[-1]) + T)
            rest = carried_by_others_pct(res, e["target"], t1)
            if rest is not None:
                add(f"{what}: the other sources carry (% of the load)", rest, L["trip_carried_pct"],
                    rest >= L["trip_carried_pct"])
        elif e["kind"] in ("connect", "close"):
            add(f"{what}: accepted", e["accepted"], True, e["accepted"])
            if e["accepted"]:
                add(f"{what}: line inrush (A)", e.get("inrush_A"), L["inrush_A"],
                    e.get("inrush_A") is not None and e["inrush_A"] <= L["inrush_A"])
                moves = [v for v in (e.get("bus_move_V") or {}).values() if v is not None]
                mv = max(moves, default=None)
                add(f"{what}: bus move (V)", mv, L["bus_move_V"], mv is not None and mv <= L["bus_move_V"])
    for b, d in m["buses"].items():
        add(f"bus {b}: steady deviation (%)", d["ss_dev_pct"], L["bus_ss_dev_pct"],
            d["ss_dev_pct"] is not None and d["ss_dev_pct"] <= L["bus_ss_dev_pct"])
    errs = [abs(s["sharing_error_pp"]) for s in m["sources"].values() if s["sharing_error_pp"] is not None]
    worst = max(errs, default=None)
    add("steady sharing error (pp)", worst, L["sharing_pp"], worst is not None and worst <= L["sharing_pp"])
    return out
