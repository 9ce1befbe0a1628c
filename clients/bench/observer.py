"""``energyctl bench observer``: what a subscriber that stops reading costs the stack beside it (issue 28, item 3).

The stack (controller daemon, stand-in plant and load as processes on loopback Zenoh; realtime or lockstep) runs
alternately with a monitor beside it that keeps reading ("reading") and with the same monitor SIGSTOPped from
``stop_at_s`` after the plant starts, for ``stop_s`` ("stopped"). The monitor is what a user's dashboard, a bridge or
a logger is to Zenoh: a peer subscribed to PREFIX/** that asks the controller's status every 50 ms, with a 4 KiB
socket receive buffer (so that its stop fills the senders' queues at once, not after megabytes). While it is
stopped, what ``energyctl query status`` does (a new Zenoh session, the query, its close) runs once a second in this
process. Compared within one run of the bench: the plant's measurement -> command latency (p50, p99, max), its
missed and late commands, how long the status queries took to be answered and their sessions to close.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

MONITOR = """
import json, sys, time, zenoh
ep, lease_ms = sys.argv[1], sys.argv[2]
c = zenoh.Config(); c.insert_json5("mode", '"peer"'); c.insert_json5("scouting/multicast/enabled", "false")
c.insert_json5("connect/endpoints", json.dumps([ep])); c.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
c.insert_json5("transport/link/tcp/so_rcvbuf", "4096")
c.insert_json5("transport/link/tx/lease", lease_ms)
s = zenoh.open(c)
sub = s.declare_subscriber("energyctl/**", lambda sample: None)
print("ready", flush=True)
while True:
    s.get("energyctl/source/status", lambda reply: None, timeout=1.0)
    time.sleep(0.05)
"""


def _status_query(ep: str) -> tuple[float, float, bool]:
    """What `energyctl query status` does, in this process (its interpreter's start is not timed): a new Zenoh
    session to ep and the status query (3 s timeout), then the session's close: (seconds to the answer, seconds the
    close took, answered)."""
    from clients.query import QueryError, ask, query_session
    from schemas.component import ZenohConfig
    from service.daemon.bus import close_session

    t0 = time.monotonic()
    try:
        session = query_session(ZenohConfig(mode="peer", connect=[ep]))
    except ConnectionError:
        return time.monotonic() - t0, 0.0, False
    try:
        ask(session, "energyctl", "source", "status", timeout_s=3.0)
        ok = True
    except QueryError:
        ok = False
    t1 = time.monotonic()
    close_session(session)  # not raised if it times out: what it took is the figure
    return t1 - t0, time.monotonic() - t1, ok


def _stack_up(procs) -> bool:
    """Whether the run is still on: its plant not yet started or still running (once it ends, the rest of the
    stack is stopped, and a status query in flight then goes unanswered for that reason)."""
    plant = next((p for name, p in procs.procs if name == "plant"), None)
    return plant is None or plant.poll() is None


def run_arm(scn, stopped: bool, lockstep: bool, rate_hz: float | None, delay: int | None, duration_s: float,
            stop_at_s: float, stop_s: float, lease_ms: int = 10_000) -> dict:
    """One stack with the monitor beside it, SIGSTOPped (stopped) or not: the plant's latency and counters, the
    status queries made meanwhile (seconds to each answer, seconds each session's close took, how many failed; one
    that went unanswered because the plant ended meanwhile and the stack was being stopped is left out), the run's
    wall time."""
    from clients.live import run_live

    queries: list[tuple[float, float, bool]] = []
    threads: list[threading.Thread] = []
    done = threading.Event()

    def extra(ep, procs, env):
        mon = subprocess.Popen([sys.executable, "-c", MONITOR, ep, str(lease_ms)], stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True, env=env)
        procs.procs.append(("monitor", mon))  # stopped (SIGTERM, then SIGKILL) with the rest
        if mon.stdout.readline().strip() != "ready":
            raise RuntimeError("the monitor did not start")

        def stopper():
            if done.wait(stop_at_s):
                return
            if stopped:
                os.kill(mon.pid, signal.SIGSTOP)
            end = time.monotonic() + stop_s
            try:
                while time.monotonic() < end and not done.is_set() and _stack_up(procs):
                    t = time.monotonic()
                    answer_s, close_s, ok = _status_query(ep)
                    if not ok and not _stack_up(procs):
                        break  # asked as the run ended: the controller was being stopped, not held up
                    queries.append((round(answer_s, 3), round(close_s, 3), ok))
                    done.wait(max(0.0, 1.0 - (time.monotonic() - t)))
            finally:
                if stopped:
                    os.kill(mon.pid, signal.SIGCONT)

        th = threading.Thread(target=stopper, daemon=True)
        th.start()
        threads.append(th)
        return None

    t0 = time.monotonic()
    try:
        res = run_live(scn, lockstep=lockstep, rate_hz=rate_hz, out=None, duration_s=duration_s,
                       controller_delay=delay, extra=extra)
    finally:
        done.set()
        for th in threads:
            th.join(70.0)
    c = res["counters"]
    lat = res.get("latency_us") or {}
    return {"arm": "stopped" if stopped else "reading", "wall_s": round(time.monotonic() - t0, 2),
            "latency_p50_us": lat.get("p50"), "latency_p99_us": lat.get("p99"), "latency_max_us": lat.get("max"),
            "samples": c.get("samples"), "commands": c.get("commands"), "missed": c.get("missed"),
            "late": c.get("late"), "queries_s": [q[0] for q in queries],
            "query_closes_s": [q[1] for q in queries], "queries_failed": sum(1 for q in queries if not q[2]),
            "overrun_pct": (res.get("daemon", {}).get("loop") or {}).get("overrun_pct")}


def bench_observer(scn, lockstep: bool = False, rate_hz: float | None = None, delay: int | None = None,
                   duration_s: float = 14.0, stop_at_s: float = 1.0, stop_s: float = 12.0, pairs: int = 1,
                   lease_ms: int = 10_000, progress=None) -> dict:
    """``pairs`` of (reading, stopped) runs, alternated; the default stop (12 s) outlasts Zenoh's 10 s lease, as the
    issue's 15 s stops did."""
    rows = []
    for _ in range(pairs):
        for stopped in (False, True):
            row = run_arm(scn, stopped, lockstep, rate_hz, delay, duration_s, stop_at_s, stop_s, lease_ms)
            rows.append(row)
            if progress:
                progress(row)

    def span(arm, k):
        vals = [r[k] for r in rows if r["arm"] == arm and r.get(k) is not None]
        return [min(vals), max(vals)] if vals else None

    summary = {arm: {k: span(arm, k) for k in ("latency_p50_us", "latency_p99_us", "latency_max_us", "missed",
                                                "late", "queries_failed")} for arm in ("reading", "stopped")}
    for arm in summary:
        qs = [q for r in rows if r["arm"] == arm for q in r["queries_s"]]
        summary[arm]["query_max_s"] = max(qs) if qs else None
        cs = [q for r in rows if r["arm"] == arm for q in r["query_closes_s"]]
        summary[arm]["close_max_s"] = max(cs) if cs else None
    return {"bench": "observer", "scenario": scn.name, "lockstep": lockstep, "rate_hz": rate_hz,
            "duration_s": duration_s, "stop_at_s": stop_at_s, "stop_s": stop_s, "lease_ms": lease_ms,
            "runs": rows, "summary": summary}
