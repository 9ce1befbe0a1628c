"""The operating envelope a DC bus sees (energyctl sweep --preset envelope): load steps between every pair of power
levels, both directions of power and through zero, for every controller, and the same kinds of step on networks.

Single source: from the steady state at P1 the load steps to P2 at ``T_STEP_S``, for every ordered pair of
``LEVELS_W`` (negative: power flowing back into the bus, a battery charging or a drive braking), on the base
scenario's plant, model error and sensor noise (default: the paper's, scenarios/paper-varying-load.toml), at each of
``TIMINGS`` (rate, loop delay). Networks: each network scenario's loads, split equally, step from P1 to P2 at
``NET_STEP_S`` for ``NET_CASES`` (load rejection, reversal, light load), and carry ``NET_STEADY_W`` for
``NET_SEEDS`` noise seeds.

What a run is judged by, against v_ref: it diverges when v leaves +-``DIVERGE`` (25 %); after the step, its peak
deviation (%), the time it spends outside +-``BAND`` (2 %), when it is back in that band for good (ms after the
step), and its steady deviation over the last ``TAIL_S`` (%). A single-source case passes at the first timing when it
does not diverge, is back within ``BACK_MAX_S`` and holds ``STEADY_MAX_PCT``; at the others (1 kHz) when it does not
diverge. A network case passes when it does not diverge and every bus is back within ``NET_BACK_MAX_S`` (steady
cases: every bus within the band at the end).
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np

from service.metrics import max_dev_pct, worst_back
from service.metrics import step_metrics as service_step_metrics

LEVELS_W = (-2400.0, -1200.0, -300.0, 0.0, 300.0, 1200.0, 2400.0)
TIMINGS = ((10_000.0, 3), (1_000.0, 1), (1_000.0, 2))  # (control rate Hz, loop delay samples)
T_STEP_S, DURATION_S = 0.2, 0.4
DIVERGE, BAND = 0.25, 0.02
TAIL_S = 0.05
BACK_MAX_S, STEADY_MAX_PCT = 0.030, 1.0
CONTROLLERS = "nested,fblc,smc,lqr,bm,pi"
REFERENCE_LAW, BASELINE = "nested", "pi"
SENSOR_RESOLUTION_V = 0.05  # the base scenario's sensor noise sigma: peaks closer than this are a tie

NET_SCENARIOS = ("two-source", "ring")
NET_CASES = {"rejection": (1200.0, 0.0), "reversal": (1200.0, -1200.0), "light": (2400.0, 150.0)}
NET_STEADY_W, NET_SEEDS = 100.0, 8
NET_STEP_S, NET_DURATION_S = 0.3, 0.7
NET_BACK_MAX_S = 0.150


def single_overrides(P1: float, P2: float, rate_hz: float, delay: int, kind: str, v_ref: float, R: float
                     ) -> list[str]:
    """--set overrides of one single-source case: steady at P1 (W), a step to P2 (W) at T_STEP_S."""
    i0 = P1 / v_ref
    return [f'controller.kind="{kind}"', f"timing.control_rate_hz={rate_hz}", f"timing.delay_samples={delay}",
            f"timing.duration_s={DURATION_S}", 'load.kind="steps"', f"load.value={P1}",
            f"load.steps=[[{T_STEP_S}, {P2}]]", "load.components=[]", f"plant.initial.i_A={i0}",
            f"plant.initial.v_V={v_ref}", f"plant.initial.u_V={v_ref + R * i0}"]


def step_metrics(t: np.ndarray, v: np.ndarray, v_ref: float, t_step: float) -> dict:
    """A step's metrics against +-BAND, +-DIVERGE and over the last TAIL_S (service.metrics.step_metrics)."""
    return service_step_metrics(t, v, v_ref, t_step, BAND, DIVERGE, TAIL_S)


def single_worker(job: tuple[str, list[str]]) -> dict:
    """One single-source case (run on a worker process)."""
    from clients.commands.common import load
    from service.sim import run

    path, ovs = job
    scn = load(path, ovs)
    res = run(scn, stop_on_divergence=True)
    m = step_metrics(res.trace["t"], res.trace["v"], scn.controller.v_ref_V, T_STEP_S)
    ended_early = float(res.trace["t"][-1]) < DURATION_S - 2.0 / scn.timing.control_rate_hz
    m["diverged"] = bool(m["diverged"] or res.metrics["diverged"] or ended_early)
    return m


def net_overrides(path: str, P1: float, P2: float, seed: int) -> list[str]:
    """--set overrides of one network case: its loads, split equally, at P1 (W), stepping to P2 (W) at NET_STEP_S."""
    from schemas.network import load_network

    names = list(load_network(path).loads)
    n = len(names)
    ovs = [f"seed={seed}", f"timing.duration_s={NET_DURATION_S}"]
    for name in names:
        ovs += [f'loads.{name}.kind="steps"', f"loads.{name}.value={P1 / n}", f"loads.{name}.components=[]",
                f"loads.{name}.active_from_s=0.0",
                f"loads.{name}.steps=[[{NET_STEP_S}, {P2 / n}]]" if P2 != P1 else f"loads.{name}.steps=[]"]
    return ovs


def net_worker(job: tuple[str, list[str]]) -> dict:
    """One network case: diverged, the slowest bus back in band after the step (s; None: never), the largest bus
    deviation over the last TAIL_S (%), the worst sharing error (pp)."""
    from schemas.network import load_network
    from service.network.netsim import run_network

    path, ovs = job
    net = load_network(path, ovs)
    res = run_network(net)
    m = res.metrics
    v_nom = net.nominal_v_V
    steady = max(max_dev_pct(res.t, v, res.t[-1] - TAIL_S, math.inf, v_nom) for v in res.buses.values())
    step = [e for e in m["events"] if e["kind"] == "load" and abs(e["t_s"] - NET_STEP_S) < 1e-9]
    backs = [b for e in step for b in e["bus_back_in_band_s"].values()]
    errs = [abs(s["sharing_error_pp"]) for s in m["sources"].values() if s["sharing_error_pp"] is not None]
    return {"diverged": bool(m["diverged"]), "back_s": worst_back(backs),
            "steady_pct": steady, "sharing_pp": max(errs, default=None)}


def jobs(base: str, controllers: list[str], network_paths: list[str], sets: list[str]):
    """(single-source jobs, their labels (kind, rate, delay, P1, P2), network jobs, their labels (scenario, case,
    seed))."""
    from clients.commands.common import load

    scn = load(base, sets)
    v_ref, R = scn.controller.v_ref_V, scn.plant.R_ohm
    sj, sl = [], []
    for kind, (rate, d), (P1, P2) in itertools.product(controllers, TIMINGS, itertools.permutations(LEVELS_W, 2)):
        sj.append((base, [*sets, *single_overrides(P1, P2, rate, d, kind, v_ref, R)]))
        sl.append((kind, rate, d, P1, P2))
    nj, nl = [], []
    for path in network_paths:
        name = path.rsplit("/", 1)[-1].removesuffix(".toml")
        for case, (P1, P2) in NET_CASES.items():
            nj.append((path, net_overrides(path, P1, P2, 1)))
            nl.append((name, case, 1))
        for seed in range(1, NET_SEEDS + 1):
            nj.append((path, net_overrides(path, NET_STEADY_W, NET_STEADY_W, seed)))
            nl.append((name, f"steady {NET_STEADY_W:.0f} W", seed))
    return sj, sl, nj, nl


def single_passes(m: dict, first_timing: bool) -> bool:
    if m["diverged"]:
        return False
    if not first_timing:
        return True
    return m["back_s"] is not None and m["back_s"] <= BACK_MAX_S and m["steady_pct"] <= STEADY_MAX_PCT


def net_passes(m: dict, steady_case: bool) -> bool:
    if m["diverged"]:
        return False
    if steady_case:
        return m["steady_pct"] <= BAND * 100
    return m["back_s"] is not None and m["back_s"] <= NET_BACK_MAX_S


def _f(x, fmt=".2f", scale=1.0) -> str:
    return "-" if x is None else format(x * scale, fmt)


def report(sl: list, sr: list[dict], nl: list, nr: list[dict], v_ref: float) -> tuple[str, bool]:
    """The tables, and whether every run of the reference law passed (the others are reported, and fail the sweep
    too when they diverge or miss the band: the exit code is for every run)."""
    from clients.table import render

    out, all_ok = [], True
    rows = []
    for (kind, rate, d) in dict.fromkeys((k, r, dd) for k, r, dd, _, _ in sl):
        ms = [m for (k, r, dd, _, _), m in zip(sl, sr, strict=True) if (k, r, dd) == (kind, rate, d)]
        first = (rate, d) == TIMINGS[0]
        ok = [m for m in ms if not m["diverged"]]
        fails = sum(not single_passes(m, first) for m in ms)
        all_ok &= fails == 0
        backs = [m["back_s"] for m in ok]
        rows.append([kind, f"{rate / 1e3:g} kHz, {d}", str(len(ms)), str(len(ms) - len(ok)),
                     "never" if None in backs else _f(max(backs, default=0.0), ".1f", 1e3),
                     _f(max((m["peak_pct"] for m in ok), default=None)),
                     _f(max((m["steady_pct"] for m in ok), default=None), ".3f"), str(fails)])
    out.append(f"Single source: steps between every pair of {', '.join(f'{p / 1e3:g}' for p in LEVELS_W)} kW at "
               f"{T_STEP_S:g} s from the steady state; passes: no divergence (+-{DIVERGE:.0%}), and at "
               f"{TIMINGS[0][0] / 1e3:g} kHz back within +-{BAND:.0%} in {BACK_MAX_S * 1e3:.0f} ms and steady within "
               f"{STEADY_MAX_PCT:g} %")
    out.append(render(["controller", "rate, delay", "runs", "diverged", "worst back ms", "worst peak %",
                       "worst steady %", "failing"], rows))
    cmp = comparison(sl, sr, v_ref)
    if cmp:
        out.append("")
        out.append(cmp)
    if nl:
        rows = []
        for (name, case, seed), m in zip(nl, nr, strict=True):
            steady_case = case.startswith("steady")
            ok = net_passes(m, steady_case)
            all_ok &= ok
            rows.append([name, case, str(seed), "yes" if m["diverged"] else "no",
                         "-" if steady_case else ("never" if m["back_s"] is None else _f(m["back_s"], ".1f", 1e3)),
                         _f(m["steady_pct"], ".3f"), _f(m["sharing_pp"]), "pass" if ok else "FAIL"])
        out.append("")
        out.append(f"Networks (default law, loads split equally, step at {NET_STEP_S:g} s): passes: no divergence and "
                   f"every bus back within +-{BAND:.0%} in {NET_BACK_MAX_S * 1e3:.0f} ms (steady: within it at the "
                   "end)")
        out.append(render(["network", "case", "seed", "diverged", "bus back ms", "bus steady %", "sharing pp",
                           "verdict"], rows))
    return "\n".join(out), all_ok


def comparison(sl: list, sr: list[dict], v_ref: float) -> str:
    """The reference law against the baseline at the first timing, case by case: the ratio of their peak deviations
    and of their times outside the band (< 1: the reference law is better)."""
    from clients.table import render

    rate, d = TIMINGS[0]
    by = {(k, P1, P2): m for (k, r, dd, P1, P2), m in zip(sl, sr, strict=True) if (r, dd) == (rate, d)}
    pairs = [(P1, P2) for (k, P1, P2) in by if k == REFERENCE_LAW and (BASELINE, P1, P2) in by]
    if not pairs:
        return ""
    rows, strict, tied = [], 0, 0
    tie_pct = SENSOR_RESOLUTION_V / v_ref * 100
    for P1, P2 in pairs:
        a, b = by[(REFERENCE_LAW, P1, P2)], by[(BASELINE, P1, P2)]
        if a["diverged"] or b["diverged"]:
            rows.append([f"{P1:g}", f"{P2:g}", "-", "-", "diverged: " + ("law" if a["diverged"] else BASELINE)])
            continue
        pr = a["peak_pct"] / b["peak_pct"] if b["peak_pct"] else None
        orr = a["outside_s"] / b["outside_s"] if b["outside_s"] else (0.0 if a["outside_s"] == 0 else None)
        s_ok = a["peak_pct"] <= b["peak_pct"] and a["outside_s"] <= b["outside_s"]
        t_ok = a["peak_pct"] <= b["peak_pct"] + tie_pct and a["outside_s"] <= b["outside_s"] + 1.0 / rate + 1e-12
        strict += s_ok
        tied += t_ok
        rows.append([f"{P1:g}", f"{P2:g}", _f(pr, ".3f"), "-" if orr is None else _f(orr, ".2f"),
                     "no worse" if s_ok else ("tie" if t_ok else "worse")])
    head = (f"{REFERENCE_LAW} against {BASELINE} at {rate / 1e3:g} kHz with {d} samples of delay, per case (ratio < 1: "
            f"{REFERENCE_LAW} better): no worse in both in {strict} of {len(pairs)} cases; within one sensor sigma "
            f"({SENSOR_RESOLUTION_V} V) of peak and one period outside the band in {tied} of {len(pairs)}")
    return head + "\n" + render(["P1 W", "P2 W", "peak ratio", "outside ratio", "verdict"], rows)


def as_json(sl, sr, nl, nr) -> str:
    return json.dumps({"single": [{"controller": k, "rate_hz": r, "delay_samples": d, "P1_W": P1, "P2_W": P2, **m}
                                  for (k, r, d, P1, P2), m in zip(sl, sr, strict=True)],
                       "network": [{"network": n, "case": c, "seed": s, **m}
                                   for (n, c, s), m in zip(nl, nr, strict=True)]})
