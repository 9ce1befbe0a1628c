"""Scenario and controller configuration models (pydantic v2).

A scenario keeps the *true* plant (``plant``) apart from the controller's own, possibly wrong,
model of it (``model``). Every numeric field carries its unit in its name (``_V``, ``_A``, ``_W``,
``_s``, ``_hz``, ``_per_s``...). Unknown keys are rejected, so a typo names the field.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

# Every number a config holds has a lower and an upper bound (tests/schemas/test_strict.py checks it): from physics
# where there is one, else from sense: a value beyond them is a typo or a hostile request, never a plant or a
# controller this runs (v_ref_V = 1e300 reached the law; K_per_s = true became 1.0 and drove v to 191 V).
V_MAX = 10_000.0  # V: voltages (a DC bus of up to 10 kV)
A_MAX = 100_000.0  # A: currents
W_MAX = 1e9  # W: powers and profile values (W for a load, V for a disturbance)
S_MAX = 86_400.0  # s: times, windows and time constants (a day)
RATE_MAX = 1e7  # 1/s: gains and bandwidths (1000 times the fastest loop's rate)
GAIN_MAX = 1e6  # gains of mixed or no unit (lqr, bm)
SEED_MAX = 2**63 - 1  # seeds: what numpy's generators take


def _bounded(lo: float | None, hi: float, *, open_lo: bool = False):
    lower = {} if lo is None else {"gt": lo} if open_lo else {"ge": lo}
    return Annotated[float, Field(le=hi, allow_inf_nan=False, **lower)]


Pos = _bounded(0, W_MAX, open_lo=True)  # any positive quantity without a tighter bound of its own
NonNeg = _bounded(0, W_MAX)
Finite = _bounded(-W_MAX, W_MAX)
Volt = _bounded(0, V_MAX, open_lo=True)
VoltNonNeg = _bounded(0, V_MAX)
VoltSigned = _bounded(-V_MAX, V_MAX)
Amp = _bounded(0, A_MAX, open_lo=True)
AmpNonNeg = _bounded(0, A_MAX)
AmpSigned = _bounded(-A_MAX, A_MAX)
Watt = Finite  # W, either sign
WattNonNeg = NonNeg
WattPos = Pos
Secs = _bounded(0, S_MAX)
SecsPos = _bounded(0, S_MAX, open_lo=True)
PerS = _bounded(0, RATE_MAX, open_lo=True)
Ohm = _bounded(0, 1e6)  # Ω
Henry = _bounded(0, 100.0, open_lo=True)  # H
Farad = _bounded(0, 1e4, open_lo=True)  # F (a supercapacitor bank)
Gain = _bounded(-GAIN_MAX, GAIN_MAX)
Margin = _bounded(0, 100.0)  # a relative widening (1 = 100 %)
Hz = _bounded(0, 1e6)
Rad = _bounded(-1000.0, 1000.0)
VPerS = _bounded(0, 1e10, open_lo=True)  # V/s
WPerS = _bounded(0, 1e15)  # W/s
Seed = Annotated[int, Field(ge=0, le=SEED_MAX)]


def _tuple(v: Any) -> Any:
    """A TOML or JSON array for a tuple field: strict mode takes only a tuple from Python input."""
    return tuple(v) if isinstance(v, list) else v


def Pair(a, b):  # noqa: N802 (a type)
    """[a, b]: a two-element array."""
    return Annotated[tuple[a, b], BeforeValidator(_tuple)]


class Strict(BaseModel):
    """Unknown keys refused; strict types: a bool, a string or a float given for a number, an integer or a bool
    (true for 1.0, "2000" for 2000, 3.0 for 3) is refused; an integer for a float is taken (TOML's 2000)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class CircuitParams(Strict):
    """Series R-L source branch and shunt C at the terminal (paper Eqn RLCEqn)."""

    R_ohm: Ohm = Field(default=0.01, description="series resistance of the source branch, Ω")
    L_H: Henry = Field(default=1.12e-3, description="series inductance of the source branch, H")
    C_F: Farad = Field(default=6.8e-3, description="shunt capacitance at the terminal, F")


class InitialState(Strict):
    i_A: AmpSigned = Field(default=1.0, description="initial source-branch current, A")
    v_V: Volt = Field(default=80.0, description="initial terminal voltage, V")
    u_V: VoltSigned | None = Field(default=None, description="initial source voltage, V; default: v_V + R i")


class SourceLimits(Strict):
    """Physical limits of the controllable voltage source (the actuator)."""

    u_min_V: VoltSigned = Field(default=0.0, description="lowest source voltage the plant's source reaches, V")
    u_max_V: VoltSigned = Field(default=200.0, description="highest source voltage the plant's source reaches, V")
    i_max_A: Amp | None = Field(
        default=None, description="the converter's current limit, A: |i| never exceeds it (while at it and pushed "
                                  "further, di/dt = 0); unset: no limit")

    @model_validator(mode="after")
    def _order(self) -> SourceLimits:
        if not self.u_min_V < self.u_max_V:
            raise ValueError("u_min_V must be < u_max_V")
        return self


class PlantConfig(CircuitParams):
    initial: InitialState = InitialState()
    source: SourceLimits = SourceLimits()
    v_cpl_min_V: Volt = Field(
        default=5.0, description="below this terminal voltage (V) the CPL behaves as a constant resistance"
    )

    @model_validator(mode="after")
    def _within_limit(self) -> PlantConfig:
        lim = self.source.i_max_A
        if lim is not None and abs(self.initial.i_A) > lim:
            raise ValueError(f"initial.i_A = {self.initial.i_A:g} A is beyond source.i_max_A = {lim:g} A")
        return self


class SineComponent(Strict):
    amplitude: Finite = Field(description="amplitude, in the profile's unit (W for a load, V for a disturbance)")
    freq_hz: Hz = Field(description="frequency, Hz")
    phase_rad: Rad = Field(default=0.0, description="phase at t = 0, rad")


class OUConfig(Strict):
    """A seeded Ornstein-Uhlenbeck term: mean-reverting noise with spread sigma and correlation time tau_s, drawn
    from its seed on a fixed grid (the exact discretisation x[k+1] = a x[k] + sigma sqrt(1 - a^2) n[k],
    a = exp(-grid_s / tau_s), x[0] = 0) and linear between grid points, so value and rate are exact and the same
    in every process that reads the same table."""

    sigma: NonNeg = Field(description="its stationary standard deviation, in the profile's unit (W for a load, V "
                                      "for a disturbance)")
    tau_s: SecsPos = Field(description="its correlation time, s")
    seed: Seed = Field(default=1, description="seed of its path (another seed, another path)")
    grid_s: Annotated[float, Field(ge=1e-4, le=1.0)] = Field(
        default=1e-3, description="the grid its path is drawn on, s; linear in between (the rate is the segment's "
                                  "slope). Memory: 8 bytes a grid point up to the latest time asked for")


class ProfileConfig(Strict):
    """A scalar time profile (W for loads, V for a matched disturbance).

    kind: ``constant`` (value), ``steps`` (value, then ``steps = [[t_s, value], ...]``),
    ``sines`` (value + sum of ``components``), ``combined`` (value, then the steps, plus the sines),
    ``csv`` (piecewise-linear, columns t_s,value). Any kind may add a seeded Ornstein-Uhlenbeck term (``ou``) and
    switch on and off (``off_at_s``, ``on_at_s``: 0 while off). A load may be negative: power fed into the bus (a
    regenerative drive braking, a battery discharging into it).
    """

    kind: Literal["constant", "steps", "sines", "combined", "csv"] = Field(
        default="constant", description="constant: value; steps: value, then each [t_s, value] of steps from its "
                                        "time on; sines: value + the components; combined: the steps plus the "
                                        "components; csv: piecewise-linear from csv_path")
    value: Finite = Field(default=0.0, description="the constant, or the base of steps and sines, in the profile's "
                                                   "unit (W for a load, V for a disturbance)")
    steps: list[Pair(Secs, Finite)] = Field(
        default=[], description="[[t_s, value], ...] sorted by time: from t_s (s) on, the profile is value (W or V); "
                                "kinds steps and combined")
    components: list[SineComponent] = Field(default=[], description="sines added to value; kinds sines and "
                                                                    "combined")
    csv_path: str | None = Field(default=None, description="csv file with columns t_s (s), value (W or V); a "
                                                          "relative path is taken from base_dir")
    ou: OUConfig | None = Field(default=None, description="a seeded Ornstein-Uhlenbeck term added to the profile "
                                                          "(any kind)")
    off_at_s: list[Secs] = Field(
        default=[], description="times it switches off, s, increasing: from each until the next on_at_s time the "
                                "profile is 0 (W or V) and so is its rate")
    on_at_s: list[Secs] = Field(
        default=[], description="times it switches back on, s, increasing (off_at_s = [0.0] with on_at_s = [t]: "
                                "switched in at t)")

    @model_validator(mode="after")
    def _consistent(self) -> ProfileConfig:
        if self.kind == "csv" and not self.csv_path:
            raise ValueError("kind 'csv' needs csv_path")
        if self.steps and self.kind not in ("steps", "combined"):
            raise ValueError(f"steps: kind {self.kind!r} has no steps (kind 'combined' adds steps and sines)")
        if self.components and self.kind not in ("sines", "combined"):
            raise ValueError(f"components: kind {self.kind!r} has no sines (kind 'combined' adds steps and sines)")
        ts = [t for t, _ in self.steps]
        if ts != sorted(ts):
            raise ValueError("steps must be sorted by time")
        for name in ("off_at_s", "on_at_s"):
            ts = getattr(self, name)
            if any(b <= a for a, b in zip(ts, ts[1:], strict=False)):
                raise ValueError(f"{name} must be strictly increasing")
        both = sorted(set(self.off_at_s) & set(self.on_at_s))
        if both:
            raise ValueError(f"off_at_s and on_at_s both name {', '.join(f'{t:g}' for t in both)} s")
        return self


class LoadConfig(ProfileConfig):
    """The neighbour Sigma_2: a constant-power load absorbing P_l(t) (W)."""

    value: Finite = Field(default=1200.0, description="the load power, or the base of steps and sines, W")


class SensorConfig(Strict):
    """Measurement chain: seeded white noise (standard deviation) and quantisation (LSB)."""

    noise_v_V: VoltNonNeg = Field(default=0.0, description="standard deviation of the noise on measured voltages "
                                                       "(v, u), V; 0: none")
    noise_i_A: AmpNonNeg = Field(default=0.0, description="standard deviation of the noise on measured currents "
                                                       "(i, i_load), A; 0: none")
    lsb_v_V: VoltNonNeg = Field(default=0.0, description="quantisation step of measured voltages, V; 0: none")
    lsb_i_A: AmpNonNeg = Field(default=0.0, description="quantisation step of measured currents, A; 0: none")


class CommandDisturbances(Strict):
    """Seeded disturbances of the commands on their way to the plant (offline and lockstep; a realtime stack has
    its own): loss, one period of lateness, and outages."""

    command_loss: Annotated[float, Field(ge=0, lt=1)] = Field(
        default=0.0, description="probability that a command never reaches the plant, seeded: its predecessor's "
                                 "plan acts in its period (the source holds its voltage if that one was lost too)")
    command_late: Annotated[float, Field(ge=0, le=1)] = Field(
        default=0.0, description="probability that a command arrives one period late, seeded: too late for its own "
                                 "period (its predecessor's plan acts there), in time for its own plan to serve the "
                                 "next one if that command is missing; jitter around the schedule's deadline")
    command_late_windows: list[Pair(Secs, SecsPos)] = Field(
        default=[], description="windows (start s, length s) in which every command arrives one period late: the "
                                "transport's delay a period longer than the schedule for a while")
    command_outages: list[Pair(Secs, SecsPos)] = Field(
        default=[], description="windows (start s, length s) in which no command arrives at the plant: a stall of "
                                "the transport or of the controller longer than the loop delay, as the realtime "
                                "stack sees on a shared machine")


class TimingConfig(CommandDisturbances):
    control_rate_hz: Annotated[float, Field(ge=100, le=100_000)] = Field(
        default=10_000.0, description="sampling and control rate, Hz")
    plant_step_s: Annotated[float, Field(gt=0, le=1e-3)] = Field(
        default=1e-5, description="the plant's integration step, s")
    delay_samples: Annotated[int, Field(ge=0, le=200)] = Field(
        default=0, description="loop delay: the command answering sample k acts from sample k + this (samples)")
    duration_s: Annotated[float, Field(gt=0, le=3600)] = Field(default=0.2, description="simulated time, s")


class LimitsConfig(Strict):
    """Actuator limits the controller enforces on its own command."""

    u_min_V: VoltSigned = Field(default=0.0, description="lowest source voltage the controller commands, V")
    u_max_V: VoltSigned = Field(default=200.0, description="highest source voltage the controller commands, V")
    du_dt_max_V_per_s: VPerS = Field(default=2.0e5, description="largest |du/dt| the controller commands, V/s")
    i_floor_A: Amp = Field(default=0.5, description="current floor where a law divides by i, A")
    i_max_A: Amp | None = Field(
        default=None, description="largest |i| the law asks of the source branch, A (nested: the branch-power "
                                  "reference is clipped to +-v i_max; pi: the current reference); None: no limit")

    @model_validator(mode="after")
    def _order(self) -> LimitsConfig:
        if not self.u_min_V < self.u_max_V:
            raise ValueError("u_min_V must be < u_max_V")
        return self


ControllerKind = Literal["nested", "fblc", "smc", "lqr", "bm", "pi", "fixed"]


class ControllerConfig(Strict):
    """Controller selection, gains and limits.

    kind: ``fblc`` energy feedback linearisation (paper Eqn FBLC), ``smc`` energy sliding mode
    (Eqn SMC), ``lqr`` proportional baseline in deviation form (Eqn CtrlCG), ``bm`` Brayton-Moser
    baseline (Eqn BMCtrl), ``fixed`` a source held at its initial voltage (du/dt = 0).
    mapping: ``exact`` chooses the constant du/dt of the next period so that the nominal model lands
    y_z on the law's target at the period's end (discrete-time form of Eqn ControlImp);
    ``continuous`` evaluates Eqn ControlImp as printed, du/dt = (u di/dt - u_z)/i.
    """

    kind: ControllerKind = Field(default="nested", description="control law: nested energy-space control on the "
                                                               "terminal energy and the branch power (holds both "
                                                               "directions of power), fblc the paper's energy feedback "
                                                               "linearisation, smc energy sliding mode, lqr "
                                                               "proportional baseline, bm Brayton-Moser baseline, pi "
                                                               "cascaded PI baseline, fixed du/dt = 0")
    v_ref_V: Volt = Field(default=80.0, description="terminal voltage reference, V")
    K_per_s: PerS = Field(default=2000.0, description="energy-space gain K (1/s)")
    mapping: Literal["exact", "continuous"] = Field(
        default="exact", description="exact: the constant du/dt of the next period that lands y_z on the law's "
                                     "target at the period's end; continuous: du/dt = (u di/dt - u_z) / i as printed")
    regulation: Literal["paper", "energy"] = Field(
        default="paper",
        description="y_ref: 'paper' P^{r,in} v_ref / v (Eqn OutputRefRLCReg); 'energy' P^{r,in} + "
        "K_E C (v^2 - v_ref^2) / 2, so the stored energy converges at rate K_E whatever the load",
    )
    K_E_per_s: PerS = Field(default=100.0, description="energy regulation rate for regulation='energy' (1/s)")
    nested_K_u_per_s: PerS = Field(
        default=10000.0, description="nested: rate (1/s) at which its output sigma, the branch power's error and "
                                     "its rate, decays over each period (sigma(T) = sigma(0) exp(-K_u T))")
    nested_K_P_per_s: PerS = Field(
        default=8000.0, description="nested: rate (1/s) at which the branch power P_b = v i converges to its "
                                    "reference P_l - K_E (E_C - E_C,ref)")
    nested_K_E_per_s: PerS = Field(
        default=1500.0, description="nested: rate K_E (1/s) at which the terminal energy E_C = C v^2 / 2 converges "
                                    "to C v_ref^2 / 2")
    pi_current_bw_per_s: PerS | None = Field(
        default=None, description="pi: current-loop bandwidth w_i (1/s, rad/s): Kp_i = L w_i, Ki_i = R w_i; None: "
                                  "1.1 / ((d + 1.5) T) from the sample period T (s) and the loop delay d (samples), "
                                  "at most 2 500 /s (2 444 /s at 10 kHz with 3 samples)")
    pi_voltage_bw_per_s: PerS | None = Field(
        default=None, description="pi: voltage-loop bandwidth w_v (1/s, rad/s): Kp_v = C w_v, Ki_v = C w_v^2 / 4; "
                                  "None: w_i / 5")
    cancel_tangent_energy: bool = Field(
        default=True,
        description="True: u_z cancels eta - 4E_t so e decays at exactly K; False: paper's general form "
        "u_z = -eta - K e + dy_ref/dt, which leaves -4E_t in the closed loop",
    )
    smc_bound_W_per_s: WPerS = Field(default=1.0e6, description="L-bar, bound on the uncancelled term, W/s")
    smc_boundary_W: WattNonNeg = Field(default=0.0, description="boundary layer width phi, W; 0 = pure sign")
    lqr_K1_ohm: Gain = Field(default=0.4512, description="lqr: current gain K1 in u = u_ref - K1 (i - i_ref) - "
                                                           "K2 (v - v_ref), Ω")
    lqr_K2: Gain = Field(default=0.45, description="lqr: voltage gain K2 (dimensionless, V/V)")
    bm_K1: Gain = Field(default=0.3756, description="bm: voltage gain K1 in u = R i + v_ref - L (Pi / v^2 + K3) "
                                                      "dv/dt - K1 (v - v_ref) - K2 dv/dt (dimensionless, V/V)")
    bm_K2_s: Gain = Field(default=1.8e-3, description="bm: damping gain K2 on dv/dt, s")
    bm_K3_S: Gain = Field(default=1.0, description="bm: gain K3, S")
    bm_Pi_W: WattNonNeg = Field(default=2400.0, description="bm: power Pi in the damping term L (Pi / v^2 + K3) "
                                                             "dv/dt, W")
    delay_compensation_samples: Annotated[int, Field(ge=0, le=200)] | None = Field(
        default=None, description="samples of loop delay to predict over; None = the known loop delay"
    )
    deriv_tau_s: SecsPos = Field(default=5e-4, description="estimator derivative window time constant, s")
    plan_next_period: bool = Field(
        default=True, description="each command also carries du/dt planned for the period after it (the same law "
                                  "applied to the predicted state there); the plant applies that plan when the next "
                                  "command is missing or late, instead of holding u (packetized predictive control)")
    late_detect_V: VoltNonNeg = Field(
        default=0.0, description="late-command detection, V: when the measured u moved over the last period by more "
                                 "than this away from what the command for that period implied, commands are not "
                                 "arriving in time, and the prediction takes the ones still in flight as not acting "
                                 "(du/dt = 0) until u follows the commands again; 0 = off. Set it above the u "
                                 "sensor's noise (several times sqrt(2) sigma)")
    load_power: Literal["measured", "reference"] = Field(
        default="measured", description="the load power the delay prediction, the law and the observer carry the "
                                        "state with (W): 'measured' v i_load of the sample; 'reference' -P^{r,in}, "
                                        "the power the neighbours announce (paper Eqn PsiMap; the local fallback "
                                        "when they are silent). The measured i_load's noise (0.05 A: 4 W at 80 V) "
                                        "was most of the commands' noise, and what made a lost or late command cost")
    observer_gain: Annotated[float, Field(ge=0, le=1)] | None = Field(
        default=None, description="where the delay prediction starts: None = the law's default (0.15 for nested, "
                                  "0 for the others); 0 = the raw sample (i, v, u); g in (0, 1] = a "
                                 "model-based estimate x = x- + g (y - x-), x- the previous estimate carried over "
                                 "one period by the circuit model at the rate the plant applied (1: the sample). "
                                 "Sensor noise on u - v drives di/dt through 1/L over the predicted periods; at 1 kHz "
                                 "with 3 samples of delay the commands were mostly that noise")
    limits: LimitsConfig = LimitsConfig()


class OutgoingForecastConfig(Strict):
    """Forecast of the component's own outgoing range Z^{r,out}[k] per window, checked against Z^{r,in}[k]
    ahead of the window (service/forecast.py)."""

    enabled: bool = Field(default=False, description="forecast Z^{r,out}[k] for each window and check it ahead")
    load_steps: bool = Field(default=True, description="the neighbours' loads may jump anywhere inside their range "
                                                       "(False: they only ramp, within their rate range)")
    settle_s: Annotated[float, Field(gt=0, le=1.0)] = Field(
        default=0.025, description="each forecast run holds this long after the load stops moving (s)")


class FeasibilityConfig(Strict):
    """Per-window interaction ranges (paper Eqn IncomingIntRange)."""

    window_s: SecsPos = Field(default=1.0, description="length T_s of the windows the interaction ranges are for, s")
    forecast_margin: Margin = Field(default=0.0, description="relative widening of the load forecast (fraction of "
                                                             "its largest magnitude, each side)")
    literal_paper_range: bool = Field(
        default=False,
        description="True: Qdot range offset (2/tau')[P_min, P_max] as printed; False: (2/tau')[-P_max, P_max]",
    )
    forecast: OutgoingForecastConfig = OutgoingForecastConfig()


class AcceptanceConfig(Strict):
    """What a run must meet for ``energyctl sim``, ``compare`` and ``sweep`` to exit 0 (else 1, naming the run and
    the criterion): it does not diverge, and its voltage stays inside the band where the band must hold."""

    diverge_dev_pct: Annotated[float, Field(gt=0, le=100)] = Field(
        default=25.0, description="the run diverges (and stops) when the terminal voltage is further than this from "
                                  "v_ref, % of v_ref (a network: any node a source supplies, from nominal_v_V)")
    band_pct: Annotated[float, Field(gt=0, le=100)] = Field(
        default=2.0, description="the band: the terminal voltage within +-this of v_ref, % (a network: every bus "
                                 "within +-this of nominal_v_V); settle_s and the events' back-in-band times use it "
                                 "too")
    hold_from_s: Secs | None = Field(
        default=0.05, description="from this time on the voltage must stay inside the band, s; unset: the band is "
                                  "not required (only divergence is checked)")
    max_outside_band_s: Secs = Field(
        default=0.0, description="how long in total the voltage may be outside the band where it must hold, s")
    recover_s: Secs = Field(
        default=0.0, description="after each event (a step or an on/off switch of the load or disturbance profile) "
                                 "the band need not hold for this long, s; 0: a load step must be ridden through "
                                 "inside the band")


class Scenario(Strict):
    name: str = Field(default="scenario", description="name of the scenario (not empty)")
    description: str = Field(default="", description="free text")
    seed: Seed = Field(default=1, description="seed of the sensor noise and the command loss and lateness draws")
    plant: PlantConfig = PlantConfig()
    model: CircuitParams = CircuitParams()
    load: LoadConfig = LoadConfig()
    disturbance: ProfileConfig | None = Field(default=None, description="matched disturbance voltage (V)")
    sensor: SensorConfig = SensorConfig()
    timing: TimingConfig = TimingConfig()
    controller: ControllerConfig = ControllerConfig()
    feasibility: FeasibilityConfig = FeasibilityConfig()
    acceptance: AcceptanceConfig = AcceptanceConfig()
    base_dir: str = Field(default=".", description="directory for relative csv paths (set by the loader)")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("name must not be empty")
        return v


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names every offending field."""


def format_validation_error(err: ValidationError, source: str = "", what: str = "scenario") -> str:
    """One line per offending field, headed 'invalid <what> <source> (N errors):'."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"])
        got = e.get("input")
        shown = "" if isinstance(got, dict) or got is None else f" (got {_short(got)})"
        lines.append(f"  {loc or '<root>'}: {e['msg']}{shown}")
    head = f"invalid {what} {source}".rstrip() + f" ({len(lines)} error{'s' if len(lines) > 1 else ''}):"
    return "\n".join([head, *lines])


def _short(value: Any, limit: int = 60) -> str:
    """repr(value), cut to about limit characters (a 4000-digit number or a long string named in an error)."""
    r = repr(value)
    return r if len(r) <= limit else f"{r[:limit]}... ({len(r)} characters)"


def parse_override(text: str) -> tuple[list[str], Any]:
    """``a.b.c=value`` -> (["a","b","c"], value) with value parsed as a TOML value when possible."""
    if "=" not in text:
        raise ScenarioError(f"override {text!r}: expected dotted.key=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not p for p in key.split(".")):
        raise ScenarioError(f"override {text!r}: empty key")
    try:
        value = parse_toml(f"x = {raw.strip()}", f"override {text[:80]!r}")["x"]
    except ScenarioError as e:
        if "not valid TOML" not in str(e) or raw.strip()[:1] in "[{" or raw.strip().isdigit():
            raise  # nested too deep, or an array, a table or a number that is not TOML: not a bare string either
        value = raw.strip()  # a bare word: the string it spells (--set controller.kind=fblc)
    return key.split("."), value


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    out = _deepcopy(data)
    for ov in overrides:
        path, value = parse_override(ov)
        node = out
        for p in path[:-1]:
            nxt = node.get(p)
            if nxt is None:
                nxt = node[p] = {}
            elif not isinstance(nxt, dict):
                raise ScenarioError(f"override {ov!r}: {p} is not a table")
            node = nxt
        node[path[-1]] = value
    return out


def _deepcopy(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _deepcopy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_deepcopy(v) for v in d]
    return d


def scenario_from_dict(data: dict, overrides: list[str] | None = None, source: str = "") -> Scenario:
    data = apply_overrides(data, overrides or [])
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(format_validation_error(err, source)) from None


MAX_FILE_BYTES = 1 << 20  # a scenario or config file: 1 MiB (the largest here is under 20 KiB)
MAX_DEPTH = 16  # tables and arrays nested in a file or a --set value (the deepest here: 5)


def parse_toml(text: str, what: str) -> dict:
    """TOML text's table; anything tomllib or Python refuses (bad syntax, an integer of more than 4300 digits,
    nesting that exhausts the stack) and nesting deeper than MAX_DEPTH is a ScenarioError naming ``what``."""
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise ScenarioError(f"{what} is nested deeper than {MAX_DEPTH} levels") from None
    except ValueError as e:  # TOMLDecodeError, and int()'s digit limit
        raise ScenarioError(f"{what} is not valid TOML: {e}") from None
    if _depth(data) > MAX_DEPTH:
        raise ScenarioError(f"{what} is nested deeper than {MAX_DEPTH} levels")
    return data


def _depth(node: Any) -> int:
    """How deep tables and arrays nest (a scalar: 0), without recursion."""
    deepest, todo = 0, [(node, 1)]
    while todo:
        n, d = todo.pop()
        if isinstance(n, dict | list):
            deepest = max(deepest, d)
            todo.extend((v, d + 1) for v in (n.values() if isinstance(n, dict) else n))
    return deepest


def read_toml(p: Path, what: str) -> dict:
    """The TOML file's table; a file that cannot be read, is not UTF-8, is larger than MAX_FILE_BYTES, cannot be
    parsed, nests too deep or holds no key at all is a ScenarioError naming it as ``what``."""
    try:
        with open(p, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as e:
        raise ScenarioError(f"cannot read {what} {p}: {e.strerror}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise ScenarioError(f"{what} {p} is larger than {MAX_FILE_BYTES >> 20} MiB")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ScenarioError(f"{what} {p} is not UTF-8 text (byte {e.start}: {raw[e.start:e.start + 1]!r})") from None
    data = parse_toml(text, f"{what} {p}")
    if not data:
        raise ScenarioError(f"{what} {p} is empty: it sets no key (a run on nothing but defaults is asked for "
                            "by naming at least one key, e.g. name = \"...\")")
    return data


def load_scenario(path: str | Path, overrides: list[str] | None = None) -> Scenario:
    """Read a TOML scenario file, apply ``dotted.key=value`` overrides, validate."""
    p = Path(path)
    data = read_toml(p, "scenario")
    data.setdefault("base_dir", str(p.parent.resolve()))
    return scenario_from_dict(data, overrides, str(p))

