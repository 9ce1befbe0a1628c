"""What the host took from this machine while a bench ran: steal time (Linux /proc/stat).

On a virtual machine the hypervisor runs other guests on the same physical cores; the time a vCPU was ready but
not running is counted as steal. A 10 kHz loop has 100 us per period, so a steal of a few tenths of a percent,
in slices of 100-200 us, is a floor for its overruns that no code in the guest can lower. Benches report it beside
their results so that two runs can be compared knowing what the host was doing.
"""

from __future__ import annotations

from pathlib import Path

_STAT = Path("/proc/stat")


def cpu_times() -> tuple[int, int] | None:
    """(steal, total) jiffies over all CPUs since boot; None where /proc/stat is missing."""
    try:
        first = _STAT.read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    if not first or first[0] != "cpu" or len(first) < 9:
        return None
    vals = [int(x) for x in first[1:9]]  # user nice system idle iowait irq softirq steal (guest is inside user)
    return vals[7], sum(vals)


class StealMeter:
    """Steal as a % of all CPU time between ``start()`` and ``stop()`` (``pct``; None if unknown); also
    ``with StealMeter() as m: ...``."""

    def __init__(self):
        self._t0 = None
        self.pct = None

    def start(self) -> StealMeter:
        self._t0 = cpu_times()
        return self

    def stop(self) -> float | None:
        t1 = cpu_times()
        if self._t0 is not None and t1 is not None and t1[1] > self._t0[1]:
            self.pct = round(100.0 * (t1[0] - self._t0[0]) / (t1[1] - self._t0[1]), 3)
        return self.pct

    def __enter__(self) -> StealMeter:
        return self.start()

    def __exit__(self, *exc) -> bool:
        self.stop()
        return False
