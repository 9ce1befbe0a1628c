"""``energyctl bench wake``: how late a timed wait ends, at the kernel's default timer slack and at ours.

A realtime loop between instants waits with a timeout: the daemon's clock loop sleeps, the HIL plant waits on its
command queue until shortly before its next sampling instant. Linux may end such a wait up to the thread's timer
slack late (50 us by default, to coalesce wake-ups; service/priority.py). This bench waits 60 us, ``n`` times per
setting, as ``time.sleep`` and as the plant's ``Queue.get(timeout=...)`` on an empty queue, alternating the two
slack settings in blocks so that both see the same minutes of this shared machine, and reports the overshoot.
"""

from __future__ import annotations

import time
from queue import Empty, Queue

import numpy as np

from service.priority import DEFAULT_TIMER_SLACK_NS, set_timer_slack, timer_slack_ns

WAIT_S = 60e-6


def _overshoots_us(wait, n: int) -> np.ndarray:
    now = time.monotonic_ns
    out = np.empty(n)
    for k in range(n):
        t0 = now()
        wait()
        out[k] = (now() - t0) / 1e3 - WAIT_S * 1e6
    return out


def bench_wake(slack_ns: int = 1000, n: int = 20_000, blocks: int = 10) -> dict:
    before = timer_slack_ns()
    if before is None:
        return {"bench": "wake", "error": "no timer slack on this system (Linux prctl)"}
    q: Queue = Queue()

    def queue_wait() -> None:
        try:
            q.get(timeout=WAIT_S)
        except Empty:
            pass

    waits = {"sleep": lambda: time.sleep(WAIT_S), "queue_get": queue_wait}
    got = {(s, w): [] for s in (DEFAULT_TIMER_SLACK_NS, slack_ns) for w in waits}
    try:
        for _ in range(blocks):
            for s in (DEFAULT_TIMER_SLACK_NS, slack_ns):
                refused = set_timer_slack(s)
                if refused:
                    return {"bench": "wake", "error": refused}
                for w, fn in waits.items():
                    got[(s, w)].append(_overshoots_us(fn, max(1, n // blocks)))
    finally:
        set_timer_slack(before)
    res = {"bench": "wake", "wait_us": WAIT_S * 1e6, "waits_each": n}
    for (s, w), parts in got.items():
        v = np.concatenate(parts)
        p50, p99, p999 = np.percentile(v, [50, 99, 99.9])
        res[f"{w}_overshoot_us_slack_{s}ns"] = {"p50": round(float(p50), 1), "p99": round(float(p99), 1),
                                                "p99.9": round(float(p999), 1), "max": round(float(v.max()), 1)}
    return res
