"""Scalar time profiles: value(t) and its time derivative, for loads (W) and disturbances (V)."""

from __future__ import annotations

import bisect
import csv
import math
from pathlib import Path

from schemas.scenario import ProfileConfig

TWO_PI = 2.0 * math.pi


class Profile:
    """Piecewise description of a scalar signal. ``value(t)`` and ``rate(t)`` (unit/s) are exact."""

    def __init__(self, cfg: ProfileConfig, base_dir: str = "."):
        self.kind = cfg.kind
        self.offset = cfg.value
        self.sines = [(c.amplitude, TWO_PI * c.freq_hz, c.phase_rad) for c in cfg.components]
        if cfg.kind == "steps":
            self.times = [float(t) for t, _ in cfg.steps]
            self.values = [float(v) for _, v in cfg.steps]
        elif cfg.kind == "csv":
            self.times, self.values = _read_csv(Path(base_dir) / str(cfg.csv_path))
        else:
            self.times, self.values = [], []

    def value(self, t: float) -> float:
        k = self.kind
        if k == "constant":
            return self.offset
        if k == "sines":
            s = self.offset
            for a, w, ph in self.sines:
                s += a * math.sin(w * t + ph)
            return s
        if k == "steps":
            j = bisect.bisect_right(self.times, t)
            return self.offset if j == 0 else self.values[j - 1]
        return _interp(self.times, self.values, t)

    def rate(self, t: float) -> float:
        k = self.kind
        if k == "sines":
            s = 0.0
            for a, w, ph in self.sines:
                s += a * w * math.cos(w * t + ph)
            return s
        if k == "csv":
            ts = self.times
            j = bisect.bisect_right(ts, t)
            if j == 0 or j >= len(ts):
                return 0.0
            return (self.values[j] - self.values[j - 1]) / (ts[j] - ts[j - 1])
        return 0.0  # constant and steps: piecewise constant

    def range_over(self, t0: float, t1: float, n: int = 400) -> tuple[float, float, float, float]:
        """(min, max, min rate, max rate) over [t0, t1], sampled on n points plus breakpoints."""
        ts = [t0 + (t1 - t0) * k / n for k in range(n + 1)]
        ts += [t for t in self.times if t0 <= t <= t1]
        vals = [self.value(t) for t in ts] + [self.value(max(t0, t - 1e-12)) for t in self.times if t0 < t <= t1]
        rates = [self.rate(t) for t in ts]
        return min(vals), max(vals), min(rates), max(rates)


def _interp(ts: list[float], vs: list[float], t: float) -> float:
    if t <= ts[0]:
        return vs[0]
    if t >= ts[-1]:
        return vs[-1]
    j = bisect.bisect_right(ts, t)
    t0, t1 = ts[j - 1], ts[j]
    return vs[j - 1] + (vs[j] - vs[j - 1]) * (t - t0) / (t1 - t0)


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
