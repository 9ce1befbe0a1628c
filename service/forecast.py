"""This component's outgoing interaction range Z^{r,out}[k], forecast ahead of window k.

Paper Sec. "Feed-forward checking of feasibility conditions": given the ranges of its incoming
interaction variable for window k (from the neighbours' forecasts), Sigma_1 "is to compute the ranges
of outgoing interaction variables using the definition in Eqn IntModelCommon given its local control
saturation and local predicted disturbance limits"; the window is feasible only if
Z^{r,out}[k] is inside Z^{r,in}[k] (Lemma "Feasibility of component interconnection", Eqn
FeasibilityConds). The paper leaves the numerical method open ("a topic of future research").

Ours: the closed loop itself (the same core and plant model every driver uses, noise-free, with the
configured loop delay, the controller's own u and du/dt limits) is run over the admissible load
trajectories that bound the forecast box P_l in [P_lo, P_hi], dP_l/dt in [Pdot_lo, Pdot_hi]:
from equilibrium at each end of the range, hold; ramp to the other end at the extreme admissible
rate, then hold; and (``steps=True``, the default: a load that can switch) jump to the other end,
then hold. Each run lasts the ramp plus ``settle_s``. The envelope over all runs, after the
estimator's warm-up, is the forecast:

    P^{r,out}    = -v i_2 = -P_l                       (the port identity: exact for a CPL)   W
    dP^{r,out}/dt = -dP_l/dt                                                                 W/s
    Qdot^{r,out} = Qdot_l + 2 (i dv/dt - v di/dt)      (estimator, Eqn IntModelCommon at the port) W/s

so the P parts are the negated box and the Qdot part carries the internal dynamics: the voltage
transients the controller allows when the load moves. Local saturation is an input of that computation, as
the paper has it ("given its local control saturation"): the runs carry the controller's own u and du/dt
limits, so a transient the slew limit shapes is inside the forecast range. The window is infeasible, with a
named reason, when the source voltage u reaches [u_min, u_max] (it cannot supply the box), when du/dt stays at
its limit for more than ``SLEW_LIMITED_MAX_S`` (2 ms) in one run (the source cannot follow the load), or when
v leaves +-25 % of v_ref (``V_BAND``: the divergence band). A fast law meets the slew limit for a few periods
on every large load step and rides through it (the nested law: 0.4-0.8 ms on the paper's 1 kW steps); any
tick at the limit counting as infeasible refused every such law, while a 1 kV/s slew limit holds it there for
tens of milliseconds. The terminal voltage's
range over the runs is reported beside the verdict (a transient, not a feasibility condition). Pure: no clocks,
no I/O.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, replace

from schemas.scenario import CircuitParams, ControllerConfig, PlantConfig, SourceLimits
from service.core import make_core
from service.core.feasibility import incoming_range
from service.core.types import Incoming, Sample
from service.plant.rlc import RLCPlant, load_current

V_BAND = 0.25  # a run whose v leaves +-25 % of v_ref diverged: the window is infeasible
SLEW_LIMITED_MAX_S = 2e-3  # longest time (s) one run may spend with du/dt at its limit

FORECAST_STEP_S = 5e-5  # plant integration step inside the forecast (s): 2 RK4 steps per 10 kHz period


class _PiecewiseLinear:
    """A load power P(t) (W) through (t, P) points, constant outside them; the plant's load interface."""

    __slots__ = ("pts",)

    def __init__(self, pts: list[tuple[float, float]]):
        self.pts = pts

    def value(self, t: float) -> float:
        pts = self.pts
        if t <= pts[0][0]:
            return pts[0][1]
        for (t0, p0), (t1, p1) in itertools.pairwise(pts):
            if t < t1:
                return p1 if t1 == t0 else p0 + (p1 - p0) * (t - t0) / (t1 - t0)
        return pts[-1][1]

    def rate(self, t: float) -> float:
        pts = self.pts
        for (t0, p0), (t1, p1) in itertools.pairwise(pts):
            if t0 <= t < t1:
                return (p1 - p0) / (t1 - t0)
        return 0.0


@dataclass(frozen=True)
class OutgoingForecast:
    """Z^{r,out}[k] (forecast), Z^{r,in}[k] (from the neighbours) and the verdict for one window."""

    P_lo: float  # W, P^{r,out}
    P_hi: float
    P_dot_lo: float  # W/s, dP^{r,out}/dt
    P_dot_hi: float
    Qdot_lo: float  # W/s, Qdot^{r,out}
    Qdot_hi: float
    z_in: tuple[float, float, float, float]  # (P_lo, P_hi, Qdot_lo, Qdot_hi) of Z^{r,in}[k], W and W/s
    v_lo: float  # V, terminal voltage over all runs after warm-up
    v_hi: float
    u_lo: float  # V, source voltage over all runs
    u_hi: float
    limited_ticks: int  # ticks at the du/dt or u limit
    runs: int
    steps: int  # control periods simulated in all
    saturation: str  # "" or the local saturation met (divergence, u at its limits, du/dt at its limit)
    feasible: bool
    reason: str  # "" when feasible, else what failed first

    def as_dict(self) -> dict:
        return asdict(self)

    def for_box(self, box: tuple[float, float, float, float], tau_p: float, literal: bool = False
                ) -> OutgoingForecast:
        """This forecast judged for a load box inside the one it was run for (a cached forecast of a widened
        box): P parts from the box itself (port identity), Qdot envelope and saturation as run (conservative),
        Z^{r,in} and the verdict from the box."""
        z_in = incoming_range(*box, tau_p, literal)
        reason = verdict(z_in, (-box[1], -box[0]), (self.Qdot_lo, self.Qdot_hi), self.saturation)
        return replace(self, P_lo=-box[1], P_hi=-box[0], P_dot_lo=-box[3], P_dot_hi=-box[2], z_in=z_in,
                       feasible=reason == "", reason=reason)


def verdict(z_in: tuple[float, float, float, float], P_out: tuple[float, float], Qdot_out: tuple[float, float],
            saturation: str = "") -> str:
    """Whether Z^{r,out} lies in Z^{r,in} element by element (paper Eqn FeasibilityConds): "" if it does and the
    source met no saturation, else what failed first. z_in: (P lo, P hi W, Qdot lo, Qdot hi W/s); P_out (W) and
    Qdot_out (W/s): the forecast's ranges; saturation: the forecast's own failure ("" none)."""
    if saturation:
        return saturation
    if P_out[0] < z_in[0] or P_out[1] > z_in[1]:
        return f"P^r,out [{P_out[0]:.4g}, {P_out[1]:.4g}] W is not inside P^r,in [{z_in[0]:.4g}, {z_in[1]:.4g}] W"
    if Qdot_out[0] < z_in[2] or Qdot_out[1] > z_in[3]:
        return (f"Qdot^r,out [{Qdot_out[0]:.4g}, {Qdot_out[1]:.4g}] W/s is not inside Qdot^r,in "
                f"[{z_in[2]:.4g}, {z_in[3]:.4g}] W/s")
    return ""


def trajectories(P_lo: float, P_hi: float, Pdot_lo: float, Pdot_hi: float, t0: float, settle_s: float,
                 steps: bool, max_ramp_s: float = math.inf) -> list[list[tuple[float, float]]]:
    """The admissible extreme load trajectories of the box, as (t, P) points starting at t0 (s); a ramp stops
    after max_ramp_s (the window ends first)."""
    out: list[list[tuple[float, float]]] = []
    span = P_hi - P_lo
    for a, b in ((P_lo, P_hi), (P_hi, P_lo)):
        out.append([(t0, a), (t0 + settle_s, a)])
        if span <= 0.0:
            continue
        rate = Pdot_hi if b > a else Pdot_lo
        if rate != 0.0 and (rate > 0.0) == (b > a):
            t_ramp = min(span / abs(rate), max_ramp_s)
            c = a + rate * t_ramp
            out.append([(t0, a), (t0 + t_ramp, c), (t0 + t_ramp + settle_s, c)])
        if steps:
            out.append([(t0, a), (t0, b), (t0 + settle_s, b)])
    if len(out) > 1 and span <= 0.0:
        out = out[:1]
    return out


def forecast_outgoing(controller: ControllerConfig, model: CircuitParams, period_s: float, delay_samples: int,
                      box: tuple[float, float, float, float], tau_p: float, *, steps: bool = True,
                      settle_s: float = 0.025, max_ramp_s: float = 1.0, literal: bool = False,
                      impl: str | None = None) -> OutgoingForecast:
    """Forecast Z^{r,out} for a window whose load box is (P_lo, P_hi, Pdot_lo, Pdot_hi) (W, W/s) and check it
    against Z^{r,in} = incoming_range(box, tau_p) (paper Eqn IncomingIntRange). A ramp longer than max_ramp_s
    (s; a window is no longer) is cut there."""
    P_lo, P_hi, Pdot_lo, Pdot_hi = box
    lim = controller.limits
    v_ref = controller.v_ref_V
    T = float(period_s)
    n_sub = max(1, math.ceil(T / FORECAST_STEP_S - 1e-9))
    t_warm = max(5.0 * controller.deriv_tau_s, 10 * T)  # the estimator's derivative history fills
    plant_cfg = PlantConfig(R_ohm=model.R_ohm, L_H=model.L_H, C_F=model.C_F,
                            source=SourceLimits(u_min_V=lim.u_min_V, u_max_V=lim.u_max_V))
    Q_lo = Q_hi = 0.0
    v_lo = u_lo = math.inf
    v_hi = u_hi = -math.inf
    limited = n_steps = worst_limited = 0
    reason = ""
    runs = trajectories(P_lo, P_hi, Pdot_lo, Pdot_hi, t_warm, settle_s, steps, max_ramp_s)
    for pts in runs:
        load = _PiecewiseLinear(pts)
        plant = RLCPlant(plant_cfg, load)  # type: ignore[arg-type] - duck-typed load profile
        P0 = pts[0][1]
        plant.i = P0 / v_ref
        plant.v = v_ref
        plant.u = v_ref + model.R_ohm * plant.i
        core = make_core(controller, model, T, delay_samples, impl)
        pending = [0.0] * delay_samples
        limited_before = limited
        n = int(math.ceil(pts[-1][0] / T)) + 1
        for k in range(n):
            t = plant.t
            P = load.value(t)
            i2 = load_current(P, plant.v, plant.v_min)
            out = core.step(Sample(k, t, plant.i, plant.v, plant.u, i2), Incoming(-P, -load.rate(t)))
            r = out.du_dt
            if delay_samples:
                pending.append(r)
                r = pending.pop(0)
            if t >= t_warm:
                est = out.est
                q = est.Qdot_r_out_port
                Q_lo = min(Q_lo, q)
                Q_hi = max(Q_hi, q)
                v_lo, v_hi = min(v_lo, plant.v), max(v_hi, plant.v)
                u_lo, u_hi = min(u_lo, plant.u), max(u_hi, plant.u)
                if out.limited:
                    limited += 1
            plant.advance(r, T, n_sub)
            if not abs(plant.v - v_ref) < V_BAND * v_ref or not math.isfinite(plant.i):
                reason = reason or (f"v leaves {V_BAND * 100:.0f} % of v_ref (load {pts[0][1]:.0f} -> "
                                    f"{pts[-1][1]:.0f} W, du/dt at its limit on {limited} ticks)")
                break
        n_steps += k + 1
        worst_limited = max(worst_limited, limited - limited_before)
    if not reason:
        if u_lo <= lim.u_min_V or u_hi >= lim.u_max_V:
            reason = f"source voltage saturates: u in [{u_lo:.2f}, {u_hi:.2f}] V"
        elif worst_limited * T > SLEW_LIMITED_MAX_S:
            reason = (f"du/dt at its limit for {worst_limited * T * 1e3:.1f} ms in one run (more than "
                      f"{SLEW_LIMITED_MAX_S * 1e3:.0f} ms): the source cannot follow the load")
    f = OutgoingForecast(0.0, 0.0, 0.0, 0.0, Q_lo, Q_hi, (0.0,) * 4, v_lo, v_hi, u_lo, u_hi, limited, len(runs),
                         n_steps, reason, False, "")
    return f.for_box(box, tau_p, literal)


def widen_to_grid(box: tuple[float, float, float, float], quantum: float) -> tuple[float, float, float, float]:
    """The box widened outward to a grid of ``quantum`` of each pair's magnitude (rounded up to a power of 2), so
    that nearby boxes share one forecast and the forecast stays conservative."""
    out = []
    for lo, hi in ((box[0], box[1]), (box[2], box[3])):
        mag = max(abs(lo), abs(hi))
        if mag == 0.0 or quantum <= 0.0:
            out += [lo, hi]
            continue
        q = quantum * 2.0 ** math.ceil(math.log2(mag))
        out += [math.floor(lo / q) * q, math.ceil(hi / q) * q]
    return out[0], out[1], out[2], out[3]
