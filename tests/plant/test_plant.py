"""The plant integrator converges; the sensor chain is seeded and quantises."""

from __future__ import annotations

import importlib.util

import pytest

from schemas.scenario import PlantConfig, ProfileConfig, SensorConfig
from service.plant.profiles import Profile
from service.plant.rlc import RLCPlant, Sensor


def trajectory(n_sub: int, r: float = 3000.0):
    plant = RLCPlant(PlantConfig(initial={"i_A": 1.0, "v_V": 80.0}),
                     Profile(ProfileConfig(kind="sines", value=1200.0, components=[{"amplitude": 200, "freq_hz": 20}])))
    for _ in range(100):
        plant.advance(r, 1e-4, n_sub)
    return plant.i, plant.v, plant.u


def test_rk4_converges_at_fourth_order():
    ref = trajectory(200)
    errs = [abs(trajectory(n)[0] - ref[0]) for n in (1, 2, 4)]
    assert errs[0] > 0
    assert errs[0] / errs[1] > 10 and errs[1] / errs[2] > 10  # ~16 for 4th order


def test_source_voltage_integrates_the_rate_and_stays_within_its_limits():
    plant = RLCPlant(PlantConfig(initial={"i_A": 15.0, "v_V": 80.0, "u_V": 80.0}, source={"u_max_V": 81.0}),
                     Profile(ProfileConfig(value=1200.0)))
    plant.advance(5000.0, 1e-4, 10)
    assert plant.u == pytest.approx(80.5)
    plant.advance(5000.0, 1e-3, 10)
    assert plant.u == 81.0


def test_sensor_noise_is_seeded_and_quantised():
    cfg = SensorConfig(noise_v_V=0.05, noise_i_A=0.05, lsb_v_V=0.025, lsb_i_A=0.01)
    a = [Sensor(cfg, 3).measure(k, 0.0, 15.0, 80.0, 80.1, 15.0) for k in range(3)]
    s1, s2 = Sensor(cfg, 3), Sensor(cfg, 3)
    seq1 = [s1.measure(k, k * 1e-4, 15.0, 80.0, 80.1, 15.0) for k in range(5000)]
    seq2 = [s2.measure(k, k * 1e-4, 15.0, 80.0, 80.1, 15.0) for k in range(5000)]
    assert seq1 == seq2 and a[0] == seq1[0]
    assert all(abs(s.v / 0.025 - round(s.v / 0.025)) < 1e-9 for s in seq1)
    vs = [s.v for s in seq1]
    mean = sum(vs) / len(vs)
    std = (sum((x - mean) ** 2 for x in vs) / len(vs)) ** 0.5
    assert std == pytest.approx((0.05**2 + 0.025**2 / 12) ** 0.5, rel=0.1)
    assert seq1 != [Sensor(cfg, 4).measure(k, k * 1e-4, 15.0, 80.0, 80.1, 15.0) for k in range(5000)]


def test_the_hil_plant_schedule_applies_commands_then_plans_then_holds():
    """The realtime plant's fixed schedule (service.plant.rlc.CommandSchedule), d = 2: the command answering j acts
    over period j + 2; missing, its predecessor's plan acts; with neither, u is held; a late command is dropped
    but its plan still serves the next period."""
    from service.plant.rlc import CommandSchedule

    s = CommandSchedule(2)
    assert s.take(0) == (0.0, False) and s.take(1) == (0.0, False)  # nothing answered before sample 0
    s.arrive(0, 100.0, 110.0)
    s.arrive(1, 200.0, 210.0)
    assert s.take(2) == (100.0, True) and s.take(3) == (200.0, True)
    # the command answering 2 is missing at period 4: the plan sent with the answer to 1 acts
    assert s.take(4) == (210.0, False)
    # nor does 3 arrive in time for period 5: 2 never came, so there is no plan either: hold
    assert s.take(5) == (0.0, False)
    # 3 arrives late (after period 5), 4 never: 3 is dropped, but its plan is for period 6
    s.arrive(3, 400.0, 410.0)
    assert s.take(6) == (410.0, False)
    s.arrive(5, 600.0, 610.0)
    assert s.take(7) == (600.0, True)
    assert s.counts == {"late": 1, "planned_periods": 2, "stale_periods": 3}
    lock = CommandSchedule(0)  # lockstep: the answer to k acts at k (the delay line follows); a timeout -> plan
    lock.arrive(0, 5.0, 6.0)
    assert lock.take(0) == (5.0, True) and lock.take(1) == (6.0, False) and lock.take(2) == (0.0, False)


def test_the_schedule_never_applies_anything_but_the_command_its_plan_or_a_hold():
    """Any arrival pattern (commands on time, late, never): each period gets the command meant for it, else the
    plan sent with its predecessor, else 0; every period is counted once; every late command is counted."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from service.plant.rlc import CommandSchedule

    @settings(max_examples=200, deadline=None)
    @given(d=st.integers(0, 4), fate=st.lists(st.sampled_from(["on_time", "late", "lost"]), min_size=1, max_size=60))
    def check(d, fate):
        s = CommandSchedule(d)
        cmd = {j: (1000.0 + j, 2000.0 + j) for j in range(len(fate))}
        n = len(fate) + d + 1
        fresh = 0
        for k in range(n):
            j = k - d
            # a command on time is in by its period; a late one comes just after (before the next period)
            if 0 <= j < len(fate) and fate[j] == "on_time":
                s.arrive(j, *cmd[j])
            r, is_cmd = s.take(k)
            if 0 <= j < len(fate) and fate[j] == "on_time":
                assert (r, is_cmd) == (cmd[j][0], True)
                fresh += 1
            else:
                assert not is_cmd
                prev_ok = 0 <= j - 1 < len(fate) and fate[j - 1] in ("on_time", "late")
                assert r == (cmd[j - 1][1] if prev_ok else 0.0)
            if 0 <= j < len(fate) and fate[j] == "late":
                s.arrive(j, *cmd[j])
        c = s.counts
        assert fresh + c["planned_periods"] + c["stale_periods"] == n
        assert c["late"] == sum(1 for f in fate[:n - d - 1] if f == "late")

    check()


def _ramped(impl: str, i_max: float | None, r: float, periods: int = 300) -> list[tuple[float, float, float]]:
    """The plant from its 1.2 kW operating point with u ramped at r V/s: (i, v, u) after each 0.1 ms period."""
    plant = RLCPlant(PlantConfig(initial={"i_A": 15.0, "v_V": 80.0, "u_V": 80.15},
                                 source={"i_max_A": i_max} if i_max is not None else {}),
                     Profile(ProfileConfig(value=1200.0)), impl=impl)
    out = []
    for _ in range(periods):
        plant.advance(r, 1e-4, 10)
        out.append((plant.i, plant.v, plant.u))
    return out


@pytest.mark.parametrize("r", [2e4, -2e4])
def test_the_source_current_stays_within_its_limit_where_it_would_exceed_it(r):
    """Ramping u up (down) drives i far past +20 A (-20 A) unlimited; with i_max_A = 20 it stops at the limit and
    stays there while the branch pushes further, u goes on as commanded, and the capacitor gets i_max: v follows
    C dv/dt = i_max - P / v."""
    free = _ramped("python", None, r)
    held = _ramped("python", 20.0, r)
    assert max(abs(i) for i, _, _ in free) > 40.0
    assert max(abs(i) for i, _, _ in held) <= 20.0
    at_limit = [k for k, (i, _, _) in enumerate(held) if abs(i) == 20.0]
    assert len(at_limit) > 50 and at_limit == list(range(at_limit[0], at_limit[-1] + 1))  # held, not chattering
    assert [x[2] for x in held] == [x[2] for x in free]  # u is the converter's command either way
    k = at_limit[5]
    i, v, _ = held[k]
    dv_dt = (held[k + 1][1] - held[k - 1][1]) / 2e-4
    assert dv_dt == pytest.approx((i - 1200.0 / v) / 6.8e-3, rel=1e-3)


def test_a_source_current_limit_the_run_never_reaches_changes_nothing():
    assert _ramped("python", 1e3, 2e4) == _ramped("python", None, 2e4)


@pytest.mark.skipif(not importlib.util.find_spec("service._kernel"), reason="compiled kernel not built")
@pytest.mark.parametrize("r", [2e4, -2e4])
def test_the_compiled_plant_holds_the_current_limit_to_the_same_bits(r):
    assert _ramped("c", 20.0, r) == _ramped("python", 20.0, r)


def test_an_initial_current_beyond_the_limit_is_refused_with_the_fields_named():
    from schemas.scenario import ScenarioError, scenario_from_dict

    with pytest.raises(ScenarioError, match=r"plant: .*initial.i_A = 30 A is beyond source.i_max_A = 20 A"):
        scenario_from_dict({"plant": {"initial": {"i_A": 30.0}, "source": {"i_max_A": 20.0}}})


def test_a_source_limited_below_what_a_load_step_needs_holds_its_current_and_loses_the_bus():
    """paper-feasibility's step to 1.8 kW needs 22.5 A: with i_max_A = 23.5 the run is the unlimited one (its peak is
    23.0 A); with 20 A the source sits at its limit and v collapses, which the run reports as a divergence."""
    import numpy as np
    from conftest import SCENARIOS

    from schemas.scenario import load_scenario
    from service.sim import run

    def sim(*ov):
        return run(load_scenario(SCENARIOS / "paper-feasibility.toml", ["timing.duration_s=0.6", *ov]))

    free, roomy, tight = sim(), sim("plant.source.i_max_A=23.5"), sim("plant.source.i_max_A=20.0")
    assert np.abs(free.trace["i"]).max() > 22.5 and np.array_equal(roomy.trace["i"], free.trace["i"])
    assert np.abs(tight.trace["i"]).max() == 20.0 and np.sum(tight.trace["i"] == 20.0) > 100
    assert tight.metrics["failures"][0]["criterion"] == "divergence" and tight.metrics["diverged_at_s"] > 0.35
