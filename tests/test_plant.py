"""The plant integrator converges; the sensor chain is seeded and quantises."""

from __future__ import annotations

import pytest

from schemas.scenario import PlantConfig, ProfileConfig, SensorConfig
from service.plant import RLCPlant, Sensor
from service.profiles import Profile


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
