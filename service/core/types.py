"""Plain value types that cross the core's boundary (no behaviour, no I/O)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(slots=True)
class Sample:
    """One measurement as the controller sees it (SI units)."""

    seq: int
    t: float  # s
    i: float  # A, source-branch current
    v: float  # V, terminal voltage
    u: float  # V, source voltage
    i_load: float  # A, load current i_2


@dataclass(slots=True)
class Incoming:
    """Incoming interaction variable rates: P^{r,in} = -sum_j P_j^{r,out} (paper Eqn PsiMap)."""

    P_r_in: float  # W
    P_r_in_dot: float  # W/s
