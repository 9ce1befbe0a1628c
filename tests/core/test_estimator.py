"""The derivative filter does what its docstring says: lag 2 tau, noise gain sigma / (2 sqrt(f_s tau^3))."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.estimator import EnergyEstimator, EwLineFit


def feed(fit: EwLineFit, ts, ys):
    slopes, values = [], []
    for t, y in zip(ts, ys, strict=True):
        fit.update(t, (y,))
        slopes.append(fit.slope[0])
        values.append(fit.value[0])
    return np.array(slopes), np.array(values)


def test_ramp_slope_is_exact_even_with_irregular_spacing():
    rng = np.random.default_rng(1)
    ts = np.cumsum(rng.uniform(20e-6, 180e-6, 3000))  # 5.5 kHz average, +-80 % jitter
    slopes, values = feed(EwLineFit(1, 5e-4), ts, 3.0 + 250.0 * ts)
    np.testing.assert_allclose(slopes[2:], 250.0, rtol=1e-7)
    np.testing.assert_allclose(values[2:], 3.0 + 250.0 * ts[2:], rtol=1e-9)


def test_slope_lags_by_two_tau_on_a_parabola():
    tau, fs, a = 5e-4, 100_000.0, 4000.0
    ts = np.arange(0, 0.02, 1 / fs)
    slopes, _ = feed(EwLineFit(1, tau), ts, 0.5 * a * ts**2)
    k = ts > 20 * tau  # after the window has filled
    lag = ts[k] - slopes[k] / a  # the time at which the true derivative a t equals the estimate
    assert np.median(lag) == pytest.approx(2 * tau, rel=0.02)


@pytest.mark.parametrize("tau", [2e-4, 5e-4, 1e-3])
def test_noise_gain_matches_the_formula_and_beats_a_backward_difference(tau):
    fs, sigma = 10_000.0, 0.05
    rng = np.random.default_rng(7)
    ts = np.arange(0, 4.0, 1 / fs)
    ys = 80.0 + sigma * rng.standard_normal(len(ts))
    slopes, _ = feed(EwLineFit(1, tau), ts, ys)
    measured = slopes[int(50 * tau * fs) + 10:].std()
    predicted = sigma / (2 * math.sqrt(fs * tau**3))
    assert measured == pytest.approx(predicted, rel=0.12)
    backward = np.diff(ys) * fs
    assert backward.std() == pytest.approx(sigma * math.sqrt(2) * fs, rel=0.05)
    assert measured < backward.std() / 5


def test_non_advancing_timestamps_are_ignored():
    fit = EwLineFit(1, 1e-3)
    assert fit.update(0.0, (1.0,))
    assert fit.update(1e-4, (2.0,))
    before = (fit.value[0], fit.slope[0])
    assert not fit.update(1e-4, (99.0,))  # duplicate
    assert not fit.update(5e-5, (99.0,))  # backwards
    assert (fit.value[0], fit.slope[0]) == before


def test_unrolled_three_channel_update_equals_the_general_one():
    rng = np.random.default_rng(3)
    a, b = EwLineFit(3, 4e-4), EwLineFit(3, 4e-4)
    t = 0.0
    for _ in range(500):
        t += rng.uniform(5e-5, 2e-4)
        y = rng.normal(size=3).tolist()
        a.update(t, y)
        b.update3(t, *y)
    assert a.value == b.value and a.slope == b.slope


def test_estimator_y_z_balance_needs_no_R():
    """Two estimators differing only in R: the energy-balance y_z is identical, the model one is not."""
    e1, e2 = EnergyEstimator(0.01, 1.12e-3, 6.8e-3, 5e-4), EnergyEstimator(0.05, 1.12e-3, 6.8e-3, 5e-4)
    for k in range(50):
        t = k * 1e-4
        args = (t, 15.0 + 0.1 * math.sin(300 * t), 80.0 + 0.2 * math.cos(300 * t), 80.2, 15.0, 0.0)
        q1, q2 = e1.update(*args), e2.update(*args)
    assert q1.y_z_balance == q2.y_z_balance
    assert q1.y_z != q2.y_z
