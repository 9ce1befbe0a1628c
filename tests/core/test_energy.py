"""Identities between energy-space quantities, checked on simulated trajectories."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import exact_energy_along, scenario

from service.core import energy as en
from service.sim import run

R, L, C = 0.01, 1.12e-3, 6.8e-3


@pytest.fixture(scope="module")
def startup():
    """Paper start-up (i = 1 A -> 15 A): large p, E_t and Qdot during the transient."""
    res = run(scenario(timing={"duration_s": 0.04, "control_rate_hz": 20000.0, "plant_step_s": 1e-6},
                       controller={"K_per_s": 300.0}))
    return res.trace


def test_energy_balance_p_equals_Pu_minus_Pl_minus_Ri2_from_the_simulated_energy(startup):
    tr = startup
    E = 0.5 * (L * tr["i"] ** 2 + C * tr["v"] ** 2)
    dt = tr["t"][1] - tr["t"][0]
    p_numeric = (E[2:] - E[:-2]) / (2 * dt)  # differentiate the plant's own trajectory
    balance = (tr["u"] * tr["i"] - tr["v"] * tr["i_load"] - R * tr["i"] ** 2)[1:-1]
    # u ramps with a new slope each sample, so pdot jumps there and a central difference across a
    # jump errs by ~h |jump| / 4; skip the slew-limited first millisecond where the jumps are largest
    sl = tr["t"][1:-1] > 1e-3
    scale = np.abs(balance[sl]).max()
    assert scale > 500  # a real transient, not a steady state
    assert np.abs(p_numeric[sl] - balance[sl]).max() < 1e-3 * scale


def test_the_two_y_z_agree_with_exact_derivatives(startup):
    q = exact_energy_along(startup, R, L, C)
    assert np.abs(q["y_z"]).max() > 1000
    np.testing.assert_allclose(q["y_z_balance"], q["y_z"], rtol=0, atol=1e-9 * np.abs(q["y_z"]).max())


def test_interaction_rates_match_their_structural_forms(startup):
    tr = startup
    q = exact_energy_along(tr, R, L, C)
    # P^{r,out} = p + E/tau - P^u = -v i_2 (energy balance)
    np.testing.assert_allclose(q["P_r_out"], -tr["v"] * tr["i_load"], rtol=0, atol=1e-8 * 1200)
    # Qdot^{r,out} = -pdot + 4E_t - Qdot^u = Qdot_l + 2 (i dv/dt - v di/dt)  (KVL, KCL)
    structural = q["Qdot_l"] + 2 * (tr["i"] * q["dv"] - tr["v"] * q["di"])
    assert np.abs(structural).max() > 1e4
    np.testing.assert_allclose(q["Qdot_r_out"], structural, rtol=0, atol=1e-9 * np.abs(structural).max())


def test_normal_form_dy_z_equals_minus_4Et_plus_eta_plus_Qdot_u(startup):
    tr = startup
    q = exact_energy_along(tr, R, L, C)
    dt = tr["t"][1] - tr["t"][0]
    # within one control period u ramps linearly, so y_z is smooth there: compare the sampled derivative
    # (central difference across samples) with the normal form, away from the slew-limited start
    dy = (q["y_z"][2:] - q["y_z"][:-2]) / (2 * dt)
    nf = (-4 * q["E_t"] + q["eta"] + q["Qdot_u"])[1:-1]
    sl = slice(200, None)
    err = np.abs(dy[sl] - nf[sl])
    assert np.median(err) < 0.01 * np.abs(nf[sl]).max()


def test_generic_H_B_forms_equal_the_rlc_instance():
    rng = np.random.default_rng(0)
    for _ in range(20):
        i, v, u, i2, di, dv, du, di2 = rng.normal(size=8) * [10, 80, 80, 10, 1e3, 1e2, 1e4, 1e2]
        q = en.RLCEnergy().update(R, L, C, i, v, u, i2, di, dv, du, di2)
        H, B = en.rlc_H(L, C), en.rlc_B(R)
        x, xd = [i, v], [di, dv]
        xdd = [(du - R * di - dv) / L, (di - di2) / C]
        assert q.E == pytest.approx(en.stored_energy(H, x))
        assert q.E_t == pytest.approx(en.tangent_energy(H, xd))
        assert q.D == pytest.approx(en.dissipation(B, x))
        assert q.p == pytest.approx(en.energy_rate(H, x, xd))
        assert q.pdot == pytest.approx(en.energy_rate_dot(H, x, xd, xdd))
        assert q.Qdot_u == pytest.approx(en.port_reactive_rate(u, i, du, di))
        P_out, Q_out = en.interaction_rates(q.E, q.D, q.p, q.pdot, q.E_t, q.P_u, q.Qdot_u)
        assert q.P_r_out == pytest.approx(P_out)
        assert q.Qdot_r_out == pytest.approx(Q_out)


def test_z_out_is_constant_once_the_interconnection_is_removed():
    """Load disconnected at 20 ms: the P part of z_out stops moving at once (exactly, P^{r,out} = -v i_2 = 0);
    the Qdot part = integral of -2 Qdot_C stops moving once the internal LC transient has died out."""
    res = run(scenario(plant={"initial": {"i_A": 15.0, "v_V": 80.0, "u_V": 80.15}},
                       load={"kind": "steps", "value": 1200.0, "steps": [[0.02, 0.0]]},
                       timing={"duration_s": 0.3, "control_rate_hz": 10000.0}))
    tr = res.trace
    q = exact_energy_along(tr, R, L, C)
    dt = tr["t"][1] - tr["t"][0]
    z0 = np.concatenate([[0.0], np.cumsum(0.5 * dt * (q["P_r_out"][1:] + q["P_r_out"][:-1]))])
    z1 = np.concatenate([[0.0], np.cumsum(0.5 * dt * (q["Qdot_r_out"][1:] + q["Qdot_r_out"][:-1]))])
    before = tr["t"] < 0.02
    after = tr["t"] > 0.0201
    assert np.ptp(z0[before]) > 10.0  # it moved while connected (1.2 kW for 20 ms = 24 J)
    assert np.ptp(z0[after]) < 1e-9  # and not at all afterwards
    late = tr["t"] > 0.25
    assert np.ptp(z1[late]) < 1e-3 * np.ptp(z1)
    # the streaming estimator (measured derivatives, lag 2 tau) agrees once its window has passed
    late_est = tr["t"] > 0.03
    assert np.ptp(tr["z_out0"][late_est]) < 0.05
