"""The loop's time statistics: period and execution time of the last N ticks in preallocated rings, and the
counters status reports. Recorded on the loop thread without allocating; summarised on a query thread."""

from __future__ import annotations

import time
from array import array

import numpy as np

STATS_EVERY_NS = 250_000_000  # and the loop's time distributions at most this often
CPU_EVERY_MASK = 1023  # the loop reads the process's CPU time every 1024 ticks (LoopStats.cpu_pct)
HIST = 2048  # ticks of command history for the measured loop delay (a power of two)


class LoopStats:
    """Period and execution time of the last N ticks (ns) in preallocated rings, plus counters."""

    def __init__(self, n: int):
        self.n = n
        self.period = array("q", bytes(8 * n))
        self.exec = array("q", bytes(8 * n))
        self.publish = array("q", bytes(8 * n))  # of exec: the command's put (Zenoh's own work on this thread)
        # of exec: the control computation, from the accepted sample to the command ready to put (reference, core
        # step, command payload, recorder slot): ros2_control's update() between read() and write(); 0 = none
        self.control = array("q", bytes(8 * n))
        self.k = 0
        self.ticks = 0
        self.overruns = 0  # whole periods skipped because a tick ran late
        self.no_new_sample = 0  # clock ticks that found no new measurement
        self.missing_samples = 0  # gaps in the measurement sequence
        self.lockstep_timeouts = 0
        self.window_exec_max = self.window_period_max = 0  # since the last loop record
        self._dist: tuple[int, dict] | None = None  # (when, distributions): see summary
        self._scratch: np.ndarray | None = None  # the distributions' working ring (_distributions)
        # the process's CPU time (all threads: the loop, Zenoh's, queries) and the wall time (s), at the first tick
        # and every CPU_EVERY_MASK + 1 ticks since: cpu_pct in summary() is its share of one CPU while ticks came
        self._cpu0 = self._cpu1 = (0.0, 0.0)

    def record(self, period_ns: int, exec_ns: int, publish_ns: int = 0, control_ns: int = 0) -> None:
        k = self.k
        self.period[k] = period_ns
        self.exec[k] = exec_ns
        self.publish[k] = publish_ns
        self.control[k] = control_ns
        self.k = k + 1 if k + 1 < self.n else 0
        self.ticks += 1
        if self.ticks & CPU_EVERY_MASK == 1:  # two clock reads every CPU_EVERY_MASK + 1 ticks
            mark = (time.process_time(), time.monotonic())
            if self.ticks == 1:
                self._cpu0 = mark
            self._cpu1 = mark
        if exec_ns > self.window_exec_max:
            self.window_exec_max = exec_ns
        if period_ns > self.window_period_max:
            self.window_period_max = period_ns

    def summary(self, now_ns: int, fresh: bool = False) -> dict:
        """Counters as they are now; the distributions (mean, p50, p99, max of the last n ticks, ns -> us) computed
        on the caller's thread with numpy on the raw buffers (no per-sample Python objects: sorting 100 000 Python
        ints per query fragmented the heap and grew RSS ~3 MB/min at 100 Hz), and reused while younger than
        STATS_EVERY_NS unless ``fresh``. Over 100 000 ticks they take ~5 ms here, mostly holding the GIL the loop
        needs; at 100 status queries a second, recomputed each time, that was 18 ms a query and more than a core.
        Percentiles are nearest-rank (the value at index floor(q * (m - 1)) of the sorted window)."""
        m = min(self.ticks, self.n)
        out = {"ticks": self.ticks, "overruns": self.overruns, "no_new_sample": self.no_new_sample,
               "missing_samples": self.missing_samples, "lockstep_timeouts": self.lockstep_timeouts,
               "overrun_pct": 100.0 * self.overruns / max(1, self.ticks + self.overruns),
               "cpu_pct": self.cpu_pct()}
        cached = self._dist
        if fresh or cached is None or now_ns - cached[0] >= STATS_EVERY_NS:
            cached = self._dist = (now_ns, self._distributions(m))
        out.update(cached[1])
        return out

    def cpu_pct(self) -> float | None:
        """The process's CPU time as a % of one CPU between the first tick's mark and the latest (one every
        CPU_EVERY_MASK + 1 ticks; None before two marks): 100 is a whole CPU, and on this 2-CPU machine 200 is all
        of it."""
        wall = self._cpu1[1] - self._cpu0[1]
        return round(100.0 * (self._cpu1[0] - self._cpu0[0]) / wall, 1) if wall > 0 else None

    def _distributions(self, m: int) -> dict:
        """mean, p50, p99 and max (us) of each ring over its m filled ticks, computed in one scratch ring made once:
        numpy's partition and masks made 800 KB temporaries for each distribution at 100 000 ticks, 3 MB per
        recompute, which glibc served from the querying thread's arena once its mmap threshold had risen
        (docs/decisions, the scratch ring)."""
        if self._scratch is None:
            self._scratch = np.empty(self.n, dtype=np.int64)
        ex = np.frombuffer(self.exec, dtype=np.int64)[:m]
        pub = np.frombuffer(self.publish, dtype=np.int64)[:m]
        per = np.frombuffer(self.period, dtype=np.int64)[:m]
        ctl = np.frombuffer(self.control, dtype=np.int64)[:m]
        out = {}
        # exec_us: the whole tick; publish_us: its command put; compute_us: the rest (read, checks, core, record);
        # control_us: of compute, the control computation alone (ticks that computed a command)
        for name, src, positive in (("period_us", per, True), ("exec_us", ex, False), ("publish_us", pub, False),
                                    ("compute_us", None, False), ("control_us", ctl, True)):
            vals = self._scratch[:m]
            if src is None:
                np.subtract(ex, pub, out=vals)
            else:
                vals[:] = src
            # positive: only the entries > 0 count (0: the first tick's period, a tick with no command). The values
            # are never negative, so the z zeros sort first, and the positives' ranks are z on (no mask, no copy)
            n = int(np.count_nonzero(vals)) if positive else m
            if n:
                z = m - n
                k = [z + int(0.5 * (n - 1)), z + int(0.99 * (n - 1))]
                mean, top = float(vals.sum()) / n, float(vals.max())
                vals.partition(k)  # in place, in the scratch ring
                out[name] = {"mean": mean / 1e3, "p50": float(vals[k[0]]) / 1e3, "p99": float(vals[k[1]]) / 1e3,
                             "max": top / 1e3}
        return out
