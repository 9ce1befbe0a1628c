"""Closed-loop behaviour: decay at rate K, reaching time, poles, divergence, delay, feasibility, must-reach."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SCENARIOS, scenario

from schemas.scenario import ScenarioError, load_scenario
from service.core import ControlCore, make_core
from service.core.types import Incoming, Sample
from service.sim import run

R, L, C, P, V = 0.01, 1.12e-3, 6.8e-3, 1200.0, 80.0
AT_EQUILIBRIUM = {"initial": {"i_A": P / V, "v_V": V, "u_V": V + R * P / V}}


def fitted_decay_rate(t, e, lo=1e-3, hi=0.5):
    """Slope of log|e| where |e| is between lo and hi times its peak (1/s)."""
    a = np.abs(e)
    k0 = int(np.argmax(a))
    sel = np.arange(len(a)) >= k0
    sel &= (a > lo * a[k0]) & (a < hi * a[k0])
    slope, _ = np.polyfit(t[sel], np.log(a[sel]), 1)
    return -slope


@pytest.mark.parametrize(("mapping", "rate_hz", "K"), [("exact", 10_000.0, 500.0), ("exact", 2_000.0, 300.0),
                                                       ("continuous", 50_000.0, 500.0)])
def test_fblc_tracking_error_decays_at_rate_K(mapping, rate_hz, K):
    """A load step from 1.2 to 1.5 kW at 10 ms moves y_ref; y_z - y_ref then decays as exp(-K t)."""
    res = run(scenario(plant=AT_EQUILIBRIUM, load={"kind": "steps", "value": P, "steps": [[0.01, 1500.0]]},
                       controller={"K_per_s": K, "mapping": mapping},
                       timing={"control_rate_hz": rate_hz, "duration_s": 0.04}))
    tr = res.trace
    after = tr["t"] >= 0.01
    e = (tr["y_z_true"] - tr["y_ref_true"])[after]
    assert np.abs(e).max() > 250  # the step really disturbed the output
    assert fitted_decay_rate(tr["t"][after], e) == pytest.approx(K, rel=0.05)


def test_paper_general_form_leaves_minus_4Et_in_the_loop():
    """With u_z = -eta - K e + dy_ref/dt the closed loop is de/dt = -K e - 4 E_t, E_t >= 0: e only moves down."""
    base = {"plant": AT_EQUILIBRIUM, "load": {"kind": "steps", "value": P, "steps": [[0.005, 1500.0]]},
            "timing": {"control_rate_hz": 50_000.0, "duration_s": 0.03}}
    exact = run(scenario(**base, controller={"K_per_s": 300.0, "mapping": "continuous"})).trace
    paper = run(scenario(**base, controller={"K_per_s": 300.0, "mapping": "continuous",
                                             "cancel_tangent_energy": False})).trace
    e_exact = exact["y_z_true"] - exact["y_ref_true"]
    e_paper = paper["y_z_true"] - paper["y_ref_true"]
    after = exact["t"] > 0.005
    diff = (e_exact - e_paper)[after]
    assert diff.min() > -1e-6 * np.abs(e_exact).max()
    assert diff.max() > 0.1  # W


def test_smc_reaches_the_surface_within_sqrt2_sigma0_over_K():
    K = 1e4
    res = run(scenario(plant=AT_EQUILIBRIUM, load={"value": 1400.0},
                       controller={"kind": "smc", "mapping": "continuous", "K_per_s": K, "smc_bound_W_per_s": 2e6},
                       timing={"control_rate_hz": 50_000.0, "duration_s": 0.03}))
    tr = res.trace
    sigma = tr["y_z_true"] - tr["y_ref_true"]
    band = (2e6 + K) / 50_000.0  # one period of switching: alpha T
    reached = np.nonzero(np.abs(sigma) < band)[0]
    assert len(reached) and not res.metrics["diverged"]
    t_reach = tr["t"][reached[0]]
    assert 0 < t_reach <= np.sqrt(2) * abs(sigma[0]) / K
    assert np.abs(sigma[reached[0]:]).max() < 2 * band  # and it stays on it (chattering within the band)


def test_smc_with_too_small_a_bound_loses_the_surface():
    """Eqn ControlImp's fast mode (rate u/(iL)) is unstable under SMC: L_bar must cover what it excites."""
    res = run(scenario(plant=AT_EQUILIBRIUM, load={"value": 1400.0},
                       controller={"kind": "smc", "mapping": "continuous", "K_per_s": 1e4, "smc_bound_W_per_s": 2e5},
                       timing={"control_rate_hz": 50_000.0, "duration_s": 0.03}))
    assert res.metrics["diverged"]


def test_fixed_voltage_source_diverges_on_the_constant_power_load():
    A = np.array([[-R / L, -1 / L], [1 / C, P / (C * V**2)]])  # open loop, linearised at 80 V
    ev = np.linalg.eigvals(A)
    assert ev.real.max() == pytest.approx(9.3, abs=0.2)
    assert np.abs(ev.imag).max() == pytest.approx(362, rel=0.01)
    res = run(scenario(plant=AT_EQUILIBRIUM | {"initial": {"i_A": 15.2, "v_V": V, "u_V": V + R * P / V}},
                       controller={"kind": "fixed"}, timing={"duration_s": 1.0}))
    assert res.metrics["diverged"]
    regulated = run(scenario(plant=AT_EQUILIBRIUM | {"initial": {"i_A": 15.2, "v_V": V, "u_V": V + R * P / V}},
                             timing={"duration_s": 1.0}))
    assert not regulated.metrics["diverged"]


def oscillation_fit(t, x):
    """(decay rate 1/s, angular frequency rad/s) of the dominant pole pair of a step response.

    Prony-style: least-squares fit of x[k+1] = a1 x[k] + a2 x[k-1] + c while the response is large,
    discrete poles z from z^2 - a1 z - a2, s = ln(z) / dt.
    """
    dt = t[1] - t[0]
    dev = np.abs(x - x[-1])
    n = int(np.nonzero(dev > 1e-3 * dev.max())[0][-1])
    A = np.column_stack([x[1:n - 1], x[0:n - 2], np.ones(n - 2)])
    (a1, a2, _), *_ = np.linalg.lstsq(A, x[2:n], rcond=None)
    z = np.roots([1.0, -a1, -a2]).astype(complex)
    s_ = np.log(z[np.argmax(z.imag)]) / dt
    return -s_.real, abs(s_.imag)


def test_proportional_baseline_closed_loop_poles():
    K1, K2 = 0.4512, 0.45
    A = np.array([[-(R + K1) / L, -(1 + K2) / L], [1 / C, P / (C * V**2)]])
    ev = np.linalg.eigvals(A)
    assert ev.real.max() == pytest.approx(-192, rel=0.01)
    assert np.abs(ev.imag).max() == pytest.approx(377, rel=0.01)
    # the sampled implementation has the same poles: a 2 % load step rings down at them
    res = run(scenario(plant=AT_EQUILIBRIUM, load={"kind": "steps", "value": P, "steps": [[0.002, 1224.0]]},
                       controller={"kind": "lqr"}, timing={"control_rate_hz": 50_000.0, "duration_s": 0.04}))
    tr = res.trace
    k = tr["t"] > 0.002
    sigma, omega = oscillation_fit(tr["t"][k], tr["v"][k])
    assert sigma == pytest.approx(-ev.real.max(), rel=0.1)
    assert omega == pytest.approx(np.abs(ev.imag).max(), rel=0.05)


def test_brayton_moser_closed_loop_is_the_linear_one_when_Pi_equals_P():
    K1, K2, K3 = 0.3756, 1.8e-3, 1.0
    roots = np.roots([L * C, L * K3 + K2, 1 + K1])
    res = run(scenario(plant=AT_EQUILIBRIUM, load={"kind": "steps", "value": P, "steps": [[0.002, P]]},
                       controller={"kind": "bm", "bm_Pi_W": P, "v_ref_V": 80.8},
                       timing={"control_rate_hz": 50_000.0, "duration_s": 0.04}))
    tr = res.trace
    sigma, omega = oscillation_fit(tr["t"], tr["v"])
    assert sigma == pytest.approx(-roots.real.max(), rel=0.1)
    assert omega == pytest.approx(np.abs(roots.imag).max(), rel=0.05)


def test_naive_continuous_law_diverges_at_10kHz_from_1A_and_limits_fix_it():
    # "no limits": the widest a config takes (schemas.scenario: 10 kV, 1e10 V/s), far outside an 80 V bus's swing
    no_limits = {"du_dt_max_V_per_s": 1e10, "i_floor_A": 1e-9, "u_min_V": -1e4, "u_max_V": 1e4}
    wide_source = {"source": {"u_min_V": -1e4, "u_max_V": 1e4}}
    naive = run(scenario(plant=wide_source, controller={"mapping": "continuous", "limits": no_limits},
                         timing={"duration_s": 0.05}))
    assert naive.metrics["diverged"]
    fast = run(scenario(plant=wide_source, controller={"mapping": "continuous", "limits": no_limits},
                        timing={"duration_s": 0.05, "control_rate_hz": 100_000.0}))
    assert not fast.metrics["diverged"]
    limited = run(scenario(plant=wide_source, controller={"mapping": "continuous"}, timing={"duration_s": 0.05}))
    assert not limited.metrics["diverged"] and limited.metrics["settle_s"] is not None


def test_three_samples_of_delay_diverge_without_prediction():
    path = SCENARIOS / "paper-constant-load.toml"
    assert run(load_scenario(path, ["controller.delay_compensation_samples=0"])).metrics["diverged"]
    assert not run(load_scenario(path)).metrics["diverged"]


def test_feasibility_check_flags_the_proportional_controller_only():
    path = SCENARIOS / "paper-feasibility.toml"
    lqr = run(load_scenario(path, ['controller.kind="lqr"']))
    fblc = run(load_scenario(path))
    q_viol = [v for v in lqr.violations if v.element == "Qdot"]
    assert q_viol and 0.34 <= q_viol[0].t <= 0.37  # at the load step, as the paper reports (~0.35 s)
    assert fblc.violations == []
    assert all(w.inside for w in fblc.windows)
    assert not all(w.inside for w in lqr.windows)


def test_must_reach_paper_scenario_with_noise_delay_and_model_error():
    start = run(load_scenario(SCENARIOS / "paper-constant-load.toml")).metrics
    assert start["settle_s"] is not None and start["settle_s"] <= 0.030
    varying = run(load_scenario(SCENARIOS / "paper-varying-load.toml")).metrics
    assert varying["settle_s"] <= 0.030
    assert varying["hold_max_dev_pct"] <= 1.0


@pytest.mark.parametrize("rate_hz", [1000.0, 2000.0])
def test_regulates_at_low_control_rates(rate_hz):
    res = run(load_scenario(SCENARIOS / "paper-varying-load.toml",
                            [f"timing.control_rate_hz={rate_hz}", "timing.delay_samples=1",
                             "controller.K_per_s=1500.0", "timing.duration_s=0.5"]))
    m = res.metrics
    assert not m["diverged"]
    assert m["hold_max_dev_pct"] <= 1.0


def test_core_replays_a_run_bit_for_bit():
    """The core is a pure function of its inputs: feeding a run's samples to a fresh core gives the same
    commands, float for float (what log replay relies on)."""
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.05"])
    res = run(scn)
    tr = {k: v.tolist() for k, v in res.trace.items()}
    P_dot = [-float(x) for x in np.zeros(len(tr["t"]))]
    from service.plant.profiles import Profile

    load = Profile(scn.load)
    core = ControlCore(scn.controller, scn.model, 1.0 / scn.timing.control_rate_hz, scn.timing.delay_samples)
    got = []
    for k, t in enumerate(tr["t"]):
        s = Sample(k, t, tr["i_meas"][k], tr["v_meas"][k], tr["u_meas"][k], tr["i_load_meas"][k])
        got.append(core.step(s, Incoming(-load.value(t), -load.rate(t))).du_dt)
    assert got == tr["du_dt"]
    assert P_dot  # (rates came from the profile, as in the run)
    again = run(scn).trace["du_dt"].tolist()
    assert again == tr["du_dt"]


def test_energy_regulation_removes_the_slow_zero_dynamics_of_the_paper_map():
    """30 A into a 300 W load: with y_ref = P v_ref / v the stored energy relaxes with C v^2 / P = 145 ms;
    with y_ref = P + K_E C (v^2 - v_ref^2) / 2 it relaxes at K_E whatever the load."""
    base = ["plant.initial.i_A=30.0", "load.value=300.0", "timing.duration_s=0.3"]
    path = SCENARIOS / "paper-constant-load.toml"
    paper = run(load_scenario(path, base)).metrics
    energy = run(load_scenario(path, [*base, 'controller.regulation="energy"'])).metrics
    assert paper["settle_s"] > 0.1
    assert energy["settle_s"] < 0.03 and not energy["diverged"]


def test_fblc_rides_through_lost_commands_at_1kHz():
    """5 % of commands lost, 1 kHz, one sample of delay: the predecessor's plan acts in the lost period."""
    base = ["timing.control_rate_hz=1000.0", "timing.delay_samples=1", "controller.K_per_s=800.0",
            "timing.duration_s=0.5"]
    path = SCENARIOS / "paper-varying-load.toml"
    clean = run(load_scenario(path, base)).metrics
    lossy = run(load_scenario(path, [*base, "timing.command_loss=0.05"]))
    tr = lossy.trace
    lost = tr["du_dt_applied"][1:] != tr["du_dt"][:-1]  # the command answering k-1 did not act at k
    assert lost.sum() > 10  # losses really happened
    assert not lossy.metrics["diverged"]
    assert lossy.metrics["hold_max_dev_pct"] <= 2.0
    assert lossy.metrics["hold_max_dev_pct"] > clean["hold_max_dev_pct"]


def test_a_lost_command_is_replaced_by_the_plan_its_predecessor_carried():
    """Packetized predictive control: each command carries du/dt planned for the period after it. At 1 kHz, two
    samples of delay, K = 1500/s and 5 % of commands lost, holding u in a lost period (no plan) costs several
    times the deviation that applying the plan does; with no loss the plan changes nothing."""
    base = ["timing.control_rate_hz=1000.0", "timing.plant_step_s=5e-5", "timing.delay_samples=2",
            "controller.K_per_s=1500.0", "controller.limits.du_dt_max_V_per_s=20000.0", "timing.duration_s=1.0"]
    path = SCENARIOS / "paper-varying-load.toml"
    no_plan = "controller.plan_next_period=false"
    runs = {(loss, plan): run(load_scenario(path, [*base, f"timing.command_loss={loss}", *([] if plan else [no_plan])]),
                              stop_on_divergence=False)
            for loss in (0.0, 0.05) for plan in (True, False)}
    assert np.array_equal(runs[0.0, True].trace["v"], runs[0.0, False].trace["v"])
    tr = runs[0.05, True].trace
    lost = tr["du_dt_applied"][2:] != tr["du_dt"][:-2]
    assert 25 < lost.sum() < 80
    planned = tr["du_dt_applied"][2:][lost]
    assert (planned != 0.0).mean() > 0.8  # a plan acted (0 only where its predecessor was lost too)
    dev = {plan: runs[0.05, plan].metrics["hold_max_dev_pct"] for plan in (True, False)}
    assert not runs[0.05, True].metrics["diverged"] and dev[True] < 2.0
    assert dev[False] > 2.0 * dev[True], dev


def _skipping_loop(renumber: bool, d: int = 2, n: int = 600):
    """Nominal plant (controller model = plant, no noise, constant-power load) at 1 kHz; the controller skips
    a few samples now and then (its loop stalled). The plant's schedule: the command answering sample j acts
    over [t_{j+d}, t_{j+d+1}]; if it is missing, the plan its predecessor carried; else u is held.
    renumber: give the core consecutive numbers instead of the plant's (what a tick-indexed history sees).
    Returns the largest |u_pred - u(t_{k+d})| and |i_pred - i(t_{k+d})| over the ticks."""
    from service.plant.profiles import Profile
    from service.plant.rig import substeps
    from service.plant.rlc import RLCPlant, load_current

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml",
                        ["timing.control_rate_hz=1000.0", "controller.K_per_s=1500.0", "timing.plant_step_s=5e-5",
                         "model.R_ohm=0.01", "model.L_H=1.12e-3", "model.C_F=6.8e-3"])  # the plant's own values
    T = 1.0 / scn.timing.control_rate_hz
    load = Profile(scn.load, scn.base_dir)
    plant = RLCPlant(scn.plant, load, None)
    core = ControlCore(scn.controller, scn.model, T, d)
    skip = {97, 230, 231, 340, 341, 342, 343, 344, 461}
    sent: dict[int, tuple[float, float]] = {}
    pred: dict[int, tuple[float, float]] = {}
    true_u: list[float] = []
    true_i: list[float] = []
    ticks = 0
    for k in range(n):
        true_u.append(plant.u)
        true_i.append(plant.i)
        P = load.value(plant.t)
        if k not in skip:
            s = Sample(ticks if renumber else k, plant.t, plant.i, plant.v, plant.u,
                       load_current(P, plant.v, plant.v_min))
            o = core.step(s, Incoming(-P, 0.0))
            sent[k] = (o.du_dt, o.du_dt_next)
            pred[k + d] = (o.u_pred, o.i_pred)
            ticks += 1
        j = k - d
        r = sent[j][0] if j in sent else sent[j - 1][1] if j - 1 in sent else 0.0
        plant.advance(r, T, substeps(T, scn.timing.plant_step_s))
    du = max(abs(u - true_u[k]) for k, (u, _) in pred.items() if k < n)
    di = max(abs(i - true_i[k]) for k, (_, i) in pred.items() if k < n)
    return du, di


def test_the_prediction_follows_the_plant_across_skipped_samples():
    """The core keys what it sent by the sample each command answers: over a skipped sample's period it predicts
    the plan the plant applies there, so its predicted u at t_{k+d} is the plant's to rounding. A history kept
    in tick order would predict with the wrong commands after every skip."""
    du, di = _skipping_loop(renumber=False)
    assert du < 1e-9
    assert di < 1e-4  # the model's 4 RK4 steps per period against the plant's 20
    du_tick, di_tick = _skipping_loop(renumber=True)
    assert du_tick > 1e-4 and du_tick > 1e6 * du
    assert di_tick > 10 * di


def _late_burst_run(late_detect_V: float, observer_gain: float = 0.0) -> tuple[float, int]:
    """The embedded demo at 1 kHz, 2 samples of delay, K = 1500/s, 20 V per period slew: a burst of 10 commands
    (and their plans) that all arrive too late, as the realtime stack saw on this VM. Returns (max |v - 80| / 80
    in % after the burst, or inf if v left 40..160 V; ticks the core flagged late)."""
    from pathlib import Path

    from service.core import make_core
    from service.plant.profiles import Profile
    from service.plant.rig import substeps
    from service.plant.rlc import RLCPlant, Sensor, load_current

    scn = load_scenario(Path(__file__).parents[2] / "clients" / "embedded" / "demo.toml",
                        ['controller.kind="fblc"', "timing.control_rate_hz=1000.0", "timing.plant_step_s=5e-5",
                         "controller.K_per_s=1500.0",
                         "controller.limits.du_dt_max_V_per_s=20000.0", f"controller.late_detect_V={late_detect_V}",
                         f"controller.observer_gain={observer_gain}"])
    T, d = 1e-3, 2
    load = Profile(scn.load, scn.base_dir)
    plant = RLCPlant(scn.plant, load, None)
    sensor = Sensor(scn.sensor, scn.seed)
    core = make_core(scn.controller, scn.model, T, d)
    late = set(range(500, 510))
    sent: dict[int, tuple[float, float]] = {}
    v, flagged = [], 0
    for k in range(800):
        j = k - d
        r = sent[j][0] if j in sent and j not in late else sent[j - 1][1] if j - 1 in sent and j - 1 not in late \
            else 0.0
        P = load.value(plant.t)
        s = sensor.measure(k, plant.t, plant.i, plant.v, plant.u, load_current(P, plant.v, plant.v_min))
        o = core.step(s, Incoming(-P, -load.rate(plant.t)))
        sent[k] = (o.du_dt, o.du_dt_next)
        flagged += o.late
        plant.advance(r, T, substeps(T, scn.timing.plant_step_s))
        if not 40.0 < plant.v < 160.0:
            return float("inf"), flagged
        v.append(plant.v)
    return float(np.abs(np.array(v[500:]) - 80.0).max() / 0.8), flagged


def test_a_burst_of_late_commands_is_detected_from_the_measured_u():
    """Predicting from the raw sample, without detection the prediction keeps counting on commands that never
    acted, each new command corrects the last one's imagined effect, and v diverges; with it (u's change over a
    period off by more than 0.3 V from the command meant for it) the in-flight commands are taken as not acting and
    v stays near 80 V. With the observer (g = 0.15, the realtime stacks' setting) the same burst passes without
    detection: why the realtime stacks no longer turn it on."""
    dev_off, flagged_off = _late_burst_run(0.0)
    dev_on, flagged_on = _late_burst_run(0.3)
    assert flagged_off == 0 and dev_off == float("inf")
    assert 3 <= flagged_on <= 30
    assert dev_on < 5.0
    dev_obs, flagged_obs = _late_burst_run(0.0, observer_gain=0.15)
    assert flagged_obs == 0 and dev_obs < 2.0


# ---------------------------------------------------------------- the observer for the delay prediction's start
# the paper's law (the demo's until the nested law became the default), whose sampled-data machinery these show
REALTIME_1KHZ = ['controller.kind="fblc"', "timing.control_rate_hz=1000.0", "timing.delay_samples=3",
                 "controller.K_per_s=1500.0", "timing.plant_step_s=5e-5"]


def _demo(extra: list[str]):
    from conftest import ROOT

    return load_scenario(ROOT / "clients" / "embedded" / "demo.toml", [*REALTIME_1KHZ, *extra])


def _rms_du_after(tr, t0: float = 0.1) -> float:
    du, t = np.asarray(tr["du_dt"]), np.asarray(tr["t"])
    return float(np.sqrt(np.mean(du[t > t0] ** 2)))


def test_the_observer_quiets_the_commands_and_holds_regulation_when_commands_are_lost():
    """At 1 kHz with 3 samples of delay and the demo's sensor noise, the prediction from the raw sample turns
    v and u noise into commands (through (u - v)/L over the predicted periods); with 5 % of the commands lost
    (seeded), raw falls out of the ±2 % band, the observer (g = 0.15) stays in it with a fifth of the du/dt."""
    for seed in (0, 3):
        raw = run(_demo(["timing.duration_s=2.0", "timing.command_loss=0.05", f"seed={seed}"]))
        obs = run(_demo(["timing.duration_s=2.0", "timing.command_loss=0.05", f"seed={seed}",
                         "controller.observer_gain=0.15"]))
        assert raw.metrics["hold_max_dev_pct"] > 5.0
        assert obs.metrics["hold_max_dev_pct"] < 2.0 and not obs.metrics["diverged"]
        assert _rms_du_after(obs.trace) < 0.2 * _rms_du_after(raw.trace)


def test_the_observer_carries_its_estimate_with_the_rate_the_plant_applied():
    """Noise-free samples and an exact model: the estimate carried over each period (at the rate the command for
    that period set, through the start-up transient's steps of up to 10 V) agrees with the next sample, so the
    corrected estimate is the sample. Carried at the wrong command it would be off by volts."""
    scn = _demo(["timing.duration_s=0.1", "sensor.noise_v_V=0.0", "sensor.noise_i_A=0.0", "model.R_ohm=0.01",
                 "model.L_H=1.12e-3", "model.C_F=6.8e-3", "controller.observer_gain=0.15"])
    tr = {k: v.tolist() for k, v in run(scn, impl="python").trace.items()}
    assert max(abs(r) for r in tr["du_dt"]) > 5e3  # the transient's commands moved u by volts a period
    for impl in ("python", "c"):
        core = make_core(scn.controller, scn.model, 1e-3, 3, impl)
        worst = [0.0, 0.0, 0.0]
        for k in range(len(tr["t"])):
            s = Sample(k, tr["t"][k], tr["i_meas"][k], tr["v_meas"][k], tr["u_meas"][k], tr["i_load_meas"][k])
            o = core.step(s, Incoming(tr["P_r_in"][k], tr["P_r_in_dot"][k]))
            assert o.du_dt == tr["du_dt"][k]  # the run's own commands
            if impl == "python":
                worst = [max(w, abs(a - b)) for w, a, b in zip(worst, core._x_hat, (s.i, s.v, s.u), strict=True)]
        if impl == "python":
            assert worst[2] < 1e-9 and worst[1] < 0.05 and worst[0] < 0.5, worst


def test_observer_gain_one_is_the_raw_sample():
    scn = _demo(["timing.duration_s=0.3"])
    raw = run(scn, impl="python")
    one = run(_demo(["timing.duration_s=0.3", "controller.observer_gain=1.0"]), impl="python")
    assert np.allclose(one.trace["du_dt"], raw.trace["du_dt"], rtol=1e-9, atol=1e-6)


def test_commands_one_period_late_run_on_their_predecessors_plans_and_late_detection_turns_that_into_divergence():
    """timing.command_late / command_late_windows: a late command misses its own period, where its predecessor's
    plan acts instead. With the realtime stack's controller (1 kHz, 8-sample schedule, K = 1500/s, observer 0.15,
    20 V per period) that costs little with the late detection off; with it on (0.28 V, its former realtime value)
    the plans' effect on u reads as commands not acting, the in-flight ones are predicted as 0, and the loop
    leaves the band or diverges. Why the realtime stacks leave it off (README)."""
    base = ["timing.control_rate_hz=1000", "timing.delay_samples=8", "controller.K_per_s=1500",
            "timing.plant_step_s=5e-5", "controller.observer_gain=0.15", "timing.duration_s=1.0",
            "controller.limits.du_dt_max_V_per_s=20000"]
    d = 8
    r = run(_demo([*base, "timing.command_late_windows=[[0.5, 0.049]]"]))
    t, applied, plan = r.trace["t"], r.trace["du_dt_applied"], r.trace["du_dt_next"]
    k = np.nonzero((t >= 0.501) & (t < 0.549))[0]
    assert np.array_equal(applied[k], plan[k - 1 - d])  # each period ran on the plan sent one sample earlier
    assert not np.array_equal(applied[k], r.trace["du_dt"][k - d])
    assert not r.metrics["diverged"] and r.metrics["hold_max_dev_pct"] < 5.0
    on = run(_demo([*base, "timing.command_late_windows=[[0.5, 0.049]]", "controller.late_detect_V=0.28"]))
    assert on.metrics["diverged"]
    off = run(_demo([*base, "timing.command_late=0.1"]))
    on = run(_demo([*base, "timing.command_late=0.1", "controller.late_detect_V=0.28"]))
    assert off.metrics["hold_max_dev_pct"] < 2.0 < on.metrics["hold_max_dev_pct"]


def test_the_announced_load_power_quiets_the_commands_and_makes_lost_ones_cheap():
    """controller.load_power: at 3 kHz with the realtime stack's 24-sample schedule, the measured load power
    (v i_load, 0.05 A of noise) is most of the commands' noise; a lost command, replaced by its predecessor's plan,
    then differs from it by that noise, and over the 24 predicted periods 10 % of them take v out of the band.
    With the load power the neighbour announces (-P^{r,in}) the commands are far quieter and the same losses keep
    v within ±2 %."""
    base = ["timing.control_rate_hz=3000", "timing.delay_samples=24", "controller.K_per_s=1500",
            "timing.plant_step_s=5e-5", "controller.observer_gain=0.15", "timing.duration_s=1.0",
            "controller.limits.du_dt_max_V_per_s=60000"]
    res = {}
    for power in ("measured", "reference"):
        quiet = run(_demo([*base, f'controller.load_power="{power}"']))
        lossy = run(_demo([*base, f'controller.load_power="{power}"', "timing.command_loss=0.1"]))
        assert quiet.metrics["hold_max_dev_pct"] < 2.0
        res[power] = (_rms_du_after(quiet.trace), lossy.metrics["hold_max_dev_pct"])
    assert res["reference"][0] < res["measured"][0] / 5
    assert res["reference"][1] < 2.0 < res["measured"][1]


def test_energy_regulation_recovers_from_a_stall_in_the_start_up_transient_where_the_paper_map_is_slow():
    """A 10 ms outage just when the first commands would act (2 kHz, the realtime demo's 16-sample schedule and
    controller). With the paper's map y_ref = P^{r,in} v_ref / v, v comes back to v_ref only with the capacitor's
    C v^2 / P (tens of ms) and is still more than 2 % low at 50 ms; regulating the stored energy at K_E = 100/s
    (regulation = "energy", the realtime stacks' choice) brings it back within the band."""
    base = ["timing.control_rate_hz=2000", "timing.delay_samples=16", "controller.K_per_s=1500",
            "timing.plant_step_s=5e-5", "controller.observer_gain=0.15", "timing.duration_s=0.3",
            "controller.limits.du_dt_max_V_per_s=40000", 'controller.load_power="reference"',
            "timing.command_outages=[[0.008, 0.01]]"]
    paper = run(_demo([*base, 'controller.regulation="paper"']))
    energy = run(_demo([*base, 'controller.regulation="energy"', "controller.K_E_per_s=100"]))
    assert paper.metrics["hold_max_dev_pct"] > 2.0
    assert energy.metrics["hold_max_dev_pct"] < 2.0
    assert energy.metrics["settle_s"] < paper.metrics["settle_s"]


def test_a_command_outage_holds_the_source_and_regulation_survives_it():
    """timing.command_outages: in the window no command reaches the plant (the first period runs on its
    predecessor's plan, then u is held). At 3 kHz with the realtime stack's 24-sample (8 ms) schedule a 50 ms outage,
    six times the schedule, keeps v within ±2 % with late detection off and on; without the outage every period
    gets a command."""
    base = ["timing.control_rate_hz=3000", "timing.delay_samples=24", "controller.K_per_s=1500",
            "timing.plant_step_s=5e-5", "controller.observer_gain=0.15", "timing.duration_s=1.0"]
    for late in ("0", "0.28"):
        for outage, window_cmds in (("[]", 150), ("[[0.7, 0.05]]", 1)):
            r = run(_demo([*base, f"controller.late_detect_V={late}", f"timing.command_outages={outage}"]))
            t, applied = r.trace["t"], r.trace["du_dt_applied"]
            assert np.count_nonzero(applied[(t >= 0.7) & (t < 0.75)]) == window_cmds
            assert r.metrics["hold_max_dev_pct"] < 2.0 and not r.metrics["diverged"]
    with pytest.raises(ScenarioError, match="command_outages"):
        _demo(["timing.command_outages=[[0.1, 0.0]]"])


def test_the_metrics_say_when_v_deviated_most_and_how_long_it_was_outside_the_band():
    """One 3 % excursion of 10 ms at 0.30 s in an otherwise exact run: hold_max_dev_pct finds 3 %, and the new
    metrics put it at 0.30 s and 10 ms outside the band (a run that never settles and a single stall look alike
    in hold_max_dev_pct alone)."""
    from service.metrics import compute_metrics

    v_ref, dt = 80.0, 1e-4
    t = np.arange(0.0, 0.5, dt)
    v = np.full_like(t, v_ref)
    bump = (t >= 0.30 - 1e-9) & (t < 0.31 - 1e-9)
    v[bump] = v_ref * 1.03
    v[t < 0.01] = 0.5 * v_ref  # the start-up transient, before 50 ms: not counted
    tr = {"t": t, "v": v, "y_z_true": np.zeros_like(t), "y_ref_true": np.zeros_like(t),
          "du_dt_applied": np.zeros_like(t)}
    m = compute_metrics(tr, v_ref, 0.5, False, 0)
    assert m["hold_max_dev_pct"] == pytest.approx(3.0)
    assert m["hold_max_dev_t_s"] == pytest.approx(0.30, abs=dt)
    assert m["hold_outside_band_s"] == pytest.approx(0.010, abs=1.5 * dt)
    assert not m["accepted"] and m["failures"][0]["criterion"] == "band"


def test_the_band_is_judged_where_the_scenario_says_it_must_hold():
    """The same 10 ms excursion at 0.30 s: accepted when the scenario allows 15 ms outside the band, or gives 20 ms
    of recovery after an event at 0.295 s (not after one at 0.25 s), or a band of +-4 %, or does not require the
    band; failed again with the band required from 0.35 s but the excursion moved to 0.40 s."""
    from schemas.scenario import AcceptanceConfig
    from service.metrics import compute_metrics

    v_ref, dt = 80.0, 1e-4
    t = np.arange(0.0, 0.5, dt)

    def judged(at: float, events=(), **acc) -> dict:
        v = np.full_like(t, v_ref)
        v[(t >= at - 1e-9) & (t < at + 0.01 - 1e-9)] = v_ref * 1.03
        tr = {"t": t, "v": v, "y_z_true": np.zeros_like(t), "y_ref_true": np.zeros_like(t),
              "du_dt_applied": np.zeros_like(t)}
        return compute_metrics(tr, v_ref, 0.5, False, 0, AcceptanceConfig(**acc), events)

    assert not judged(0.30)["accepted"]
    assert judged(0.30, max_outside_band_s=0.015)["accepted"]
    assert judged(0.30, [0.295], recover_s=0.02)["accepted"]
    assert not judged(0.30, [0.25], recover_s=0.02)["accepted"]
    assert judged(0.30, band_pct=4.0)["accepted"]
    assert judged(0.30, hold_from_s=None)["accepted"]
    assert judged(0.30, hold_from_s=0.35)["accepted"] and not judged(0.40, hold_from_s=0.35)["accepted"]
    failed = judged(0.40, [0.1], recover_s=0.02)["failures"][0]["detail"]
    assert "10.0 ms from 0.05 s on, except 20 ms after each event" in failed and "3.00 % at t = 0.4000 s" in failed


def test_a_hold_with_a_rate_is_what_the_delay_prediction_integrates():
    """A sample answered outside the law (core.hold(seq, du_dt)) enters the prediction as that rate: the next
    step's predicted source voltage moves by du_dt over its period, where a plain hold predicts none."""
    from service.core import Incoming, Sample

    scn = scenario(timing={"control_rate_hz": 10000.0, "plant_step_s": 1e-5, "duration_s": 0.01, "delay_samples": 1})
    T = 1e-4
    u_pred = {}
    for rate in (0.0, 2000.0):
        core = make_core(scn.controller, scn.model, T, 1, "python")
        core.step(Sample(0, 0.0, 15.0, 80.0, 80.2, 15.0), Incoming(-1200.0, 0.0))
        core.hold(1, rate)
        u_pred[rate] = core.step(Sample(2, 2 * T, 15.0, 80.0, 80.2, 15.0), Incoming(-1200.0, 0.0)).u_pred
    assert u_pred[2000.0] - u_pred[0.0] == pytest.approx(2000.0 * T, rel=1e-9)
