"""The compiled core (service/core/kernel.c) is the Python core, bit for bit.

Every driver uses make_core, which picks the compiled twin when it was built; replay exactness and
"lockstep equals sim" then hold whichever implementation a machine has only if the two agree exactly.
These tests compare every trace column (commands, estimates, integrals) with ==, not a tolerance.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import SCENARIOS
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.scenario import load_scenario
from service.core import ControlCore, CoreBase, make_core
from service.core.types import Incoming, Sample
from service.sim import run

fastcore = pytest.importorskip("service.core.compiled", reason="compiled core not built (no C compiler)")

CASES = [
    ("fblc", "exact", 3, []),
    ("fblc", "exact", 0, []),
    ("fblc", "exact", 1, ['controller.regulation="energy"']),
    ("fblc", "exact", 2, ["controller.cancel_tangent_energy=false"]),
    ("fblc", "continuous", 0, ["timing.control_rate_hz=50000.0"]),
    ("fblc", "continuous", 3, ["controller.cancel_tangent_energy=false", 'controller.regulation="energy"']),
    ("smc", "exact", 3, ["controller.smc_boundary_W=50.0"]),
    ("smc", "exact", 0, []),
    ("smc", "continuous", 1, ["controller.smc_boundary_W=0.0"]),
    ("lqr", "exact", 3, []),
    ("bm", "exact", 2, []),
    ("fixed", "exact", 0, []),
    ("fblc", "exact", 3, ["timing.control_rate_hz=1000.0", "timing.plant_step_s=5e-5"]),  # 4 RK4 steps per period
    ("fblc", "exact", 2, ["controller.late_detect_V=0.01", "timing.command_loss=0.1"]),  # late commands detected
    # the observer for the prediction's start
    ("fblc", "exact", 3, ["controller.observer_gain=0.15", "timing.control_rate_hz=1000.0",
                          "timing.plant_step_s=5e-5"]),
    ("fblc", "exact", 2, ["controller.observer_gain=0.3", "controller.late_detect_V=0.01", "timing.command_loss=0.1"]),
    ("fblc", "exact", 0, ["controller.observer_gain=0.5"]),
    ("lqr", "exact", 3, ["controller.observer_gain=0.2"]),
    # the load power as the neighbours announce it
    ("fblc", "exact", 3, ['controller.load_power="reference"', "controller.observer_gain=0.15",
                          "timing.control_rate_hz=1000.0", "timing.plant_step_s=5e-5", "timing.command_late=0.1"]),
    ("bm", "exact", 2, ['controller.load_power="reference"']),
    # the nested law (the default) and the cascaded PI baseline, with and without their current limits
    ("nested", "exact", 3, []),
    ("nested", "exact", 0, ["controller.observer_gain=0.15"]),
    ("nested", "exact", 2, ["controller.limits.i_max_A=16.0", 'controller.load_power="reference"']),
    ("nested", "exact", 3, ["timing.control_rate_hz=1000.0", "timing.plant_step_s=5e-5", "timing.command_loss=0.1"]),
    ("pi", "exact", 3, []),
    ("pi", "exact", 1, ["controller.limits.i_max_A=12.0", "controller.limits.u_max_V=95.0"]),
]


def same(a: dict, b: dict) -> list[str]:
    return [k for k in a if not np.array_equal(a[k], b[k], equal_nan=True)]


@pytest.mark.parametrize(("kind", "mapping", "delay", "extra"), CASES)
def test_compiled_core_equals_python_core_bit_for_bit(kind, mapping, delay, extra):
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml",
                        [f'controller.kind="{kind}"', f'controller.mapping="{mapping}"',
                         f"timing.delay_samples={delay}", "timing.duration_s=0.08", *extra])
    py = run(scn, stop_on_divergence=False, impl="python")
    c = run(scn, stop_on_divergence=False, impl="c")
    assert same(py.trace, c.trace) == []
    assert len(py.trace["t"]) == round(0.08 * scn.timing.control_rate_hz)
    assert np.ptp(py.trace["du_dt"]) > 0 or kind == "fixed"  # the comparison saw commands that moved
    assert np.array_equal(py.trace["du_dt_next"], c.trace["du_dt_next"])


def _stream(n: int = 600):
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.06"])
    tr = {k: v.tolist() for k, v in run(scn, impl="python").trace.items()}
    rows = [(k, tr["t"][k], tr["i_meas"][k], tr["v_meas"][k], tr["u_meas"][k], tr["i_load_meas"][k],
             tr["P_r_in"][k], tr["P_r_in_dot"][k]) for k in range(n)]
    return scn, rows


def test_reset_set_gains_and_views_match():
    """Plant restart (reset), a gain change mid-run and the daemon's views (est, fit, z_out, steps) agree."""
    scn, rows = _stream()
    T = 1.0 / scn.timing.control_rate_hz
    cores = [ControlCore(scn.controller, scn.model, T, 3), make_core(scn.controller, scn.model, T, 3, "c")]
    assert cores[1].impl == "c"
    faster = scn.controller.model_copy(update={"K_per_s": 900.0})
    seen = [[], []]
    for j, core in enumerate(cores):
        for k, r in enumerate(rows):
            if k == 200:
                core.set_gains(faster)
            if k == 400:
                core.reset()
            if k % 50 == 0:  # the daemon's one-call step: what it returns is what step() leaves in out
                vals = core.step_values(*r)
                o = core.out
                assert vals == (o.du_dt, o.du_dt_next, o.limited, o.late, o.est.P_r_out_port, o.est.Qdot_r_out_port)
            else:
                o = core.step(Sample(*r[:6]), Incoming(r[6], r[7]))
            est = o.est
            seen[j].append((o.du_dt, o.du_dt_next, o.du_dt_raw, o.limited, o.u_z, o.y_z, o.y_ref, o.e, o.i_pred,
                            o.v_pred, o.u_pred, o.z_out0, o.z_out1, o.seq, o.t, core.applied_rate(), core.steps,
                            *core.estimator.z_out, *core.estimator.fit.value, *core.estimator.fit.slope,
                            core.estimator.fit.count, *(getattr(est, f) for f in ("E", "E_t", "D", "tau", "p", "pdot",
                                                                                   "y_z", "y_z_balance", "eta",
                                                                                   "P_r_out", "Qdot_r_out",
                                                                                   "P_r_out_port",
                                                                                   "Qdot_r_out_port")),
                            *core.est_record(), *core.interaction()))
            if k % 50 == 25:  # the compiled core's one-call readers against the generic ones over its views
                assert core.est_record() == CoreBase.est_record(core)
                assert core.interaction() == CoreBase.interaction(core)
    assert seen[0] == seen[1]
    assert seen[0][399][16] == 400 and seen[0][400][16] == 1  # reset really happened


def test_batch_run_equals_step_by_step():
    scn, rows = _stream()
    T = 1.0 / scn.timing.control_rate_hz
    stepped = [0.0 if 100 <= k < 110 else 1.0 for k in range(len(rows))]  # a held stretch (no reference)
    ref = ControlCore(scn.controller, scn.model, T, 3)
    want = [ref.step(Sample(*r[:6]), Incoming(r[6], r[7])).du_dt if s else 0.0 for r, s in zip(rows, stepped,
                                                                                               strict=True)]
    core = make_core(scn.controller, scn.model, T, 3, "c")
    buf = np.array([(*r, s) for r, s in zip(rows, stepped, strict=True)], dtype=np.float64)
    du = np.zeros(len(rows))
    core.run_batch(buf, du)
    assert du.tolist() == want
    with pytest.raises(ValueError, match="n x width"):
        core.run_batch(buf[:, :8].copy(), du)
    wide = np.hstack([buf, np.full((len(rows), 1), 7.0)])  # extra columns (the tick index's du) are ignored
    du2 = np.zeros(len(rows))
    core2 = make_core(scn.controller, scn.model, T, 3, "c")
    core2.run_batch(wide, du2)
    assert du2.tolist() == want


finite = st.floats(-1e4, 1e4, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(i=st.floats(-200, 200), v=st.floats(1.0, 400.0), u=st.floats(-400, 400), i2=finite, P=finite, Pd=finite,
       dt=st.floats(1e-6, 1e-2), kind=st.sampled_from(["fblc", "smc", "lqr", "bm", "nested", "pi"]),
       mapping=st.sampled_from(["exact", "continuous"]), d=st.integers(0, 3))
def test_any_input_same_answer(i, v, u, i2, P, Pd, dt, kind, mapping, d):
    """Arbitrary (finite, physical-sign) inputs, including ones that drive the laws to their limits."""
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml",
                        [f'controller.kind="{kind}"', f'controller.mapping="{mapping}"'])
    T = 1e-4
    a = ControlCore(scn.controller, scn.model, T, d)
    b = make_core(scn.controller, scn.model, T, d, "c")
    for k in range(4):
        s = Sample(k, k * dt, i + k, v, u, i2)
        try:
            x = a.step(s, Incoming(P, Pd))
        except ZeroDivisionError:  # Python raises where C gives inf/NaN (then du/dt = 0); not compared
            return
        y = b.step(s, Incoming(P, Pd))
        for f in ("du_dt", "du_dt_next", "du_dt_raw", "u_z", "y_ref", "i_pred", "v_pred", "u_pred", "z_out0"):
            p, q = getattr(x, f), getattr(y, f)
            assert p == q or (math.isnan(p) and math.isnan(q)), f
        assert x.limited == y.limited
        assert x.i_limited == y.i_limited


@pytest.mark.parametrize("observer", [0.0, 0.2])
@pytest.mark.parametrize("plan", [True, False])
@pytest.mark.parametrize("delay", [0, 1, 3])
def test_skipped_and_held_samples_same_answer(plan, delay, observer):
    """Samples the loop skipped (seq gaps), samples answered by a hold (no step), and a batch with held rows:
    the two cores keep the same history by sequence number, so every later command and plan agrees."""
    scn, rows = _stream()
    T = 1.0 / scn.timing.control_rate_hz
    ctl = scn.controller.model_copy(update={"plan_next_period": plan, "late_detect_V": 0.002 if plan else 0.0,
                                            "observer_gain": observer})
    cores = [ControlCore(ctl, scn.model, T, delay), make_core(ctl, scn.model, T, delay, "c")]
    skipped = {50, 51, 120, 121, 122, 123, 124, 300}
    held = {60, 61, 200, 301}
    seen = [[], []]
    for j, core in enumerate(cores):
        for k, r in enumerate(rows):
            if k in skipped:
                continue
            if k in held:
                core.hold(k)
                continue
            o = core.step(Sample(*r[:6]), Incoming(r[6], r[7]))
            seen[j].append((o.du_dt, o.du_dt_next, o.i_pred, o.v_pred, o.u_pred, o.late, core.applied_rate()))
    assert seen[0] == seen[1]
    assert any(s[1] != 0.0 for s in seen[0]) == plan
    assert any(s[5] for s in seen[0]) == (plan and delay > 0)  # the recorded u does not follow: "late" seen
    # the same stream as a batch (held rows: stepped = 0), with the plans
    buf = np.array([(*r, 0.0 if k in held else 1.0) for k, r in enumerate(rows) if k not in skipped])
    out = [(np.zeros(len(buf)), np.zeros(len(buf))) for _ in cores]
    for core, (du, nxt) in zip((ControlCore(ctl, scn.model, T, delay), make_core(ctl, scn.model, T, delay, "c")),
                               out, strict=True):
        core.run_batch(buf, du, nxt)
    assert out[0][0].tolist() == out[1][0].tolist() and out[0][1].tolist() == out[1][1].tolist()
    stepped = [s for k, s in enumerate(buf[:, 8]) if s]
    assert len(stepped) == len(seen[0])
    assert out[0][0][buf[:, 8] == 1].tolist() == [s[0] for s in seen[0]]


@settings(max_examples=300, deadline=None)
@given(i=st.floats(-200, 200), v=st.floats(-50.0, 400.0), u=st.floats(-50, 400), r=st.floats(-1e6, 1e6),
       Pa=st.floats(-5e3, 5e3), dP=st.floats(-50, 50), ma=st.floats(-5, 5), dm=st.floats(-0.1, 0.1),
       n_sub=st.integers(1, 25), h=st.floats(1e-7, 1e-4), clip=st.booleans(),
       imax=st.one_of(st.just(math.inf), st.floats(0.5, 250.0)))
def test_compiled_plant_integrator_equals_python(i, v, u, r, Pa, dP, ma, dm, n_sub, h, clip, imax):
    """The plant's RK4 loop in C (sim and the HIL plant use it when built) is the Python loop bit for bit,
    through the resistive region below v_min, the u clip and the source's current limit (held there or not)."""
    from service import _kernel
    from service.plant.rlc import rk4_steps

    args = (0.01, 1.12e-3, 6.8e-3, 40.0, 0.0, 200.0, float(clip), r, h, float(n_sub), Pa, dP, ma, dm, i, v, u, imax)
    try:
        want = rk4_steps(*args)
    except ZeroDivisionError:
        return
    got = _kernel.plant_steps(*args)
    assert all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(want, got, strict=True)), (want, got)


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_samples_answered_outside_the_law_same_answer(delay):
    """hold(seq, du_dt): a sample answered with a rate the law did not compute (a network source's idle mode);
    both cores predict over it alike, so every later command agrees."""
    scn, rows = _stream()
    T = 1.0 / scn.timing.control_rate_hz
    cores = [ControlCore(scn.controller, scn.model, T, delay), make_core(scn.controller, scn.model, T, delay, "c")]
    outside = {40: 1500.0, 41: -800.0, 42: 0.0, 150: 2500.0}
    seen = [[], []]
    for j, core in enumerate(cores):
        for k, r in enumerate(rows):
            if k in outside:
                core.hold(k, outside[k])
                continue
            o = core.step(Sample(*r[:6]), Incoming(r[6], r[7]))
            seen[j].append((o.du_dt, o.du_dt_next, o.i_pred, o.v_pred, o.u_pred, core.applied_rate()))
    assert seen[0] == seen[1]


@pytest.mark.parametrize("start", [2**53 - 4, 2**62 - 100])
def test_sequence_numbers_above_2_to_the_53_stay_exact_and_the_cores_agree(start):
    """The C tick carries seq as an integer: above 2^53 a double merges neighbours (2^53 + 1 -> 2^53), so the
    observer saw a gap where there was none, the late-command check and the plan lookup missed, and the command
    answered a seq the sample did not have. Steps, holds and skipped samples across 2^53, both cores."""
    scn, rows = _stream(80)
    T = 1.0 / scn.timing.control_rate_hz
    ctl = scn.controller.model_copy(update={"observer_gain": 0.2, "late_detect_V": 0.002})
    cores = [ControlCore(ctl, scn.model, T, 3), make_core(ctl, scn.model, T, 3, "c")]
    seen = [[], []]
    for j, core in enumerate(cores):
        for k, r in enumerate(rows):
            seq = start + k
            if k in (30, 31):
                continue  # skipped
            if k == 40:
                core.hold(seq)
                continue
            o = core.step(Sample(seq, *r[1:6]), Incoming(r[6], r[7]))
            seen[j].append((o.seq, o.du_dt, o.du_dt_next, o.i_pred, o.v_pred, o.u_pred, o.late, core.applied_rate()))
        assert [s[0] for s in seen[j]] == [start + k for k in range(len(rows)) if k not in (30, 31, 40)]
    assert seen[0] == seen[1]


def test_the_compiled_core_refuses_a_seq_it_cannot_carry_exactly():
    scn, rows = _stream(3)
    core = make_core(scn.controller, scn.model, 1e-4, 2, "c")
    with pytest.raises(ValueError, match="seq"):
        core.step(Sample(2.0**60, *rows[0][1:6]), Incoming(0.0, 0.0))  # a float that big is not exact
    with pytest.raises(ValueError, match="seq"):
        core.step(Sample(2**63, *rows[0][1:6]), Incoming(0.0, 0.0))
    core.step(Sample(7.0, *rows[0][1:6]), Incoming(0.0, 0.0))  # an integral float below 2^53, as before
    assert core.out.seq == 7
