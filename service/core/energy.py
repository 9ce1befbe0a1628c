"""Energy-space quantities of the paper (Appendix A), generic and for the RLC + CPL instance.

Generic component with state x, inertia matrix H and dissipation matrix B (both constant here):

    E    = 1/2 x^T H x                  stored energy (J)                     [Defn StoredEnergy]
    E_t  = 1/2 xdot^T H xdot            stored energy in tangent space (J/s^2) [Defn StoredEnergyTangent]
    D    = x^T B x                      dissipation (W); tau = E / D (s)      [Defn TimeConstant]
    p    = dE/dt = x^T H xdot           (W)
    pdot = xdot^T H xdot + x^T H xddot = 2 E_t + x^T H xddot   (W/s)
    P    = e f,  Qdot = e df/dt - f de/dt   at a port (W, W/s)        [Defn RealPower, ReacPower]

Outgoing interaction variable rates (paper Eqn Eqn_IntModelInv):

    P^{r,out}    = p + E/tau - P^u - P^m                 (W)
    Qdot^{r,out} = -pdot + 4 E_t - Qdot^u - Qdot^m       (W/s)
    z_out        = integral of (P^{r,out}, Qdot^{r,out}) dt   (J, W)

Output of interest and normal form (Eqn IntModelOutput_v1, NormalFormOutput):

    y_z     = E/tau - P^u - P^m                          (W)
    dy_z/dt = -4 E_t + eta + u_z,   u_z = Qdot^u         (W/s)

RLC instance (x = [i, v], H = diag(L, C), B = diag(R, 0), control port (u, i), matched port (u_m, i),
load port (v, i_2)):

    y_z  = R i^2 - u i - u_m i                   model-based, needs R     (Eqn OutputRLC)
    y_z  = -(P_l + p) = -(v i_2 + L i di/dt + C v dv/dt)   R-free, from the energy balance
    eta  = 4 E_t + 2 (R i - u - u_m) di/dt       so that dy_z/dt = -4E_t + eta + Qdot^u
    P^{r,out}    = -v i_2 = -P_l                 (follows from the energy balance)
    Qdot^{r,out} = Qdot_l + 2 (i dv/dt - v di/dt)  (follows from KVL/KCL; see tests)

The last two ("port forms") need no p and no second derivative, so an estimator working from
measured, filtered derivatives gets them without the filter's lag on p; RLCEnergy gives both.

The printed Eqn ControlDynRLC_eta writes 4E_t as 2L di/dt + 2C dv/dt (squares missing) and counts it
twice; the expressions above are derived, and tests check them on simulated trajectories.
"""

from __future__ import annotations

from collections.abc import Sequence

Vec = Sequence[float]
Mat = Sequence[Sequence[float]]


def quad(M: Mat, a: Vec, b: Vec) -> float:
    """a^T M b."""
    return sum(a[r] * sum(M[r][c] * b[c] for c in range(len(b))) for r in range(len(a)))


def stored_energy(H: Mat, x: Vec) -> float:
    """E = 1/2 x^T H x (J)."""
    return 0.5 * quad(H, x, x)


def tangent_energy(H: Mat, xdot: Vec) -> float:
    """E_t = 1/2 xdot^T H xdot (J/s^2)."""
    return 0.5 * quad(H, xdot, xdot)


def dissipation(B: Mat, x: Vec) -> float:
    """D = x^T B x (W)."""
    return quad(B, x, x)


def energy_rate(H: Mat, x: Vec, xdot: Vec) -> float:
    """p = dE/dt = x^T H xdot (W), H constant."""
    return quad(H, x, xdot)


def energy_rate_dot(H: Mat, x: Vec, xdot: Vec, xddot: Vec) -> float:
    """pdot = xdot^T H xdot + x^T H xddot (W/s)."""
    return quad(H, xdot, xdot) + quad(H, x, xddot)


def port_power(e: float, f: float) -> float:
    """P = e f (W)."""
    return e * f


def port_reactive_rate(e: float, f: float, edot: float, fdot: float) -> float:
    """Qdot = e df/dt - f de/dt (W/s)."""
    return e * fdot - f * edot


def interaction_rates(E: float, D: float, p: float, pdot: float, E_t: float,
                      P_u: float, Qdot_u: float, P_m: float = 0.0, Qdot_m: float = 0.0) -> tuple[float, float]:
    """(P^{r,out}, Qdot^{r,out}) from the definition (paper Eqn Eqn_IntModelInv); E/tau = D."""
    return p + D - P_u - P_m, -pdot + 4.0 * E_t - Qdot_u - Qdot_m


class RLCEnergy:
    """All energy-space quantities of the RLC + CPL component at one instant (filled in place).

    Inputs are the state (i A, v V, u V, i_2 A), first derivatives (A/s, V/s, V/s, A/s) and the
    matched disturbance voltage u_m (V). Second derivatives come from the model,
    L d2i/dt2 = du/dt - R di/dt - dv/dt and C d2v/dt2 = di/dt - di_2/dt, so pdot needs no
    second numerical differentiation.
    """

    __slots__ = ("E", "E_t", "D", "tau", "p", "pdot", "P_u", "Qdot_u", "P_l", "Qdot_l", "P_m",
                 "y_z", "y_z_balance", "eta", "P_r_out", "Qdot_r_out", "P_r_out_port", "Qdot_r_out_port")

    def __init__(self) -> None:
        for k in self.__slots__:
            setattr(self, k, 0.0)

    def update(self, R: float, L: float, C: float, i: float, v: float, u: float, i2: float,
               di: float, dv: float, du: float, di2: float, u_m: float = 0.0) -> RLCEnergy:
        E = 0.5 * (L * i * i + C * v * v)
        E_t = 0.5 * (L * di * di + C * dv * dv)
        D = R * i * i
        p = L * i * di + C * v * dv
        ddi = (du - R * di - dv) / L
        ddv = (di - di2) / C
        pdot = L * di * di + C * dv * dv + L * i * ddi + C * v * ddv
        P_u = u * i
        Qdot_u = u * di - i * du
        P_m = u_m * i
        Qdot_m = u_m * di
        self.E, self.E_t, self.D, self.p, self.pdot = E, E_t, D, p, pdot
        self.tau = E / D if D > 0.0 else float("inf")
        self.P_u, self.Qdot_u, self.P_m = P_u, Qdot_u, P_m
        self.P_l = v * i2
        self.Qdot_l = v * di2 - i2 * dv
        self.y_z = D - P_u - P_m
        self.y_z_balance = -(self.P_l + p)
        self.eta = 4.0 * E_t + 2.0 * (R * i - u - u_m) * di
        self.P_r_out = p + D - P_u - P_m
        self.Qdot_r_out = -pdot + 4.0 * E_t - Qdot_u - Qdot_m
        # the same two rates from the load port alone (equal under the circuit equations; no p, no pdot)
        self.P_r_out_port = -self.P_l
        self.Qdot_r_out_port = self.Qdot_l + 2.0 * (i * dv - v * di)
        return self


def rlc_H(L: float, C: float) -> list[list[float]]:
    return [[L, 0.0], [0.0, C]]


def rlc_B(R: float) -> list[list[float]]:
    return [[R, 0.0], [0.0, 0.0]]
