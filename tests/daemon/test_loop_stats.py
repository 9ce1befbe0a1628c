"""The loop's time statistics (service.daemon.loop_stats.LoopStats): what status reports, what a status query
costs."""

from __future__ import annotations

import random

import pytest

from service.daemon.loop_stats import STATS_EVERY_NS, LoopStats


def _filled(n: int, execs_us: list[int], publish_us: int = 1) -> LoopStats:
    s = LoopStats(n)
    for k, e in enumerate(execs_us):
        s.record(0 if k == 0 else 100_000, e * 1000, publish_us * 1000)
    return s


def test_percentiles_are_nearest_rank_over_the_last_n_ticks():
    execs = list(range(1, 1002))  # 1..1001 us
    random.Random(3).shuffle(execs)
    s = _filled(1001, execs)
    out = s.summary(0, fresh=True)
    ex = out["exec_us"]
    assert (ex["p50"], ex["p99"], ex["max"], ex["mean"]) == (501.0, 991.0, 1001.0, 501.0)
    assert out["compute_us"]["max"] == 1000.0 and out["publish_us"]["p99"] == 1.0  # exec - the command's put
    assert out["period_us"]["p50"] == 100.0  # the first tick has no period (0): not counted
    # a ring of 100 keeps only the last 100 ticks
    s = _filled(100, [5] * 1000 + [7] * 100)
    assert s.summary(0, fresh=True)["exec_us"]["max"] == 7.0 and s.summary(0, fresh=True)["exec_us"]["p50"] == 7.0


def test_a_status_query_reuses_the_distributions_for_a_while_and_counters_are_always_current():
    """Recomputing the distributions at each of 100 queries a second took more than a core and the GIL the loop
    needs; the counters are cheap and stay exact."""
    s = _filled(1000, [10] * 1000)
    t0 = 5_000_000_000
    assert s.summary(t0)["exec_us"]["max"] == 10.0
    s.record(100_000, 900_000)  # a 900 us tick
    s.overruns += 8
    soon = s.summary(t0 + STATS_EVERY_NS - 1)
    assert soon["ticks"] == 1001 and soon["overruns"] == 8  # counters now
    assert soon["exec_us"]["max"] == 10.0  # distributions from t0
    assert s.summary(t0 + STATS_EVERY_NS - 1, fresh=True)["exec_us"]["max"] == 900.0  # fresh: now
    s.record(100_000, 950_000)
    assert s.summary(t0 + 2 * STATS_EVERY_NS)["exec_us"]["max"] == 950.0  # old enough: recomputed


def test_cpu_pct_is_the_processes_cpu_time_over_the_wall_time_between_ticks(monkeypatch):
    """Read every 1024 ticks, from the first: a process that used 1 ms of CPU per 2 ms of ticking reports 50 % of one
    CPU; a pause with no ticks counts from the next mark on; nothing before the second mark."""
    from service.daemon import loop_stats

    clock = {"cpu": 10.0, "wall": 100.0}
    monkeypatch.setattr(loop_stats.time, "process_time", lambda: clock["cpu"])
    monkeypatch.setattr(loop_stats.time, "monotonic", lambda: clock["wall"])
    s = LoopStats(64)
    s.record(0, 1000)
    assert s.cpu_pct() is None and s.summary(0, fresh=True)["cpu_pct"] is None
    for _ in range(1024):  # tick 1025 is the next mark
        clock["cpu"] += 0.001
        clock["wall"] += 0.002
        s.record(100_000, 1000)
    assert s.cpu_pct() == 50.0
    clock["wall"] += 10.0  # no ticks for 10 s: not counted until the next mark, which then covers it
    assert s.cpu_pct() == 50.0
    for _ in range(1024):
        s.record(100_000, 1000)
    assert s.cpu_pct() == round(100.0 * 1.024 / (2.048 + 10.0), 1)


def test_control_us_is_the_control_computation_of_the_ticks_that_computed_a_command():
    """A tick that computed no command (a rejected sample: control 0) is not in control_us; the others are, apart
    from the put and the rest of the tick."""
    s = LoopStats(100)
    for k in range(100):
        s.record(100_000, 50_000, 20_000, 0 if k % 10 == 0 else (3_000 if k < 95 else 9_000))
    out = s.summary(0, fresh=True)
    ctl = out["control_us"]
    assert (ctl["p50"], ctl["max"]) == (3.0, 9.0) and ctl["mean"] == (85 * 3.0 + 5 * 9.0) / 90
    assert out["compute_us"]["p50"] == 30.0 and out["publish_us"]["p50"] == 20.0


def test_distributions_skip_the_zeros_and_need_no_temporaries():
    """period and control count only their entries > 0 (the first tick's period, ticks without a command), as
    nearest-rank percentiles of those; and a recompute over 100 000 ticks works in the ring made once: numpy's
    masks and partition copies took 3 MB a query window, served from the querying thread's glibc arena."""
    import tracemalloc

    import numpy as np

    rng = random.Random(5)
    s = LoopStats(100_000)
    ctl = [0 if rng.random() < 0.3 else rng.randint(1, 900) * 1000 for _ in range(100_000)]
    for k in range(100_000):
        s.record(0 if k == 0 else 100_000, rng.randint(1, 500) * 1000, 1000, ctl[k])
    pos = np.sort([c for c in ctl if c > 0])
    s.summary(0, fresh=True)  # the scratch ring is made here
    tracemalloc.start()
    try:
        out = s.summary(0, fresh=True)["control_us"]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    n = len(pos)
    assert out["p50"] == pos[int(0.5 * (n - 1))] / 1e3 and out["p99"] == pos[int(0.99 * (n - 1))] / 1e3
    assert out["mean"] == pytest.approx(pos.mean() / 1e3, rel=1e-12) and out["max"] == pos[-1] / 1e3
    assert peak < 64 * 1024
