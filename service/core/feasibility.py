"""Interconnection-level feasibility (paper Sec. "Interconnection-level feasibility conditions").

Per window k of length T_s, from the neighbour's load forecast P_l in [P_min, P_max] and
dP_l/dt in [Pdot_min, Pdot_max] (paper Eqn IncomingIntRange):

    P^{r,in}    in [-P_max, -P_min]                                   (W)
    Qdot^{r,in} in [-Pdot_max, -Pdot_min] + (2/tau') [-P_max, P_max]  (W/s)
    tau' = min(10 L / R, 1 / K)                                       (s)

The printed equation adds (2/tau')[P_min, P_max]; it comes from Qdot^{r,in} = -dP/dt + 2 P (dv/dt)/v
(Eqn Qinj) with |dv/dt| / v <= 1/tau', whose sign is not fixed, so the symmetric interval is the sound
one. ``literal=True`` gives the printed one.

The component's own Z^{r,out}[k] is the range of its outgoing rates (P^{r,out}, Qdot^{r,out}) in the
window; the check (Eqn FeasibilityConds) is element-wise membership, and each excursion outside the
incoming range is a violation, recorded with its start time.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field


def tau_prime(L: float, R: float, K: float) -> float:
    """tau' = min(10 L/R, 1/K) (s); a zero R or K drops that term."""
    a = 10.0 * L / R if R > 0 else math.inf
    b = 1.0 / K if K > 0 else math.inf
    return min(a, b)


def announced_window(t: float, window_s: float) -> int:
    """The window whose range a message sent at t (s) carries (topic .../z): the current one during its first
    half, the next one during its second half, so a neighbour holds each window's range half a window before it
    starts (window 0: from the first message on)."""
    k = int(t // window_s)
    return k + 1 if t - k * window_s >= 0.5 * window_s else k


def load_box(P_lo: float, P_hi: float, Pdot_lo: float, Pdot_hi: float, margin: float = 0.0
             ) -> tuple[float, float, float, float]:
    """A forecast box widened by ``margin`` of its largest magnitude on each side (paper: T_s = 1 s windows)."""
    span, dspan = max(abs(P_lo), abs(P_hi)) * margin, max(abs(Pdot_lo), abs(Pdot_hi)) * margin
    return P_lo - span, P_hi + span, Pdot_lo - dspan, Pdot_hi + dspan


def incoming_range(P_min: float, P_max: float, Pdot_min: float, Pdot_max: float, tau_p: float,
                   literal: bool = False) -> tuple[float, float, float, float]:
    """(P_lo, P_hi, Qdot_lo, Qdot_hi) of the incoming interaction variable for one window."""
    g = 2.0 / tau_p
    lo_off = g * P_min if literal else -g * max(abs(P_min), abs(P_max))
    hi_off = g * P_max if literal else g * max(abs(P_min), abs(P_max))
    return -P_max, -P_min, -Pdot_max + lo_off, -Pdot_min + hi_off


@dataclass
class Violation:
    t: float  # s, start of the excursion
    element: str  # "P" or "Qdot"
    value: float
    lo: float
    hi: float


@dataclass
class WindowRange:
    k: int
    z_in: tuple[float, float, float, float]
    z_out: list[float] = field(default_factory=lambda: [math.inf, -math.inf, math.inf, -math.inf])
    rel_tol: float = 1e-9

    def __post_init__(self) -> None:
        # z_in widened by rel_tol of each element's largest magnitude (at least 1): what a sample is checked against
        P_lo, P_hi, Q_lo, Q_hi = self.z_in
        tP = self.rel_tol * max(abs(P_lo), abs(P_hi), 1.0)
        tQ = self.rel_tol * max(abs(Q_lo), abs(Q_hi), 1.0)
        self.bounds = (P_lo - tP, P_hi + tP, Q_lo - tQ, Q_hi + tQ)

    @property
    def inside(self) -> bool:
        P_lo, P_hi, Q_lo, Q_hi = self.z_in
        o = self.z_out
        return P_lo <= o[0] and o[1] <= P_hi and Q_lo <= o[2] and o[3] <= Q_hi


class FeasibilityMonitor:
    """Tracks Z^{r,out}[k] against Z^{r,in}[k] sample by sample; no I/O."""

    MAX_VIOLATIONS = 1000  # the first ones are kept; all are counted

    def __init__(self, window_s: float, rel_tol: float = 1e-9, keep_windows: int | None = None,
                 keep_recent: int | None = None):
        """keep_windows, keep_recent: a long-running user (the daemon) keeps only the most recent windows and
        violations (its memory stays flat); otherwise the first MAX_VIOLATIONS are kept."""
        self.window_s = window_s
        self.rel_tol = rel_tol
        self.keep_windows = keep_windows
        self.windows: dict[int, WindowRange] = {}
        # the first MAX_VIOLATIONS, or (keep_recent) the newest keep_recent: a deque drops its oldest itself
        self._keep_first = keep_recent is None
        self.violations: list[Violation] | deque[Violation] = [] if self._keep_first else deque(maxlen=keep_recent)
        self._outside = {"P": False, "Qdot": False}
        self.count = 0
        self._cur_k: int | None = None  # the window update last looked up, and its record (None: no range)
        self._cur: WindowRange | None = None

    def set_range(self, k: int, z_in: tuple[float, float, float, float]) -> None:
        self.windows[k] = WindowRange(k, z_in, rel_tol=self.rel_tol)
        self._cur_k = None  # update looks it up again
        if self.keep_windows is not None and len(self.windows) > self.keep_windows:
            for old in sorted(self.windows)[: len(self.windows) - self.keep_windows]:
                del self.windows[old]

    def update(self, t: float, P_out: float, Qdot_out: float) -> None:
        """One sample of the outgoing rates P^{r,out} (W) and Qdot^{r,out} (W/s) at time t (s). Called every tick:
        the window's record is looked up when the window changes, and a violation is written only when an
        element leaves its range."""
        k = int(t // self.window_s)
        if k != self._cur_k:
            self._cur_k, self._cur = k, self.windows.get(k)
        w = self._cur
        if w is None:
            return  # no forecast for this window: nothing to check against
        o = w.z_out
        if P_out < o[0]:
            o[0] = P_out
        if P_out > o[1]:
            o[1] = P_out
        if Qdot_out < o[2]:
            o[2] = Qdot_out
        if Qdot_out > o[3]:
            o[3] = Qdot_out
        P_lo, P_hi, Q_lo, Q_hi = w.bounds
        out_P = not P_lo <= P_out <= P_hi
        out_Q = not Q_lo <= Qdot_out <= Q_hi
        if out_P and not self._outside["P"]:
            self._violation(t, "P", P_out, w.z_in[0], w.z_in[1])
        if out_Q and not self._outside["Qdot"]:
            self._violation(t, "Qdot", Qdot_out, w.z_in[2], w.z_in[3])
        self._outside["P"], self._outside["Qdot"] = out_P, out_Q

    def _violation(self, t: float, name: str, x: float, lo: float, hi: float) -> None:
        if not self._keep_first or len(self.violations) < self.MAX_VIOLATIONS:
            self.violations.append(Violation(t, name, x, lo, hi))
        self.count += 1
