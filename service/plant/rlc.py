"""The physics: RLC source branch feeding a constant-power load, and its sensor chain.

Used by the offline simulator and by the hardware-in-the-loop stand-in, so both produce the same
trajectory for the same commands. No clocks, no I/O.

    L di/dt = u + u_m - R i - v          (u_m: optional matched disturbance voltage, V)
    C dv/dt = i - i_2,   i_2 = P_l / v    (constant-power load; below v_cpl_min it is a resistor)
    du/dt   = r                           (commanded voltage rate, V/s, held over a control period;
                                           u stays inside the source's [u_min, u_max])

With a current limit i_max (plant.source.i_max_A) the converter drives no more than |i| = i_max: while |i| is at the
limit and the branch voltage u + u_m - R i - v would push it further, di/dt = 0 (the converter's current loop
takes over from its voltage command; u stays the commanded voltage), and every RK4 stage's current and each step's
result are held inside [-i_max, i_max]. docs/control.md (the plant) says why this model.
"""

from __future__ import annotations

import math

import numpy as np

from schemas.scenario import PlantConfig, SensorConfig
from service.core.types import Sample
from service.plant.profiles import Profile


def load_current(P_W: float, v_V: float, v_min_V: float) -> float:
    """i_2 (A) drawn by a constant-power load P_W at terminal voltage v_V; resistive below v_min_V."""
    if v_V >= v_min_V:
        return P_W / v_V
    return P_W * v_V / (v_min_V * v_min_V)


class RLCPlant:
    """Fixed-step RK4 integration of the circuit; state t (s), i (A), v (V), u (V)."""

    __slots__ = ("R", "L", "C", "u_min", "u_max", "i_max", "v_min", "load", "dist", "t", "i", "v", "u", "_steps")

    def __init__(self, cfg: PlantConfig, load: Profile, disturbance: Profile | None = None, impl: str = "auto"):
        """impl: the integrator, "c" (compiled, bit-identical), "python" (rk4_steps) or "auto" (c if built)."""
        self._steps = integrator(impl)
        self.R, self.L, self.C = cfg.R_ohm, cfg.L_H, cfg.C_F
        self.u_min, self.u_max = cfg.source.u_min_V, cfg.source.u_max_V
        self.i_max = cfg.source.i_max_A if cfg.source.i_max_A is not None else math.inf  # inf: no limit
        self.v_min = cfg.v_cpl_min_V
        self.load, self.dist = load, disturbance
        ini = cfg.initial
        self.t = 0.0
        self.i, self.v = float(ini.i_A), float(ini.v_V)
        u0 = ini.u_V if ini.u_V is not None else ini.v_V + cfg.R_ohm * ini.i_A
        self.u = min(max(float(u0), self.u_min), self.u_max)

    def u_m(self, t: float) -> float:
        return self.dist.value(t) if self.dist is not None else 0.0

    def advance(self, r: float, T: float, n_sub: int) -> None:
        """Integrate over T seconds with constant commanded rate r (V/s) in n_sub RK4 steps.

        The load power and disturbance are evaluated at the period's two ends and taken linear in
        between (a 13 Hz load over 100 us deviates from its chord by < 1e-5 relative).
        """
        R, L, C, vmin = self.R, self.L, self.C, self.v_min
        umin, umax = self.u_min, self.u_max
        h = T / n_sub
        t, i, v, u = self.t, self.i, self.v, self.u
        Pa = self.load.value(t)
        Pb = self.load.value(t + T)
        dP = (Pb - Pa) / n_sub
        if self.dist is not None:
            ma = self.dist.value(t)
            dm = (self.dist.value(t + T) - ma) / n_sub
        else:
            ma = dm = 0.0
        u_end = u + r * T
        clip = not (umin <= u <= umax and umin <= u_end <= umax)
        self.i, self.v, self.u = self._steps(R, L, C, vmin, umin, umax, float(clip), r, h, float(n_sub), Pa, dP, ma,
                                             dm, i, v, u, self.i_max)
        self.t = t + T


def rk4_steps(R: float, L: float, C: float, vmin: float, umin: float, umax: float, clip: float, r: float, h: float,
              n_sub: float, Pa: float, dP: float, ma: float, dm: float, i: float, v: float,
              u: float, imax: float = math.inf) -> tuple[float, float, float]:
    """RLCPlant.advance's integration: n_sub RK4 steps of h seconds from (i, v, u) at source rate r (V/s), load
    power Pa + k dP at substep k (W), disturbance ma + k dm (V); u clipped to [umin, umax] when clip; the source
    current held within [-imax, imax] (A; inf: no limit) as the module docstring says. The compiled twin
    (service/plant/rk4.c plant_steps) does the same operations in the same order."""
    hh = 0.5 * h
    vmin2 = vmin * vmin
    lim = imax != math.inf
    for k in range(int(n_sub)):
        P0 = Pa + k * dP
        P1 = P0 + dP
        Pm = P0 + 0.5 * dP
        m0 = ma + k * dm
        mm = m0 + 0.5 * dm
        m1 = m0 + dm
        # the source ramps at r and is clipped to its range (exact for u)
        if clip:
            um_ = min(max(u + r * hh, umin), umax)
            ub = min(max(u + r * h, umin), umax)
        else:
            um_ = u + r * hh
            ub = u + r * h
        # k1
        i2 = P0 / v if v >= vmin else P0 * v / vmin2
        ki1 = (u + m0 - R * i - v) / L
        if lim and (i >= imax and ki1 > 0.0 or i <= -imax and ki1 < 0.0):
            ki1 = 0.0
        kv1 = (i - i2) / C
        # k2
        ii = i + hh * ki1
        if lim:
            ii = min(max(ii, -imax), imax)
        vv = v + hh * kv1
        i2 = Pm / vv if vv >= vmin else Pm * vv / vmin2
        ki2 = (um_ + mm - R * ii - vv) / L
        if lim and (ii >= imax and ki2 > 0.0 or ii <= -imax and ki2 < 0.0):
            ki2 = 0.0
        kv2 = (ii - i2) / C
        # k3
        ii = i + hh * ki2
        if lim:
            ii = min(max(ii, -imax), imax)
        vv = v + hh * kv2
        i2 = Pm / vv if vv >= vmin else Pm * vv / vmin2
        ki3 = (um_ + mm - R * ii - vv) / L
        if lim and (ii >= imax and ki3 > 0.0 or ii <= -imax and ki3 < 0.0):
            ki3 = 0.0
        kv3 = (ii - i2) / C
        # k4
        ii = i + h * ki3
        if lim:
            ii = min(max(ii, -imax), imax)
        vv = v + h * kv3
        i2 = P1 / vv if vv >= vmin else P1 * vv / vmin2
        ki4 = (ub + m1 - R * ii - vv) / L
        if lim and (ii >= imax and ki4 > 0.0 or ii <= -imax and ki4 < 0.0):
            ki4 = 0.0
        kv4 = (ii - i2) / C
        i += h / 6.0 * (ki1 + 2.0 * ki2 + 2.0 * ki3 + ki4)
        if lim:
            i = min(max(i, -imax), imax)
        v += h / 6.0 * (kv1 + 2.0 * kv2 + 2.0 * kv3 + kv4)
        u = ub
    return i, v, u


def integrator(impl: str = "auto"):
    """The RK4 integrator: the compiled twin for "c" (ImportError if not built), the Python reference for
    "python", and for "auto" the compiled one when it was built."""
    return pick_twin(impl, rk4_steps, "plant_steps", "plant integrator")


def pick_twin(impl: str, reference, compiled_name: str, what: str):
    """``reference`` (a Python function) or its compiled twin ``service._kernel.<compiled_name>``: "python" the
    reference, "c" the twin (ImportError naming ``what`` if it was not built), "auto" the twin when built."""
    if impl not in ("auto", "c", "python"):
        raise ValueError(f"plant implementation {impl!r}: expected auto, c or python")
    if impl == "python":
        return reference
    try:
        from service import _kernel
    except ImportError as e:
        if impl == "c":
            raise ImportError(f"the compiled {what} (service._kernel) is not built: {e}") from e
        return reference
    return getattr(_kernel, compiled_name)


class CommandSchedule:
    """Which du/dt acts over each period, from the commands that arrived (pure: no clock, no I/O).

    The command answering sample j acts over period j + d (d = 0 in lockstep and in sim, where the delay line comes
    first and this then takes the command for its period).
    A command missing at its period (late or lost) is replaced by the plan its predecessor carried (du_dt_next,
    which is for exactly that period); with neither, the source holds its voltage (du/dt = 0). A command arriving
    after its period is dropped and counted late, but its plan still serves the period after. ``counts``:
    late, planned_periods, stale_periods (periods with neither)."""

    def __init__(self, d: int):
        self.d = d
        self.inbox: dict[int, tuple[float, float]] = {}  # seq answered -> (du/dt, planned du/dt)
        self.prev = (-1, 0.0)  # (seq, plan) of the newest command taken, in time or late
        self.counts = {"late": 0, "planned_periods": 0, "stale_periods": 0}

    def arrive(self, seq: int, du_dt: float, du_dt_next: float) -> None:
        self.inbox[seq] = (du_dt, du_dt_next)

    def take(self, k: int) -> tuple[float, bool]:
        """(du/dt over period k, whether it is the command meant for k rather than a plan or a hold)."""
        j = k - self.d
        got = self.inbox.pop(j, None)
        for old in [q for q in self.inbox if q < j]:
            late = self.inbox.pop(old)
            self.counts["late"] += 1
            if old == j - 1:  # too late for its own period, in time to plan this one
                self.prev = (old, late[1])
        if got is not None:
            self.prev = (j, got[1])
            return got[0], True
        return self.fallback(j), False

    def fallback(self, j: int) -> float:
        """du/dt for the period of a missing command answering sample j: the plan of the one answering j - 1 if it
        came, else 0 (hold)."""
        if self.prev[0] == j - 1:
            self.counts["planned_periods"] += 1
            return self.prev[1]
        self.counts["stale_periods"] += 1
        return 0.0


class CommandChannel:
    """The seeded disturbances of timing (CommandDisturbances) on one source's commands, between its delay line and
    its CommandSchedule (pure: no clock, no I/O). ``deliver(sched, k, t, cmd)`` hands the command for period k (or
    None: none came) to the schedule as the disturbances say and returns the rate applied over period k (V/s):
    lost or in an outage, it never arrives; late, it arrives after its period was taken (its plan still serves the
    next); else in time. seed: the streams' key (a list of ints); each kind draws from its own stream."""

    def __init__(self, tm, seed: list[int]):
        self.loss, self.outages = tm.command_loss, tm.command_outages
        self.late_p, self.late_windows = tm.command_late, tm.command_late_windows
        self.loss_rng = np.random.default_rng([*seed, 0xC0DE])  # sensor noise stays the same
        self.late_rng = np.random.default_rng([*seed, 0x1A7E])  # and the losses stay the same with lateness on

    def deliver(self, sched: CommandSchedule, k: int, t: float, cmd: tuple[float, float] | None) -> float:
        late = False
        if cmd is not None and not (self.outages and any(a <= t < a + w for a, w in self.outages)) and not (
                self.loss and self.loss_rng.random() < self.loss):
            late = bool(self.late_p and self.late_rng.random() < self.late_p) or \
                bool(self.late_windows) and any(a <= t < a + w for a, w in self.late_windows)
            if not late:
                sched.arrive(k, *cmd)
        r = sched.take(k)[0]
        if late:
            sched.arrive(k, *cmd)
        return r


class Sensor:
    """Seeded white noise and quantisation on i, v, u, i_load; drawn in blocks (same stream everywhere)."""

    BLOCK = 4096

    def __init__(self, cfg: SensorConfig, seed: int):
        self.sv, self.si = cfg.noise_v_V, cfg.noise_i_A
        self.qv, self.qi = cfg.lsb_v_V, cfg.lsb_i_A
        self.rng = np.random.default_rng(seed)
        self.noisy = self.sv > 0 or self.si > 0
        self._buf: list[float] = []
        self._k = 0

    def _next4(self) -> tuple[float, float, float, float]:
        k = self._k
        if k + 4 > len(self._buf):
            self._buf = self.rng.standard_normal(self.BLOCK * 4).tolist()
            k = 0
        self._k = k + 4
        b = self._buf
        return b[k], b[k + 1], b[k + 2], b[k + 3]

    def measure(self, seq: int, t: float, i: float, v: float, u: float, i_load: float) -> Sample:
        if self.noisy:
            n0, n1, n2, n3 = self._next4()
            i += self.si * n0
            v += self.sv * n1
            u += self.sv * n2
            i_load += self.si * n3
        if self.qi > 0:
            i = self.qi * math.floor(i / self.qi + 0.5)
            i_load = self.qi * math.floor(i_load / self.qi + 0.5)
        if self.qv > 0:
            v = self.qv * math.floor(v / self.qv + 0.5)
            u = self.qv * math.floor(u / self.qv + 0.5)
        return Sample(seq, t, i, v, u, i_load)
