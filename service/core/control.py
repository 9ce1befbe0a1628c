"""The control core: one deterministic step per sample, no clocks, no I/O, no globals.

``ControlCore.step(sample, incoming)`` reads one measurement and the incoming interaction variable,
updates the explicit state it owns (estimator, pending commands) and returns the voltage-rate
command du/dt (V/s) with diagnostics. The simulator, the live daemon and log replay all drive it the
same way, so the same inputs give bit-identical outputs.

Laws (paper Sec. "Interactive component-level control", RLC instance; derivation in energy.py):

    y_z      = R i^2 - u i                                   (W)
    y_ref    = P^{r,in} v_ref / v                            (Eqn OutputRefRLCReg, W)
               [regulation="energy": P^{r,in} + K_E C (v^2 - v_ref^2)/2; then dE/dt -> -K_E (E - E_ref)]
    dy_ref/dt= dP^{r,in}/dt v_ref / v - P^{r,in} v_ref (dv/dt) / v^2
    dy_z/dt  = 2 (R i - u) di/dt + u_z,   u_z = Qdot^u = u di/dt - i du/dt
    FBLC     u_z = -K e + dy_ref/dt - 2 (R i - u) di/dt      (exact cancellation: de/dt = -K e)
             [cancel_tangent_energy=False: paper's u_z = -eta - K e + dy_ref/dt, de/dt = -K e - 4 E_t]
    SMC      u_z = -(L_bar + K) sat(e / phi) + dy_ref/dt      (Eqn SMC; phi = 0 -> sign)
    mapping  continuous: du/dt = (u di/dt - u_z) / i          (Eqn ControlImp, i floored)
             exact: the constant du/dt over the next period for which the nominal model lands
                    y_z(T) on the law's target: FBLC e(T) = e(0) exp(-K T); SMC e(T) = e(0) moved
                    towards 0 by (L_bar + K) T (not past it).
    LQR      u = u_ref - K1 (i - i_ref) - K2 (v - v_ref), u_ref = v_ref + R P_l / v_ref,
             i_ref = P_l / v_ref                                  (Eqn CtrlCG, deviation form)
    BM       u = R i + v_ref - L (Pi / v^2 + K3) dv/dt - K1 (v - v_ref) - K2 dv/dt   (Eqn BMCtrl)
             (both u-laws are reached by ramping u to the value over one period)

Loop delay: a command computed from the sample at t_k acts from t_{k+d}, for one period (the plant's
fixed schedule). So over the periods k .. k+d-1 the commands answering samples k-d .. k-1 act. The core
keeps what it answered the last d + 1 samples with (command and plan, by the sequence number answered) and
integrates the nominal model over the rates that act from the sample (prediction), then computes the command
for the period that starts at t_{k+d}.
Each command also carries a plan, du_dt_next: the same law applied to the state predicted at t_{k+d+1}
(after this command's period), for the period after. A command that is missing or late at the plant is
replaced by its predecessor's plan (packetized predictive control), so a lost command costs only what the
newer sample would have changed, not a whole period at du/dt = 0. For a sample the core did not answer (the
loop skipped it) the prediction uses that plan as the plant does; with neither, the plant holds its voltage
(du/dt = 0) and so does the prediction. plan_next_period = false sends no plan (0: hold).

Limits: u in [u_min, u_max] at the end of the period, |du/dt| <= du_dt_max, |i| >= i_floor where the
continuous mapping divides by i.
"""

from __future__ import annotations

import math

from schemas.scenario import CircuitParams, ControllerConfig
from service.core.energy import RLCEnergy
from service.core.estimator import EnergyEstimator
from service.core.types import Incoming, Sample

_PRED_STEP_S = 2.5e-4  # longest RK4 step of the controller's own prediction


def predict(i: float, v: float, u: float, P: float, r: float, T: float, n: int,
            R: float, L: float, C: float) -> tuple[float, float, float]:
    """Nominal model over T seconds at constant du/dt = r (V/s) and load power P (W); RK4, n steps."""
    h = T / n
    hh = 0.5 * h
    for _ in range(n):
        k1i = (u - R * i - v) / L
        k1v = (i - P / v) / C
        ii, vv = i + hh * k1i, v + hh * k1v
        um = u + hh * r
        k2i = (um - R * ii - vv) / L
        k2v = (ii - P / vv) / C
        ii, vv = i + hh * k2i, v + hh * k2v
        k3i = (um - R * ii - vv) / L
        k3v = (ii - P / vv) / C
        ii, vv = i + h * k3i, v + h * k3v
        u1 = u + h * r
        k4i = (u1 - R * ii - vv) / L
        k4v = (ii - P / vv) / C
        i += h / 6.0 * (k1i + 2.0 * k2i + 2.0 * k3i + k4i)
        v += h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
        u = u1
    return i, v, u


def predict_in_range(i: float, v: float, u: float, P: float, r: float, T: float, n: int, R: float, L: float,
                     C: float, u_min: float, u_max: float) -> tuple[float, float, float]:
    """predict, then u held in [u_min, u_max] (V): the source stops at its limits."""
    i, v, u = predict(i, v, u, P, r, T, n, R, L, C)
    return i, v, (u_max if u > u_max else u_min if u < u_min else u)


def predict_with_sensitivity(i: float, v: float, u: float, P: float, r: float, T: float, n: int,
                             R: float, L: float, C: float) -> tuple[float, float, float, float, float]:
    """Nominal model over T at rate r, plus the sensitivities s_i = d i(T)/d r (A per V/s), s_v = d v(T)/d r.

    Returns (i(T), v(T), u(T), s_i, s_v). The sensitivity obeys the linearised model
    L ds_i/dt = s_u - R s_i - s_v, C ds_v/dt = s_i + (P / v^2) s_v, s_u = t, s(0) = 0.
    """
    h = T / n
    hh = 0.5 * h
    si = sv = 0.0
    tau = 0.0
    for _ in range(n):
        k1i = (u - R * i - v) / L
        k1v = (i - P / v) / C
        g = P / (v * v)
        k1si = (tau - R * si - sv) / L
        k1sv = (si + g * sv) / C
        ii, vv = i + hh * k1i, v + hh * k1v
        s2i, s2v = si + hh * k1si, sv + hh * k1sv
        um = u + hh * r
        g = P / (vv * vv)
        k2i = (um - R * ii - vv) / L
        k2v = (ii - P / vv) / C
        k2si = (tau + hh - R * s2i - s2v) / L
        k2sv = (s2i + g * s2v) / C
        ii, vv = i + hh * k2i, v + hh * k2v
        s3i, s3v = si + hh * k2si, sv + hh * k2sv
        g = P / (vv * vv)
        k3i = (um - R * ii - vv) / L
        k3v = (ii - P / vv) / C
        k3si = (tau + hh - R * s3i - s3v) / L
        k3sv = (s3i + g * s3v) / C
        ii, vv = i + h * k3i, v + h * k3v
        s4i, s4v = si + h * k3si, sv + h * k3sv
        u1 = u + h * r
        g = P / (vv * vv)
        k4i = (u1 - R * ii - vv) / L
        k4v = (ii - P / vv) / C
        k4si = (tau + h - R * s4i - s4v) / L
        k4sv = (s4i + g * s4v) / C
        i += h / 6.0 * (k1i + 2.0 * k2i + 2.0 * k3i + k4i)
        v += h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
        si += h / 6.0 * (k1si + 2.0 * k2si + 2.0 * k3si + k4si)
        sv += h / 6.0 * (k1sv + 2.0 * k2sv + 2.0 * k3sv + k4sv)
        u = u1
        tau += h
    return i, v, u, si, sv


def solve_rate_for_target(R: float, T: float, i1: float, u1: float, si: float, y_target: float) -> float:
    """delta (V/s) so that y_z = R i^2 - u i at the period's end equals y_target.

    With i(T) = i1 + si delta and u(T) = u1 + T delta (exact for the linearised model),
    y(delta) = a delta^2 + b delta + c is solved for the root on the branch through delta = 0;
    if the target is out of reach the extremum of y is returned.
    """
    a = R * si * si - T * si
    b = 2.0 * R * i1 * si - u1 * si - T * i1
    c = R * i1 * i1 - u1 * i1 - y_target
    if abs(a) * abs(c) < 1e-12 * b * b:
        return -c / b if b != 0.0 else 0.0
    disc = b * b - 4.0 * a * c
    if disc < 0.0:
        return -b / (2.0 * a)
    q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
    return c / q if q != 0.0 else 0.0


def linearisation_rate(r_prev: float, u_p: float, T: float, u_min: float, u_max: float, r_max: float) -> float:
    """Where the exact mapping linearises (V/s): the previous command, clipped to what the slew limit r_max and the
    source's range [u_min, u_max] (V) allow over the period T (s) from u_p (V)."""
    r_lo = max(-r_max, (u_min - u_p) / T)
    r_hi = max(r_lo, min(r_max, (u_max - u_p) / T))
    return min(max(r_prev, r_lo), r_hi)


def recovery_rate(u_V: float, u_target_V: float, ramp_V_per_s: float, T: float) -> float:
    """The recovery command (V/s) while the terminal voltage is out of its measurement range: the source voltage u
    (V) moved toward u_target (V) at most ramp (V/s), landing on it within the period T (s):
    du/dt = clip((u_target - u) / T, -ramp, ramp). It reads only u, which is in range, never the implausible v: a
    bus left at 0 V (a stall, a discharged start) is brought back up like a soft start, and a wrong v costs nothing
    but a slow move of u toward the voltage it would be regulated to anyway."""
    return min(max((u_target_V - u_V) / T, -ramp_V_per_s), ramp_V_per_s)


def nested_output(i: float, v: float, u: float, P: float, P_ff: float, Pdot: float, R: float, L: float, C: float,
                  v_ref: float, K_P: float, K_E: float, i_max: float) -> tuple[float, float, float, float, bool]:
    """The nested law's output sigma (W/s) at the state (i A, v V, u V), with the load power P (W) the terminal
    delivers, the power P_ff (W) the branch is to carry besides the energy correction (P itself, or the neighbours'
    announcement or the layer's allocation -P^{r,in}: controller.load_power) and their rate Pdot (W/s), with its
    gradient (d sigma/di W/(s A), d sigma/dv W/(s V), d sigma/du W/(s V)) and whether the branch-power
    reference is at the current limit:

        E_C     = C v^2 / 2,          p_C = dE_C/dt = v i - P              terminal (capacitor) energy and its rate
        P_b     = v i,                dP_b/dt = i dv/dt + v di/dt          the branch's power into the terminal
        P_b^ref = P_ff - K_E (E_C - C v_ref^2 / 2),  dP_b^ref/dt = Pdot - K_E p_C   (clipped to +-v i_max)
        sigma   = (dP_b/dt - dP_b^ref/dt) + K_P (P_b - P_b^ref)

    sigma has relative degree one in du/dt with coefficient v / L (never zero on a bus), so holding it at zero
    leaves P_b -> P_b^ref at rate K_P and then E_C -> E_C,ref at rate K_E, for either sign of P and through zero.
    i_max <= 0: no limit."""
    dv = (i - P / v) / C
    di = (u - R * i - v) / L
    Pb = v * i
    dPb = dv * i + v * di
    P_ref = P_ff - K_E * (0.5 * C * (v * v - v_ref * v_ref))
    dP_ref = Pdot - K_E * (Pb - P)
    gr_i, gr_v = 0.0, -K_E * C * v  # d P_ref / d(i, v)
    gd_i, gd_v = -K_E * v, -K_E * i  # d dP_ref / d(i, v)
    limited = False
    if i_max > 0.0:
        P_max = v * i_max
        if P_ref > P_max or P_ref < -P_max:
            im = i_max if P_ref > 0.0 else -i_max
            P_ref, dP_ref = v * im, dv * im
            gr_i, gr_v = 0.0, im
            gd_i, gd_v = im / C, im * P / (v * v * C)
            limited = True
    sigma = dPb - dP_ref + K_P * (Pb - P_ref)
    g_i = i / C + dv - v * R / L - gd_i + K_P * (v - gr_i)
    g_v = i * P / (v * v * C) + di - v / L - gd_v + K_P * (i - gr_v)
    return sigma, g_i, g_v, v / L, limited


def y_reference(P_in: float, v: float, v_ref: float, k_e_half_C: float) -> float:
    """y_ref (W). k_e_half_C = 0: the paper's P^{r,in} v_ref / v (Eqn OutputRefRLCReg); otherwise
    P^{r,in} + K_E C (v^2 - v_ref^2) / 2, with k_e_half_C = K_E C / 2 (W/V^2)."""
    if k_e_half_C == 0.0:
        return P_in * v_ref / v
    return P_in + k_e_half_C * (v * v - v_ref * v_ref)


class Output:
    """What one step returns (reused each step; copy what you keep)."""

    __slots__ = ("seq", "t", "du_dt", "du_dt_next", "du_dt_raw", "u_z", "y_z", "y_ref", "e", "limited", "late",
                 "i_limited", "est",
                 "z_out0", "z_out1", "i_pred", "v_pred", "u_pred")

    def __init__(self) -> None:
        self.seq = 0
        self.t = self.du_dt = self.du_dt_next = self.du_dt_raw = self.u_z = self.y_z = self.y_ref = self.e = 0.0
        self.i_pred = self.v_pred = self.u_pred = self.z_out0 = self.z_out1 = 0.0
        self.limited = False
        self.late = False  # late commands detected at this sample (late_detect_V): in-flight ones taken as 0
        self.i_limited = False  # the law's current reference is at limits.i_max_A (nested)
        self.est: RLCEnergy | None = None


def core_metadata(controller: ControllerConfig, model: CircuitParams, period_s: float, delay: int) -> str:
    """What replay needs to rebuild a ControlCore exactly (JSON text for an MCAP metadata record)."""
    import json

    return json.dumps({"controller": controller.model_dump(), "model": model.model_dump(), "period_s": period_s,
                       "delay_samples": delay})


# the most each of the nested law's rates may be, per sample period: K_u T <= 2, K_P T <= 1, K_E T <= 0.3
NESTED_RATE_PER_PERIOD = (2.0, 1.0, 0.3)
NESTED_OBSERVER_GAIN = 0.15  # nested: commands with a quarter of the noise, same regulation (docs/decisions/0030)
PI_MAX_CURRENT_BW = 2500.0  # pi: the derived current-loop bandwidth at most (1/s); 7 333 /s (10 kHz, no delay) rang


def nested_rates(cfg: ControllerConfig, period_s: float) -> tuple[float, float, float]:
    """The nested law's rates in use (K_u, K_P, K_E, 1/s): the configured ones, each capped at what one sample
    period of period_s (s) carries (NESTED_RATE_PER_PERIOD / T). The defaults are for 10 kHz; at 1 kHz with a
    20 V-per-period slew limit they asked for corrections the slew could not give, and rang up until v diverged,
    while the capped ones (2000, 1000, 300 /s) held every step of the envelope (docs/decisions/0030)."""
    a, b, c = NESTED_RATE_PER_PERIOD
    T = period_s
    return min(cfg.nested_K_u_per_s, a / T), min(cfg.nested_K_P_per_s, b / T), min(cfg.nested_K_E_per_s, c / T)


def pi_bandwidths(cfg: ControllerConfig, period_s: float, delay_samples: int) -> tuple[float, float]:
    """The cascaded PI's bandwidths in use (w_i, w_v, 1/s): the configured ones, or w_i = 1.1 / ((d + 1.5) T) (the
    loop delay and half a period of hold, with 45-50 degrees of phase margin), at most 2 500 /s, and w_v = w_i / 5.
    Chosen on the envelope of load steps: 2 500 /s held every step at 10 kHz with 3 samples of delay and 800 /s
    diverged at 1 kHz with 2, where the rule's 314 /s holds."""
    wi = cfg.pi_current_bw_per_s or min(PI_MAX_CURRENT_BW, 1.1 / ((delay_samples + 1.5) * period_s))
    return wi, cfg.pi_voltage_bw_per_s or wi / 5.0


def observer_gain(cfg: ControllerConfig) -> float:
    """The observer gain in use: controller.observer_gain, or the law's default when it is None (nested 0.15, the
    others 0: the paper cases settle later with it)."""
    if cfg.observer_gain is not None:
        return cfg.observer_gain
    return NESTED_OBSERVER_GAIN if cfg.kind == "nested" else 0.0


def effective_gain(cfg: ControllerConfig, model: CircuitParams) -> float:
    """K used for tau' in the feasibility ranges (paper: K2 for the proportional law, K for FBLC; nested: K_P, the
    rate of its branch power; pi: its voltage loop's bandwidth)."""
    if cfg.kind in ("fblc", "smc"):
        return cfg.K_per_s
    if cfg.kind == "nested":  # the branch power, which shapes the port's transients, converges at K_P
        return cfg.nested_K_P_per_s
    if cfg.kind == "pi":  # its voltage loop's bandwidth (at 10 kHz with 3 samples of delay when derived)
        return pi_bandwidths(cfg, 1e-4, 3)[1]
    if cfg.kind == "lqr":
        return abs(cfg.lqr_K2)
    if cfg.kind == "bm":  # real part of the linear closed loop's poles
        return (model.L_H * cfg.bm_K3_S + cfg.bm_K2_s) / (2.0 * model.L_H * model.C_F)
    return 0.0


class CoreBase:
    """What every implementation of the core shares: configuration, derived gains, the reference map."""

    impl = "python"

    def __init__(self, cfg: ControllerConfig, model: CircuitParams, period_s: float,
                 loop_delay_samples: int = 0):
        self.cfg = cfg
        self.model = model
        self.T = float(period_s)
        dc = cfg.delay_compensation_samples
        self.d = dc if dc is not None else loop_delay_samples
        self.n_pred = max(1, math.ceil(self.T / _PRED_STEP_S - 1e-9))
        self._R, self._L, self._C = model.R_ohm, model.L_H, model.C_F
        self._cache()

    def set_gains(self, cfg: ControllerConfig) -> None:
        """Swap gains and limits between steps (the caller validated cfg)."""
        self.cfg = cfg
        self._cache()

    def _cache(self) -> None:
        c, lim = self.cfg, self.cfg.limits
        self._kind = c.kind
        self._continuous = c.mapping == "continuous"
        self._gains = (c.v_ref_V, c.K_per_s, c.cancel_tangent_energy, c.smc_bound_W_per_s + c.K_per_s,
                       c.smc_boundary_W, math.exp(-c.K_per_s * self.T))
        self._lqr = (c.lqr_K1_ohm, c.lqr_K2)
        self._bm = (c.bm_K1, c.bm_K2_s, c.bm_K3_S, c.bm_Pi_W)
        self._lim = (lim.u_min_V, lim.u_max_V, lim.du_dt_max_V_per_s, lim.i_floor_A)
        self._keC = 0.5 * c.K_E_per_s * self._C if c.regulation == "energy" else 0.0
        self._plan = c.plan_next_period
        self._late_tol = c.late_detect_V
        self._obs = observer_gain(c)
        self._load_ref = c.load_power == "reference"
        K_u, K_P, K_E = nested_rates(c, self.T)
        self._nested = (K_P, K_E, lim.i_max_A or 0.0, math.exp(-K_u * self.T))
        wi, wv = pi_bandwidths(c, self.T, self.d)  # pi: gains from the loops' bandwidths
        self._pi = (self._L * wi, self._R * wi, self._C * wv, 0.25 * self._C * wv * wv, lim.i_max_A or 0.0)

    def run_batch(self, rows, du_out, next_out=None) -> None:
        """Step n rows (n x w floats, w >= 9: seq, t, i, v, u, i_load, P_r_in, P_r_in_dot, stepped, then anything;
        stepped 0 = not given to the core, answered 0.0 with no plan: hold) and write each du/dt into du_out, the
        planned du/dt into next_out if given (log replay; the compiled core does it in C)."""
        for j, r in enumerate(rows.tolist()):
            if r[8]:
                o = self.step(Sample(int(r[0]), *r[1:6]), Incoming(r[6], r[7]))
                du, nxt = o.du_dt, o.du_dt_next
            else:
                self.hold(int(r[0]))
                du = nxt = 0.0
            du_out[j] = du
            if next_out is not None:
                next_out[j] = nxt

    def hold(self, seq: int, du_dt: float = 0.0) -> None:
        """Sample seq was answered without a step, with du_dt (V/s; 0: hold the source voltage) and no plan
        (inactive, no reference, or a mode outside the law such as a network source's idle mode): the delay
        prediction then integrates over what the plant really applies."""
        raise NotImplementedError

    def est_record(self) -> tuple:
        """After a step with an estimate: (E J, p W, E_t J, y_z W, y_z_balance W, y_ref W, eta W, u_z W/s,
        P_r_out_port W, Qdot_r_out_port W/s, z_out0 J, z_out1 W), the fields of schemas Estimate after t."""
        o = self.out
        e = o.est
        return (e.E, e.p, e.E_t, o.y_z, e.y_z_balance, o.y_ref, e.eta, o.u_z, e.P_r_out_port, e.Qdot_r_out_port,
                o.z_out0, o.z_out1)

    def interaction(self) -> tuple:
        """After a step with an estimate: the outgoing interaction variable at the port, (P^{r,out} W,
        dP^{r,out}/dt W/s, Qdot^{r,out} W/s, z_out energy integral J, z_out reactive integral W). The power's rate
        is that of P^{r,out} = -v i_2 from the filtered slopes: -(dv/dt i_2 + v di_2/dt)."""
        fit = self.estimator.fit
        v, i2 = fit.value[1], fit.value[2]
        e = self.out.est
        z0, z1 = self.estimator.z_out
        return e.P_r_out_port, -(fit.slope[1] * i2 + v * fit.slope[2]), e.Qdot_r_out_port, z0, z1

    def step_values(self, seq: int, t: float, i: float, v: float, u: float, i_load: float, P_r_in: float,
                    P_r_in_dot: float) -> tuple:
        """step() for the daemon's tick: (du_dt V/s, du_dt_next V/s, limited, late, P_r_out_port W or None before
        the first estimate, Qdot_r_out_port W/s), with no Sample, Incoming or attribute reads on the way (the
        compiled core returns them from C in one call)."""
        o = self.step(Sample(seq, t, i, v, u, i_load), Incoming(P_r_in, P_r_in_dot))
        e = o.est
        return (o.du_dt, o.du_dt_next, o.limited, o.late, None if e is None else e.P_r_out_port,
                0.0 if e is None else e.Qdot_r_out_port)

    def y_ref_of(self, P_in: float, v: float) -> float:
        """This controller's reference map y_ref(P^{r,in}, v) (W)."""
        return y_reference(P_in, v, self.cfg.v_ref_V, self._keC)


class ControlCore(CoreBase):
    """Deterministic controller for one RLC source component, in Python: the reference implementation
    (service/core/kernel.c is its compiled twin; see make_core). See the module docstring."""

    def __init__(self, cfg: ControllerConfig, model: CircuitParams, period_s: float,
                 loop_delay_samples: int = 0):
        super().__init__(cfg, model, period_s, loop_delay_samples)
        self.estimator = EnergyEstimator(model.R_ohm, model.L_H, model.C_F, cfg.deriv_tau_s)
        self.out = Output()
        self.reset()

    def reset(self) -> None:
        """Forget history (new run, plant restart)."""
        # pending[s % (d + 1)] = (s, du/dt answering sample s, du/dt planned for the period after) for the last
        # d + 1 samples answered (None: no sample)
        self.pending: list[tuple] = [(None, 0.0, 0.0)] * (self.d + 1)
        self.r_prev = 0.0
        self.late = False
        self._last_seq = -2  # seq and measured u of the last step (late-command detection)
        self._last_u = 0.0
        self._x_seq = -2  # the observer (observer_gain > 0): seq of its last estimate, the estimate (i, v, u) and
        self._x_hat = (0.0, 0.0, 0.0)  # the load power P_load (W) carried with it
        self._x_P = 0.0
        self._pi_x = (0.0, 0.0)  # pi: the integrals of the voltage error (V s) and of the current error (A s)
        self._pi_u = 0.0  # pi: the source voltage it asks for at this step (V)
        self.estimator.reset()
        self.steps = 0

    def issued(self, seq: int) -> float:
        """du/dt the plant applies over the period the command answering sample seq acts on (V/s), as far as this
        core knows: that command if it answered seq, else the plan sent with the answer to seq - 1, else 0.0
        (the plant holds u). Remembered for the last d + 1 samples."""
        m = self.d + 1
        j, r, _ = self.pending[seq % m]
        if j == seq:
            return r
        j, _, plan = self.pending[(seq - 1) % m]
        return plan if j == seq - 1 else 0.0

    def hold(self, seq: int, du_dt: float = 0.0) -> None:
        """Sample seq was answered without a step, with du_dt (V/s) and no plan (CoreBase.hold)."""
        self.pending[seq % (self.d + 1)] = (seq, du_dt, 0.0)

    def _observe(self, s: Sample, late: bool, P_load: float) -> tuple[float, float, float]:
        """The state (i A, v V, u V) at sample s for the delay prediction to start from:
        x_k = x_k^- + g (y_k - x_k^-), x_k^- = the previous estimate carried over one period by the circuit model
        (predict_in_range, load power P_load of the previous sample, W) at the rate the plant applied there
        (issued(k - 1 - d); 0 when commands are late). Starts again from the sample after a gap (first step, held or
        missing samples). Call before this step's command is stored."""
        if self._x_seq != s.seq - 1:
            x = (s.i, s.v, s.u)
        else:
            u_min, u_max = self._lim[0], self._lim[1]
            r = 0.0 if late else self.issued(s.seq - 1 - self.d)
            i, v, u = predict_in_range(*self._x_hat, self._x_P, r, self.T, self.n_pred, self._R, self._L, self._C,
                                       u_min, u_max)
            g = self._obs
            x = (i + g * (s.i - i), v + g * (s.v - v), u + g * (s.u - u))
        self._x_seq, self._x_hat, self._x_P = s.seq, x, P_load
        return x

    def applied_rate(self, seq: int | None = None) -> float:
        """du/dt acting on the plant over the period from sample seq (V/s), as far as the controller knows: what
        acts for sample seq - d (issued). seq None: the period after the last step."""
        if self.d == 0:
            return self.r_prev
        if seq is None:
            seq = self.out.seq + 1 if self.steps else 0
        return self.issued(seq - self.d)

    def step(self, s: Sample, inc: Incoming) -> Output:
        R, L, C = self._R, self._L, self._C
        u_min, u_max = self._lim[0], self._lim[1]
        T, d = self.T, self.d
        out = self.out
        seq = s.seq
        if d > 0 and self._late_tol > 0.0 and self._last_seq == seq - 1:
            # u over the last period against the rate that was to act there: off by more than the tolerance ->
            # that command did not act in time, and the ones in flight are taken as not acting either
            self.late = abs((s.u - self._last_u) - T * self.issued(seq - 1 - d)) > self._late_tol
        self._last_seq, self._last_u = seq, s.u
        late = self.late
        est = self.estimator.update(s.t, s.i, s.v, s.u, s.i_load,
                                    self.r_prev if d == 0 else 0.0 if late else self.issued(seq - d))
        if est is not None:
            out.est = est
            out.z_out0, out.z_out1 = self.estimator.z_out

        # --- state at the start of the period this command will act on (delay prediction) ---
        # the load power P_load (W): measured at the port, or as the neighbours announce it (controller.load_power)
        # (nested: always measured; the announced or allocated power is its branch power's feed-forward only, as
        # the power its terminal delivers on a network differs from its allocation while the sources re-share)
        P_load = -inc.P_r_in if self._load_ref and self._kind != "nested" else s.v * s.i_load
        Pdot = -inc.P_r_in_dot  # the load's rate as announced by the neighbour
        i_p, v_p, u_p = self._observe(s, late, P_load) if self._obs > 0.0 else (s.i, s.v, s.u)
        n = self.n_pred
        for k in range(d):
            r_k = 0.0 if late else self.issued(seq - d + k)
            i_p, v_p, u_p = predict_in_range(i_p, v_p, u_p, P_load + Pdot * (k + 0.5) * T, r_k, T, n, R, L, C,
                                             u_min, u_max)
        out.i_pred, out.v_pred, out.u_pred = i_p, v_p, u_p

        # --- energy-space output and reference at the sample (reported) ---
        y_z = R * s.i * s.i - s.u * s.i
        y_ref = y_reference(inc.P_r_in, s.v, self.cfg.v_ref_V, self._keC)
        out.y_z, out.y_ref, out.e = y_z, y_ref, y_z - y_ref

        if self._kind == "pi":
            self._pi_step(s)
        # --- the command for the period from t_{k+d}, and the plan for the one after ---
        self._ilim = False
        r, raw, u_z = self._law(i_p, v_p, u_p, P_load, inc, d, self.r_prev)
        out.i_limited = self._ilim
        plan = 0.0
        if self._plan:
            i1, v1, u1 = predict_in_range(i_p, v_p, u_p, P_load + Pdot * (d + 0.5) * T, r, T, n, R, L, C, u_min,
                                          u_max)
            plan = self._law(i1, v1, u1, P_load, inc, d + 1, r)[0]
        out.limited = r != raw
        out.late = late
        out.du_dt_raw = raw
        out.du_dt = r
        out.du_dt_next = plan
        out.u_z = u_z
        out.seq = seq
        out.t = s.t
        self.r_prev = r
        self.pending[seq % (d + 1)] = (seq, r, plan)
        self.steps += 1
        return out

    def _pi_step(self, s: Sample) -> None:
        """The cascaded PI baseline on the raw sample: voltage PI -> current reference (with the measured load
        current as feedforward) -> current PI -> source voltage u_des (V), with the voltage v as feedforward;
        integrals held while their output is at a limit (anti-windup). The law then ramps u to u_des over the
        period the command acts on, from where the commands in flight leave it."""
        kp_i, ki_i, kp_v, ki_v, i_max = self._pi
        u_min, u_max = self._lim[0], self._lim[1]
        xv, xi = self._pi_x
        ev = self.cfg.v_ref_V - s.v
        i_ref = s.i_load + kp_v * ev + ki_v * xv
        i_sat = i_ref
        if i_max > 0.0:
            i_sat = min(max(i_ref, -i_max), i_max)
        ei = i_sat - s.i
        u_des = s.v + self._R * s.i + kp_i * ei + ki_i * xi
        u_sat = min(max(u_des, u_min), u_max)
        T = self.T
        if u_sat == u_des:
            xi += ei * T
            if i_sat == i_ref:
                xv += ev * T
        self._pi_x = (xv, xi)
        self._pi_u = u_sat

    def _law(self, i_p: float, v_p: float, u_p: float, P_load: float, inc: Incoming, dd: int,
             r_prev: float) -> tuple[float, float, float]:
        """(du/dt within the limits, du/dt before them, u_z) for the period from t_{k+dd}, from the state
        (i_p, v_p, u_p) predicted there; r_prev (V/s) is where the exact mapping linearises."""
        R, L, C = self._R, self._L, self._C
        u_min, u_max, r_max, i_floor = self._lim
        v_ref, K, cancel_Et, alpha, phi, decay = self._gains
        T = self.T
        P_app = P_load + (-inc.P_r_in_dot) * (dd + 0.5) * T  # load power over that period
        keC = self._keC
        P_in_app = inc.P_r_in + inc.P_r_in_dot * dd * T
        kind = self._kind
        u_z = 0.0

        if kind == "fixed":
            r = 0.0
        elif kind == "lqr":
            K1, K2 = self._lqr
            P_l = -inc.P_r_in
            i_ref = P_l / v_ref
            u_ref = v_ref + R * P_l / v_ref
            u_des = u_ref - K1 * (i_p - i_ref) - K2 * (v_p - v_ref)
            r = (u_des - u_p) / T
        elif kind == "pi":
            r = (self._pi_u - u_p) / T
        elif kind == "nested":
            K_P, K_E, i_max, decay_u = self._nested
            r0 = linearisation_rate(r_prev, u_p, T, u_min, u_max, r_max)
            Pd = -inc.P_r_in_dot
            P0 = P_load + Pd * dd * T  # the terminal's load power at the period's start (measured)
            F0 = (-inc.P_r_in if self._load_ref else P_load) + Pd * dd * T  # the branch's feed-forward there
            i1, v1, u1, si, sv = predict_with_sensitivity(i_p, v_p, u_p, P_app, r0, T, self.n_pred, R, L, C)
            sig0 = nested_output(i_p, v_p, u_p, P0, F0, Pd, R, L, C, v_ref, K_P, K_E, i_max)[0]
            sig1, g_i, g_v, g_u, self._ilim = nested_output(i1, v1, u1, P0 + Pd * T, F0 + Pd * T, Pd, R, L, C, v_ref,
                                                            K_P, K_E, i_max)
            r = r0 + (sig0 * decay_u - sig1) / (g_i * si + g_v * sv + g_u * T)
            u_z = u_p * (u_p - R * i_p - v_p) / L - i_p * r
        elif kind == "bm":
            K1, K2, K3, Pi = self._bm
            dv = (i_p - P_app / v_p) / C
            u_des = R * i_p + v_ref - L * (Pi / (v_p * v_p) + K3) * dv - K1 * (v_p - v_ref) - K2 * dv
            r = (u_des - u_p) / T
        else:
            y_p = R * i_p * i_p - u_p * i_p
            e_p = y_p - y_reference(P_in_app, v_p, v_ref, keC)
            di = (u_p - R * i_p - v_p) / L
            if self._continuous:
                dv = (i_p - P_app / v_p) / C
                if keC == 0.0:
                    dy_ref = inc.P_r_in_dot * v_ref / v_p - P_in_app * v_ref * dv / (v_p * v_p)
                else:
                    dy_ref = inc.P_r_in_dot + 2.0 * keC * v_p * dv
                if kind == "fblc":
                    u_z = -K * e_p + dy_ref - 2.0 * (R * i_p - u_p) * di
                    if not cancel_Et:
                        u_z -= 2.0 * (L * di * di + C * dv * dv)  # 4 E_t
                else:
                    if phi > 0.0:
                        sat = max(-1.0, min(1.0, e_p / phi))
                    else:
                        sat = 1.0 if e_p > 0 else -1.0 if e_p < 0 else 0.0
                    u_z = -alpha * sat + dy_ref
                i_f = max(i_p, i_floor) if i_p >= 0.0 else min(i_p, -i_floor)
                r = (u_p * di - u_z) / i_f
            else:
                r0 = linearisation_rate(r_prev, u_p, T, u_min, u_max, r_max)
                i1, v1, u1, si, _ = predict_with_sensitivity(i_p, v_p, u_p, P_app, r0, T, self.n_pred, R, L, C)
                if kind == "fblc":
                    e1 = e_p * decay
                    if not cancel_Et:
                        dv = (i_p - P_app / v_p) / C
                        e1 -= 2.0 * (L * di * di + C * dv * dv) * T  # 4 E_t T
                else:
                    sat = max(-1.0, min(1.0, e_p / phi)) if phi > 0.0 else math.copysign(1.0, e_p)
                    stepv = alpha * T * sat
                    e1 = 0.0 if abs(stepv) >= abs(e_p) else e_p - stepv
                y_target = y_reference(inc.P_r_in + inc.P_r_in_dot * (dd + 1) * T, v1, v_ref, keC) + e1
                r = r0 + solve_rate_for_target(R, T, i1, u1, si, y_target)
                u_z = u_p * di - i_p * r  # the Qdot^u this command implies at t_{k+dd}

        raw = r
        if not math.isfinite(r):
            r = 0.0
        r = min(max(r, (u_min - u_p) / T), (u_max - u_p) / T)  # u stays in range ...
        r = min(max(r, -r_max), r_max)  # ... unless that would break the slew limit
        return r, raw, u_z
