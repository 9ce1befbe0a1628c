"""What the host took from this machine while a bench ran: steal time (Linux /proc/stat); and how busy its CPUs
were, and what one process used of them (the CPU budget a realtime stack runs in).

On a virtual machine the hypervisor runs other guests on the same physical cores; the time a vCPU was ready but
not running is counted as steal. A 10 kHz loop has 100 us per period, so a steal of a few tenths of a percent,
in slices of 100-200 us, is a floor for its overruns that no code in the guest can lower. Benches report it beside
their results so that two runs can be compared knowing what the host was doing.
"""

from __future__ import annotations

import time
from pathlib import Path

_STAT = Path("/proc/stat")


def cpu_times() -> tuple[int, int] | None:
    """(steal, total) jiffies over all CPUs since boot; None where /proc/stat is missing."""
    t = _cpu_line()
    return None if t is None else (t[7], sum(t))


def _cpu_line() -> list[int] | None:
    """user nice system idle iowait irq softirq steal jiffies over all CPUs since boot (guest time is inside user)."""
    try:
        first = _STAT.read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    if not first or first[0] != "cpu" or len(first) < 9:
        return None
    return [int(x) for x in first[1:9]]


class StealMeter:
    """Steal as a % of all CPU time between ``start()`` and ``stop()`` (``pct``; None if unknown), and the CPUs'
    busy time (user, nice, system, irq, softirq; not idle, iowait or steal) as a % of it (``busy_pct``: 100 means
    every CPU busy the whole time); also ``with StealMeter() as m: ...``."""

    def __init__(self):
        self._t0 = None
        self.pct = None
        self.busy_pct = None

    def start(self) -> StealMeter:
        self._t0 = _cpu_line()
        return self

    def stop(self) -> float | None:
        t1, t0 = _cpu_line(), self._t0
        if t0 is not None and t1 is not None and sum(t1) > sum(t0):
            d = [b - a for a, b in zip(t0, t1, strict=True)]
            total = sum(d)
            self.pct = round(100.0 * d[7] / total, 3)
            self.busy_pct = round(100.0 * (d[0] + d[1] + d[2] + d[5] + d[6]) / total, 2)
        return self.pct

    def __enter__(self) -> StealMeter:
        return self.start()

    def __exit__(self, *exc) -> bool:
        self.stop()
        return False


class ProcessCpu:
    """The CPU time this process (all its threads) used between ``start()`` and ``stop()``, as a % of one CPU over
    the same wall time (``pct``: 150 is one and a half CPUs). Two clock reads each end: cheap enough around a run,
    not for a hot path."""

    def __init__(self):
        self._c0 = self._w0 = 0.0
        self.pct: float | None = None

    def start(self) -> ProcessCpu:
        self._c0, self._w0 = time.process_time(), time.monotonic()
        return self

    def stop(self) -> float | None:
        wall = time.monotonic() - self._w0
        if wall > 0:
            self.pct = round(100.0 * (time.process_time() - self._c0) / wall, 1)
        return self.pct
