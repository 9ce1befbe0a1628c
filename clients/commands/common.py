"""What the scenario commands (sim, compare, sweep, demo, bench) share: the controller kinds, the embedded demo
scenario, and running many scenarios on several processes."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from schemas.scenario import ScenarioError, load_scenario

EMBEDDED = Path(__file__).parent.parent / "embedded"
DEMO_SCENARIO = EMBEDDED / "demo.toml"
# the scenarios shipped in the repository (the sweeps' defaults name them from here, whatever the working directory)
SHIPPED = Path(__file__).resolve().parents[2] / "scenarios"
CONTROLLERS = ("nested", "fblc", "smc", "lqr", "bm", "pi", "fixed")


def is_network_file(path: str) -> bool:
    """Whether the TOML file at path is a network scenario (kind = "network"); False if it cannot be read (the
    one-source loader then says why)."""
    from pathlib import Path

    from schemas.network import is_network
    from schemas.scenario import read_toml

    try:
        return is_network(read_toml(Path(path), "scenario"))
    except ScenarioError:
        return False


def load(path: str, overrides: list[str]):
    """The scenario at path with the --set overrides applied (ScenarioError names a bad field)."""
    if is_network_file(path):
        raise ScenarioError(f"{path} is a network scenario (kind = \"network\"): energyctl sim runs it, and "
                            "energyctl sweep --preset network sweeps it")
    return load_scenario(path, overrides)


def kinds(text: str) -> list[str]:
    """--controllers: "fblc,lqr" -> ["fblc", "lqr"], each a known controller kind."""
    found = [k.strip() for k in text.split(",") if k.strip()]
    bad = [k for k in found if k not in CONTROLLERS]
    if bad:
        raise ScenarioError(f"--controllers: unknown {', '.join(bad)} (choose from {', '.join(CONTROLLERS)})")
    return found


def run_one(path: str, overrides: list[str]) -> dict:
    """The metrics of one offline closed-loop run (a network scenario's summarised: network_summary)."""
    if is_network_file(path):
        from schemas.network import load_network
        from service.network.netsim import run_network

        return network_summary(run_network(load_network(path, overrides)).metrics)
    from service.sim import run

    return run(load(path, overrides)).metrics


def network_summary(m: dict) -> dict:
    """A network run in one row: diverged, the worst sharing error (pp), the lowest bus voltage (V), the largest
    steady bus deviation (%), the longest time a bus took back into +-2 % after an event (s; None: not by the next),
    the time its sources spent falling back (s)."""
    from service.metrics import worst_back

    backs = [v for e in m["events"] for v in e["bus_back_in_band_s"].values()]
    errs = [abs(s["sharing_error_pp"]) for s in m["sources"].values() if s["sharing_error_pp"] is not None]
    return {"diverged": m["diverged"], "worst_sharing_pp": max(errs, default=None),
            "bus_min_V": min((b["v_min"] for b in m["buses"].values() if b["v_min"] is not None), default=None),
            "worst_bus_ss_dev_pct": max((b["ss_dev_pct"] for b in m["buses"].values()
                                         if b["ss_dev_pct"] is not None), default=None),
            "worst_bus_back_s": worst_back(backs),
            "fallback_s": sum(s["fallback_s"] or 0.0 for s in m["sources"].values()),
            "accepted": m["accepted"], "failures": m["failures"]}


ACCEPTANCE_HELP = ("Exit status: 0 when every run meets its scenario's [acceptance] criteria, 1 when one diverges "
                   "(a node further than acceptance.diverge_dev_pct, 25 %, from v_ref; a network: from nominal) or "
                   "leaves the band (acceptance.band_pct, +-2 %) where it must hold (from acceptance.hold_from_s on, "
                   "0.05 s, a network's buses 0.2 s, except acceptance.recover_s after each event) for longer than "
                   "acceptance.max_outside_band_s (0 s): each such run is named with its criterion, in the text and "
                   "as accepted/failures in --json; 2 for a bad scenario or option.")


def failure_lines(label: str, m: dict) -> list[str]:
    """One line per acceptance criterion the run labelled ``label`` failed (service.sim.verdict)."""
    return [f"FAILED {label}: {f['criterion']}: {f['detail']}" for f in m.get("failures") or []]


def _worker(job: tuple[str, list[str]]) -> dict:
    return run_one(*job)


def parallel(jobs: list[tuple[str, list[str]]], n_jobs: int | None, progress: bool = False, worker=None
             ) -> list[dict]:
    """worker (default: run_one on (path, overrides)) for each job on n_jobs processes (default: all cores), results
    in job order. worker: a module-level function of one job."""
    worker = worker or _worker
    n = n_jobs or os.cpu_count() or 1
    t0 = time.perf_counter()
    if n == 1 or len(jobs) == 1:
        out = []
        for k, j in enumerate(jobs, 1):
            out.append(worker(j))
            if progress:
                _progress(k, len(jobs), t0)
        return out
    import multiprocessing as mp
    import threading

    from service.priority import die_with_parent

    # each worker ends with this process (a SIGKILLed sweep left its workers running its grid to the end)
    tie = (os.getpid(), threading.current_thread() is threading.main_thread())
    with mp.get_context("fork" if sys.platform != "win32" else "spawn").Pool(n, die_with_parent, tie) as pool:
        out = []
        for k, m in enumerate(pool.imap(worker, jobs, chunksize=2), 1):
            out.append(m)
            if progress:
                _progress(k, len(jobs), t0)
    if progress:
        sys.stderr.write("\n")
    return out


def _progress(k: int, n: int, t0: float) -> None:
    el = time.perf_counter() - t0
    eta = el / k * (n - k)
    sys.stderr.write(f"\r{k}/{n} runs, {el:.0f} s elapsed, ~{eta:.0f} s left   ")
    sys.stderr.flush()
