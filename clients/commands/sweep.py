"""energyctl sweep: a cartesian grid of scenario overrides, for each controller, on all cores."""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time

from clients.commands.common import ACCEPTANCE_HELP, SHIPPED, failure_lines, kinds, load, parallel
from clients.envelope import CONTROLLERS as ENVELOPE_CONTROLLERS
from clients.options import add_scenario_set
from clients.table import metrics_table, render
from schemas.scenario import ScenarioError, parse_override

NETWORK_SCENARIOS = ("two-source", "two-source-trip", "plug-in", "ring", "radial-16")
NETWORK_GRID = {  # over each topology: loop delay x interaction delay x load x noise
    "timing.delay_samples": [0, 1, 2, 3],
    "links.*.delay_s": [0.0, 0.001, 0.005],
    "load_scale": [0.5, 1.0, 2.0],
    "sensor.noise_v_V,sensor.noise_i_A": [0.0, 0.05],
}
ROBUSTNESS_GRID = {
    "timing.control_rate_hz": [5000.0, 10000.0, 20000.0],
    "timing.delay_samples": [0, 1, 2, 3],
    "plant.initial.i_A": [0.5, 1.0, 15.0, 30.0],
    "load.value": [300.0, 1200.0, 2400.0],
    "sensor.noise_v_V,sensor.noise_i_A": [0.0, 0.05],
}


def add_parser(subparsers) -> argparse.ArgumentParser:
    w = subparsers.add_parser(
        "sweep", help="run a grid of scenario overrides on all cores",
        description="Cartesian grid of overrides on a base scenario, for each controller. "
                    "--preset robustness is the robustness grid: rates {5,10,20} kHz x delays "
                    "{0..3} x i0 {0.5,1,15,30} A x load {0.3,1.2,2.4} kW x noise {0,0.05}. --preset envelope: "
                    "load steps between every pair of {-2.4,-1.2,-0.3,0,0.3,1.2,2.4} kW from the steady state "
                    "(both directions of power, through zero) at 10 kHz (3 samples of delay) and 1 kHz (1 and 2), "
                    "for every controller, with the nested law against the cascaded PI case by case, and on the "
                    "two-source network and the ring: load rejection to 0, reversal to -1.2 kW, 2.4 kW -> 150 W, "
                    "100 W steady over 8 seeds. Exit 1 when a run diverges or misses its criteria. "
                    "The summary counts "
                    "per controller (or network) the runs that failed their acceptance criteria and names the "
                    f"first {SHOW_FAILED} of them under it (--json and --csv carry accepted and failures for every "
                    "run). " + ACCEPTANCE_HELP)
    w.add_argument("scenario", nargs="*",
                   help="the base scenario the grid overrides (default: scenarios/paper-constant-load.toml); with "
                        "--preset network, the network scenarios (default: scenarios/network/{"
                        + ",".join(NETWORK_SCENARIOS) + "}.toml)")
    w.add_argument("--preset", choices=["robustness", "network", "envelope"],
                   help="start from a named grid: robustness (one source: rates x delays x initial currents x "
                        "loads x noise), network (each network scenario: loop delay {0..3} x interaction delay "
                        "{0, 1, 5 ms} x load x {0.5, 1, 2} x noise {0, 0.05}) or envelope (load steps over both "
                        "directions of power, one source and networks; base scenario default "
                        "scenarios/paper-varying-load.toml)")
    w.add_argument("--grid", action="append", metavar="key=v1,v2,...",
                   help="a grid axis; 'k1,k2=v1,v2' sets both keys to each value (repeatable)")
    w.add_argument("--controllers", default=None,
                   help="comma list (default: nested; with --preset envelope: " + ENVELOPE_CONTROLLERS + ")")
    add_scenario_set(w)
    w.add_argument("--jobs", type=int, default=None, help="processes (default: all cores)")
    w.add_argument("--rows", action="store_true", help="also print every run")
    w.add_argument("--csv", metavar="FILE", help="write every run to a CSV file")
    w.add_argument("--json", action="store_true",
                   help="print every run as JSON (the grid, then one object per run) instead of the tables")
    w.add_argument("--quiet", action="store_true", help="no progress line on stderr")
    w.set_defaults(func=run)
    return w


SHOW_FAILED = 20  # failed runs named under the summary


def grid_from_args(args: argparse.Namespace) -> dict[str, list]:
    presets = {"robustness": ROBUSTNESS_GRID, "network": NETWORK_GRID}
    grid: dict[str, list] = dict(presets.get(args.preset, {}))
    for g in args.grid or []:
        key, _, vals = g.partition("=")
        if not vals:
            raise ScenarioError(f"--grid {g!r}: expected key=v1,v2,...")
        grid[key.strip()] = [parse_override(f"x={v}")[1] for v in vals.split(",")]
    if not grid:
        raise ScenarioError("sweep: give --preset robustness, network or envelope, or at least one --grid key=v1,v2")
    return grid


def summary_row(kind: str, ms: list[dict]) -> list[str]:
    """One controller's line of the summary table."""
    settles = [m["settle_s"] for m in ms if m["settle_s"] is not None]
    holds = [m["hold_max_dev_pct"] for m in ms if m["hold_max_dev_pct"] is not None and not m["diverged"]]
    return [kind, str(len(ms)), str(sum(not m["accepted"] for m in ms)), str(sum(m["diverged"] for m in ms)),
            str(sum(m["settle_s"] is None for m in ms)),
            f"{max(settles) * 1e3:.1f}" if settles else "-",
            f"{sorted(settles)[len(settles) // 2] * 1e3:.1f}" if settles else "-",
            f"{max(holds):.2f}" if holds else "-",
            str(sum(m["feasibility_violations"] > 0 for m in ms))]


def write_csv(path: str, keys: list[str], labels: list, results: list[dict], label: str = "controller") -> None:
    import csv

    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([label, *(k.replace(",", "+") for k in keys), *results[0].keys()])
        for (kind, combo), m in zip(labels, results, strict=True):
            w.writerow([kind, *combo, *(_cell(v) for v in m.values())])


def _cell(v) -> object:
    """A metric as a CSV cell: none empty, a list of failures as 'criterion: detail; ...'."""
    if v is None:
        return ""
    if isinstance(v, list):
        return "; ".join(f"{f['criterion']}: {f['detail']}" if isinstance(f, dict) else str(f) for f in v)
    return v


def report_failed(keys: list[str], labels: list, results: list[dict]) -> int:
    """Names the runs that failed their acceptance criteria (the first SHOW_FAILED), with their grid values;
    the exit status: 1 if any failed, else 0."""
    failed = [(k, c, m) for (k, c), m in zip(labels, results, strict=True) if not m["accepted"]]
    for k, c, m in failed[:SHOW_FAILED]:
        for line in failure_lines(" ".join([k, *(f"{key}={v}" for key, v in zip(keys, c, strict=True))]), m):
            print(line)
    if len(failed) > SHOW_FAILED:
        print(f"... and {len(failed) - SHOW_FAILED} more failed runs (--json or --csv lists every run)")
    return 1 if failed else 0


def write_runs(args: argparse.Namespace, wall: float, grid: dict, keys: list[str], labels: list, results: list[dict],
               label: str) -> bool:
    """Every run to --csv if asked, and with --json every run to stdout (True: printed, nothing else to print).
    labels: (what the run is of, e.g. its controller or network; its grid values) per run."""
    if args.csv:
        write_csv(args.csv, keys, labels, results, label)
    if args.json:
        print(json.dumps({"wall_s": wall, "grid": grid, "runs": [
            {label: k, **dict(zip(keys, c, strict=True)), **m} for (k, c), m in zip(labels, results, strict=True)]}))
    return bool(args.json)


def run(args: argparse.Namespace) -> int:
    if args.preset == "network":
        return run_network_sweep(args)
    if args.preset == "envelope":
        return run_envelope(args)
    if len(args.scenario) > 1:
        raise ScenarioError("sweep: one base scenario (several only with --preset network)")
    args.scenario = args.scenario[0] if args.scenario else str(SHIPPED / "paper-constant-load.toml")
    grid = grid_from_args(args)
    controllers = kinds(args.controllers or "nested")
    keys = list(grid)
    combos = list(itertools.product(*(grid[k] for k in keys)))
    jobs, labels = [], []
    for kind in controllers:
        for combo in combos:
            ovs = [*(args.set or []), f'controller.kind="{kind}"']
            for key, val in zip(keys, combo, strict=True):
                for sub in key.split(","):
                    ovs.append(f"{sub}={json.dumps(val)}")
            jobs.append((args.scenario, ovs))
            labels.append((kind, combo))
    load(*jobs[0])
    sys.stderr.write(f"sweep: {len(combos)} cases x {len(controllers)} controllers = {len(jobs)} runs on "
                     f"{args.jobs or os.cpu_count()} processes\n")
    t0 = time.perf_counter()
    results = parallel(jobs, args.jobs, progress=not args.quiet)
    wall = time.perf_counter() - t0
    rows = [summary_row(kind, [m for (k, _), m in zip(labels, results, strict=True) if k == kind])
            for kind in controllers]
    if write_runs(args, wall, grid, keys, labels, results, "controller"):
        return 1 if not all(m["accepted"] for m in results) else 0
    print(render(["controller", "runs", "failed", "diverged", "not settled", "worst settle ms", "median settle ms",
                  "worst hold %", "runs w/ feas viol"], rows))
    print(f"{len(jobs)} runs in {wall:.1f} s")
    if args.rows:
        print(metrics_table([([k, *map(str, c)], m) for (k, c), m in zip(labels, results, strict=True)],
                            ["controller", *keys]))
    return report_failed(keys, labels, results)


def run_network_sweep(args: argparse.Namespace) -> int:
    """--preset network: the grid over each network scenario, one summary row per scenario."""
    from pathlib import Path

    from schemas.network import load_network

    grid = grid_from_args(args)
    keys = list(grid)
    combos = list(itertools.product(*(grid[k] for k in keys)))
    paths = args.scenario or [str(SHIPPED / "network" / f"{n}.toml") for n in NETWORK_SCENARIOS]
    jobs, labels = [], []
    for path in paths:
        for combo in combos:
            ovs = list(args.set or [])
            for key, val in zip(keys, combo, strict=True):
                ovs += [f"{sub}={json.dumps(val)}" for sub in key.split(",")]
            jobs.append((path, ovs))
            labels.append((Path(path).stem, combo))
    for path in paths:  # validate before starting work
        load_network(path, args.set or [])
    sys.stderr.write(f"sweep: {len(combos)} cases x {len(paths)} networks = {len(jobs)} runs on "
                     f"{args.jobs or os.cpu_count()} processes\n")
    t0 = time.perf_counter()
    results = parallel(jobs, args.jobs, progress=not args.quiet)
    wall = time.perf_counter() - t0
    if write_runs(args, wall, grid, keys, labels, results, "network"):
        return 1 if not all(m["accepted"] for m in results) else 0
    rows = []
    for path in paths:
        ms = [m for (n, _), m in zip(labels, results, strict=True) if n == Path(path).stem]
        ok = [m for m in ms if not m["diverged"]]
        backs = [m["worst_bus_back_s"] for m in ok]
        rows.append([Path(path).stem, str(len(ms)), str(sum(not m["accepted"] for m in ms)), str(len(ms) - len(ok)),
                     f"{max((m['worst_sharing_pp'] or 0.0 for m in ok), default=0.0):.2f}",
                     f"{min((m['bus_min_V'] for m in ok), default=float('nan')):.2f}",
                     "never" if None in backs else f"{max(backs, default=0.0) * 1e3:.0f}",
                     str(sum(m["fallback_s"] > 0 for m in ok))])
    print(render(["network", "runs", "failed", "diverged", "worst sharing pp", "lowest bus V",
                  "slowest bus back ms", "runs w/ fallback"], rows))
    print(f"{len(jobs)} runs in {wall:.1f} s")
    if args.rows:
        print(render(["network", *keys, *results[0].keys()],
                     [[n, *map(str, c), *(str(_cell(v)) for v in m.values())] for (n, c), m in zip(labels, results,
                                                                                                   strict=True)]))
    return report_failed(keys, labels, results)



def run_envelope(args: argparse.Namespace) -> int:
    """--preset envelope (clients/envelope.py): the single-source steps for each controller, the law against the PI
    baseline per case, the network cases; exit 1 when any run fails its criteria."""
    from clients import envelope

    if args.grid:
        raise ScenarioError("sweep --preset envelope: its grid is fixed (no --grid); --set changes the base scenario")
    base = args.scenario[0] if args.scenario else str(SHIPPED / "paper-varying-load.toml")
    if len(args.scenario) > 1:
        raise ScenarioError("sweep --preset envelope: one base scenario")
    controllers = kinds(args.controllers or ENVELOPE_CONTROLLERS)
    nets = [str(SHIPPED / "network" / f"{n}.toml") for n in envelope.NET_SCENARIOS]
    sj, sl, nj, nl = envelope.jobs(base, controllers, nets, list(args.set or []))
    sys.stderr.write(f"sweep: envelope, {len(sj)} single-source runs ({len(controllers)} controllers) and "
                     f"{len(nj)} network runs on {args.jobs or os.cpu_count()} processes\n")
    t0 = time.perf_counter()
    sr = parallel(sj, args.jobs, progress=not args.quiet, worker=envelope.single_worker)
    nr = parallel(nj, args.jobs, progress=not args.quiet, worker=envelope.net_worker)
    wall = time.perf_counter() - t0
    text, ok = envelope.report(sl, sr, nl, nr, load(base, args.set or []).controller.v_ref_V)
    if args.json:
        print(envelope.as_json(sl, sr, nl, nr))
    else:
        print(text)
        print(f"{len(sj) + len(nj)} runs in {wall:.1f} s")
    if not ok:
        sys.stderr.write("sweep: some runs diverged or missed their criteria (see the tables)\n")
    return 0 if ok else 1
