"""Scalar time profiles: value(t) and its time derivative, for loads (W) and disturbances (V)."""

from __future__ import annotations

import bisect
import csv
import math
from array import array
from pathlib import Path

import numpy as np

from schemas.scenario import ProfileConfig

TWO_PI = 2.0 * math.pi


class Profile:
    """A scalar signal: its kind's base (constant, steps, sines, both, csv), plus an optional seeded
    Ornstein-Uhlenbeck term, gated by on/off switching (0 while off). ``value(t)`` and ``rate(t)`` (unit/s) are exact
    and deterministic: the same table gives the same numbers in every process."""

    def __init__(self, cfg: ProfileConfig, base_dir: str = "."):
        self.kind = cfg.kind
        self.offset = cfg.value
        self.sines = ([(c.amplitude, TWO_PI * c.freq_hz, c.phase_rad) for c in cfg.components]
                      if cfg.kind in ("sines", "combined") else [])
        self.stepped = cfg.kind in ("steps", "combined")
        if self.stepped:
            self.times = [float(t) for t, _ in cfg.steps]
            self.values = [float(v) for _, v in cfg.steps]
        elif cfg.kind == "csv":
            self.times, self.values = _read_csv(Path(base_dir) / str(cfg.csv_path))
        else:
            self.times, self.values = [], []
        self.ou = OUPath(cfg.ou.sigma, cfg.ou.tau_s, cfg.ou.seed, cfg.ou.grid_s) if cfg.ou is not None else None
        switches = sorted([(float(t), False) for t in cfg.off_at_s] + [(float(t), True) for t in cfg.on_at_s])
        self.switch_times = [t for t, _ in switches]
        self.switch_on = [on for _, on in switches]

    def on(self, t: float) -> bool:
        """Whether it is switched on at t (on before its first switching time)."""
        j = bisect.bisect_right(self.switch_times, t)
        return j == 0 or self.switch_on[j - 1]

    def value(self, t: float) -> float:
        if self.switch_times and not self.on(t):
            return 0.0
        k = self.kind
        if k == "constant":
            s = self.offset
        elif k == "csv":
            s = _interp(self.times, self.values, t)
        else:
            if self.stepped:
                j = bisect.bisect_right(self.times, t)
                s = self.offset if j == 0 else self.values[j - 1]
            else:
                s = self.offset
            for a, w, ph in self.sines:
                s += a * math.sin(w * t + ph)
        if self.ou is not None:
            s += self.ou.value(t)
        return s

    def rate(self, t: float) -> float:
        if self.switch_times and not self.on(t):
            return 0.0
        s = 0.0
        for a, w, ph in self.sines:
            s += a * w * math.cos(w * t + ph)
        if self.kind == "csv":
            s += _slope(self.times, self.values, t)
        if self.ou is not None:
            s += self.ou.rate(t)
        return s  # the steps are piecewise constant

    def event_times(self) -> list[float]:
        """When it jumps (s): its steps and its switching on or off."""
        return sorted({*(self.times if self.stepped else ()), *self.switch_times})

    def range_over(self, t0: float, t1: float, n: int = 400) -> tuple[float, float, float, float]:
        """(min, max, min rate, max rate) over [t0, t1]: sampled on n points, at every jump (and just before it), and
        for the piecewise-linear parts (csv, the OU term) at every breakpoint, where their extremes are, and at both
        ends and the middle of every segment, where their slopes are."""
        ts = [t0 + (t1 - t0) * k / n for k in range(n + 1)]
        jumps = [t for t in self.event_times() if t0 < t <= t1]
        kinks = [t for t in self.times if t0 <= t <= t1] if self.kind == "csv" else []
        if self.ou is not None:
            kinks = sorted(kinks + self.ou.grid_over(t0, t1))
        mids = [0.5 * (a + b) for a, b in zip(kinks, kinks[1:], strict=False)]
        ts += jumps + kinks + mids
        vals = [self.value(t) for t in ts] + [self.value(max(t0, t - 1e-12)) for t in jumps]
        # a breakpoint's rate is its right segment's: the left one's just before it (far above the times' rounding)
        before = 1e-6 * (self.ou.h if self.ou is not None else 1e-3)
        rates = [self.rate(t) for t in ts] + [self.rate(t - before) for t in kinks if t - before >= t0]
        return min(vals), max(vals), min(rates), max(rates)


class OUPath:
    """An Ornstein-Uhlenbeck path x(t) (schemas.scenario.OUConfig): drawn from its seed on the grid k h by the exact
    discretisation, x[0] = 0, in blocks as far as it is asked for (the same blocks in the same order whatever the
    order of the questions), linear in between; rate(t) is the slope of the segment that value(t) lies on."""

    BLOCK = 4096

    def __init__(self, sigma: float, tau_s: float, seed: int, grid_s: float):
        self.h = grid_s
        self.a = math.exp(-grid_s / tau_s)
        self.b = sigma * math.sqrt(1.0 - self.a * self.a)
        self.rng = np.random.default_rng([seed, 0x0C])
        self.x = array("d", [0.0])  # 8 B a grid point: 29 MB for an hour on a 1 ms grid

    def _segment(self, t: float) -> int:
        """The index j of the segment [j h, (j + 1) h] holding t (> 0), the path drawn that far."""
        j = int(t / self.h)
        x, a, b = self.x, self.a, self.b
        while len(x) < j + 2:
            last = x[-1]
            block = []
            for z in self.rng.standard_normal(self.BLOCK).tolist():
                last = a * last + b * z
                block.append(last)
            x.extend(block)
        return j

    def value(self, t: float) -> float:
        if t <= 0.0:
            return 0.0
        j = self._segment(t)
        x0 = self.x[j]
        return x0 + (self.x[j + 1] - x0) * (t - j * self.h) / self.h

    def rate(self, t: float) -> float:
        if t < 0.0:
            return 0.0
        j = self._segment(t)
        return (self.x[j + 1] - self.x[j]) / self.h

    def grid_over(self, t0: float, t1: float) -> list[float]:
        """The grid points in [t0, t1] (s)."""
        k0 = max(0, math.ceil(t0 / self.h))
        return [k * self.h for k in range(k0, int(t1 / self.h) + 1) if t0 <= k * self.h <= t1]


def _interp(ts: list[float], vs: list[float], t: float) -> float:
    if t <= ts[0]:
        return vs[0]
    if t >= ts[-1]:
        return vs[-1]
    j = bisect.bisect_right(ts, t)
    t0, t1 = ts[j - 1], ts[j]
    return vs[j - 1] + (vs[j] - vs[j - 1]) * (t - t0) / (t1 - t0)


def _slope(ts: list[float], vs: list[float], t: float) -> float:
    """The slope of the piecewise-linear (ts, vs) at t: its segment's (0 outside)."""
    j = bisect.bisect_right(ts, t)
    if j == 0 or j >= len(ts):
        return 0.0
    return (vs[j] - vs[j - 1]) / (ts[j] - ts[j - 1])


def _read_csv(path: Path) -> tuple[list[float], list[float]]:
    try:
        with open(path, newline="") as f:
            rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")]
    except OSError as e:
        raise ValueError(f"load.csv_path: cannot read {path}: {e.strerror}") from None
    if rows and not _is_number(rows[0][0]):
        rows = rows[1:]  # header
    ts, vs = [], []
    for n, r in enumerate(rows, 1):
        if len(r) < 2 or not (_is_number(r[0]) and _is_number(r[1])):
            raise ValueError(f"load.csv_path: {path} row {n}: expected two numbers t_s,value")
        ts.append(float(r[0]))
        vs.append(float(r[1]))
    if len(ts) < 2 or any(b <= a for a, b in zip(ts, ts[1:], strict=False)):
        raise ValueError(f"load.csv_path: {path}: need >= 2 rows with strictly increasing t_s")
    return ts, vs


def _is_number(s: str) -> bool:
    try:
        return math.isfinite(float(s))
    except ValueError:
        return False
