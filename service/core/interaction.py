"""The interaction variables a component exchanges with its neighbours, and the reference it takes from them.

Paper Sec. "Multi-layered distributed control design": a component's incoming interaction variable is what its
neighbours send out, P^{r,in} = -sum_j P_j^{r,out} (W), dP^{r,in}/dt = -sum_j dP_j^{r,out}/dt (W/s). Each
neighbour's P_j^{r,out} was measured at its own time t_j; at this sample's time t it is carried forward (or back)
along its announced rate over the age t - t_j (first-order hold), by at most ``horizon_s`` either way, when both
are on one clock (|t - t_j| <= ``stale_s``). Pure: the caller decides which neighbours are fresh.
"""

from __future__ import annotations


def outgoing_power_at(t_s: float, t_j_s: float, P_j_W: float, P_dot_j_W_per_s: float, stale_s: float,
                      horizon_s: float) -> float:
    """Neighbour j's outgoing power P_j^{r,out} (W) at time t_s, from its value P_j_W at t_j_s and its rate.

    Backwards too: a sample answered late (catch-up after a stall) is older than the neighbour's newest message,
    which at -18 kW/s was 96 W ahead of it and, as the prediction's load power, swung the command by 2.3 kV/s.
    In lockstep the ages are 0 and this is P_j_W itself."""
    age = t_s - t_j_s
    if 0.0 < abs(age) <= stale_s:
        return P_j_W + P_dot_j_W_per_s * max(-horizon_s, min(age, horizon_s))
    return P_j_W


def incoming_reference(t_s: float, neighbours, stale_s: float, horizon_s: float) -> tuple[float, float]:
    """(P^{r,in} W, dP^{r,in}/dt W/s) = -sum over neighbours of (P_j^{r,out} at t_s, dP_j^{r,out}/dt), from
    (t_j_s, P_j_W, P_dot_j_W_per_s) per neighbour."""
    P_in = P_in_dot = 0.0
    for t_j, P_j, P_dot_j in neighbours:
        P_in -= outgoing_power_at(t_s, t_j, P_j, P_dot_j, stale_s, horizon_s)
        P_in_dot -= P_dot_j
    return P_in, P_in_dot
