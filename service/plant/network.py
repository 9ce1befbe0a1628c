"""The physics of a DC network: sources, lines, buses and loads in node/branch form, integrated by RK4.

State (SI units):

    i_s  source-branch currents (A), one per source: L_s di_s/dt = u_s - R_s i_s - v_s; with a current limit
         (limits.i_max_A) held within +-i_max as the one-source plant holds it (``rlc`` module docstring)
    u_s  source voltages (V): du_s/dt = r_s, the commanded rate, held over a control period; u_s stays in
         [u_min, u_max] (evaluated as clip(u + r tau) at each stage, as the one-source plant does)
    i_l  line currents (A), positive from the line's a end to its b end: L_l di_l/dt = v_a - v_b - R_l i_l;
         an open breaker holds i_l = 0 (an ideal breaker: opening sets the current to zero)
    v_n  node voltages (V), the sources' terminals first, then the buses:
         C_n dv_n/dt = (source current into n) - (line currents leaving n) + (entering n) - (load currents)

A constant-power load draws P / v (P v / v_min^2 below v_min, as the one-source plant's CPL), a resistive one
v / R. Load powers are taken linear over each control period from its two ends, as in ``rlc.RLCPlant``.

``steps`` is the Python reference; ``service/plant/network.c`` repeats it operation for operation (the same
results to the bit), and ``integrator`` picks one. Pure: no clocks, no I/O.
"""

from __future__ import annotations

import math
from array import array

from schemas.network import NetworkScenario
from service.plant.profiles import Profile
from service.plant.rlc import pick_twin

CPL, RESISTIVE = 0.0, 1.0
SRC_W, LINE_W, LOAD_W = 5, 5, 5  # doubles per row: source R, L, u_min, u_max, i_max (A, inf: none);
# line R, L, a, b, closed; load node, kind, P at the period's start (W) or G (S), dP per substep (W), v_min (V)


def steps(h: float, n_sub: int, src: array, r: array, lines: array, node_C: array, loads: array, i_s: array,
          u_s: array, i_l: array, v_n: array) -> None:
    """n_sub RK4 steps of h seconds, updating i_s, u_s, i_l, v_n in place (flat arrays of doubles; rows of
    src, lines and loads as SRC_W, LINE_W, LOAD_W above). Source s's terminal is node s."""
    ns, nl, nn, nld = len(i_s), len(i_l), len(v_n), len(loads) // LOAD_W
    hh = 0.5 * h
    k1s, k2s, k3s, k4s = [0.0] * ns, [0.0] * ns, [0.0] * ns, [0.0] * ns
    k1l, k2l, k3l, k4l = [0.0] * nl, [0.0] * nl, [0.0] * nl, [0.0] * nl
    k1v, k2v, k3v, k4v = [0.0] * nn, [0.0] * nn, [0.0] * nn, [0.0] * nn
    ts, tl, tv, uu = [0.0] * ns, [0.0] * nl, [0.0] * nn, [0.0] * ns
    inj = [0.0] * nn
    for k in range(n_sub):
        fk = float(k)
        for stage in range(4):
            if stage == 0:
                frac, tau, xs, xl, xv = 0.0, 0.0, i_s, i_l, v_n
                ds, dl, dv = k1s, k1l, k1v
            elif stage == 1:
                frac, tau, xs, xl, xv = 0.5, hh, ts, tl, tv
                ds, dl, dv = k2s, k2l, k2v
            elif stage == 2:
                frac, tau, xs, xl, xv = 0.5, hh, ts, tl, tv
                ds, dl, dv = k3s, k3l, k3v
            else:
                frac, tau, xs, xl, xv = 1.0, h, ts, tl, tv
                ds, dl, dv = k4s, k4l, k4v
            for j in range(ns):
                uu[j] = min(max(u_s[j] + r[j] * tau, src[SRC_W * j + 2]), src[SRC_W * j + 3])
            _derivatives(fk + frac, src, lines, node_C, loads, uu, xs, xl, xv, ds, dl, dv, inj, ns, nl, nn, nld)
            if stage < 3:
                step = h if stage == 2 else hh
                dns = k3s if stage == 2 else (k1s if stage == 0 else k2s)
                dnl = k3l if stage == 2 else (k1l if stage == 0 else k2l)
                dnv = k3v if stage == 2 else (k1v if stage == 0 else k2v)
                for j in range(ns):
                    ts[j] = i_s[j] + step * dns[j]
                    im = src[SRC_W * j + 4]
                    if im != math.inf:
                        ts[j] = min(max(ts[j], -im), im)
                for j in range(nl):
                    tl[j] = i_l[j] + step * dnl[j]
                for j in range(nn):
                    tv[j] = v_n[j] + step * dnv[j]
        h6 = h / 6.0
        for j in range(ns):
            i_s[j] += h6 * (k1s[j] + 2.0 * k2s[j] + 2.0 * k3s[j] + k4s[j])
            im = src[SRC_W * j + 4]
            if im != math.inf:
                i_s[j] = min(max(i_s[j], -im), im)
            u_s[j] = min(max(u_s[j] + r[j] * h, src[SRC_W * j + 2]), src[SRC_W * j + 3])
        for j in range(nl):
            if lines[LINE_W * j + 4] != 0.0:
                i_l[j] += h6 * (k1l[j] + 2.0 * k2l[j] + 2.0 * k3l[j] + k4l[j])
        for j in range(nn):
            v_n[j] += h6 * (k1v[j] + 2.0 * k2v[j] + 2.0 * k3v[j] + k4v[j])


def _derivatives(kf: float, src, lines, node_C, loads, u, xs, xl, xv, ds, dl, dv, inj, ns, nl, nn, nld) -> None:
    """d/dt of (i_s, i_l, v_n) at the state (xs, xl, xv) with source voltages u; kf: the substep index plus the
    stage's fraction of it (where the loads' powers are taken)."""
    for n in range(nn):
        inj[n] = 0.0
    for j in range(ns):
        o = SRC_W * j
        d = (u[j] - src[o] * xs[j] - xv[j]) / src[o + 1]
        im = src[o + 4]
        if im != math.inf and (xs[j] >= im and d > 0.0 or xs[j] <= -im and d < 0.0):
            d = 0.0  # at its current limit, pushed further
        ds[j] = d
        inj[j] += xs[j]
    for j in range(nl):
        o = LINE_W * j
        if lines[o + 4] != 0.0:
            a, b = int(lines[o + 2]), int(lines[o + 3])
            dl[j] = (xv[a] - xv[b] - lines[o] * xl[j]) / lines[o + 1]
            inj[a] -= xl[j]
            inj[b] += xl[j]
        else:
            dl[j] = 0.0
    for j in range(nld):
        o = LOAD_W * j
        n = int(loads[o])
        v = xv[n]
        if loads[o + 1] == CPL:
            P = loads[o + 2] + kf * loads[o + 3]
            vmin = loads[o + 4]
            inj[n] -= P / v if v >= vmin else P * v / (vmin * vmin)
        else:
            inj[n] -= v * loads[o + 2]
    for n in range(nn):
        dv[n] = inj[n] / node_C[n]


def integrator(impl: str = "auto"):
    """The network integrator: the compiled twin for "c" (ImportError if not built), the reference for "python",
    and for "auto" the compiled one when it was built."""
    return pick_twin(impl, steps, "network_steps", "network integrator")


def load_profiles(net: NetworkScenario) -> list[SwitchedProfile | None]:
    """Each load's profile in the scenario's order: a constant-power load's switched, scaled profile (W), None for
    a resistive one."""
    return [SwitchedProfile(Profile(ld, net.base_dir), ld.active_from_s, net.load_scale) if ld.type == "cpl" else None
            for ld in net.loads.values()]


class LoadForecast:
    """What the interconnection layer knows of the loads ahead of time, from the scenario alone (not the plant's
    state): each load's config (``load_list``) and, for a constant-power one, its profile (``profiles``, whose
    ``range_over(t0, t1)`` gives P lo, P hi W and their rates W/s over a window). The plant's own profiles are built
    by the same load_profiles, so the layer's boxes are those of the loads the plant draws."""

    def __init__(self, net: NetworkScenario):
        self.load_list = list(net.loads.values())
        self.profiles = load_profiles(net)


class SwitchedProfile:
    """A load profile that draws nothing before ``from_s`` (s), a load switched in, scaled by ``scale``."""

    def __init__(self, profile: Profile, from_s: float, scale: float = 1.0):
        self.profile, self.from_s, self.scale = profile, from_s, scale

    def value(self, t: float) -> float:
        return self.scale * self.profile.value(t) if t >= self.from_s else 0.0

    def rate(self, t: float) -> float:
        return self.scale * self.profile.rate(t) if t >= self.from_s else 0.0

    def range_over(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """(min, max, min rate, max rate) over [t0, t1] (W, W/s)."""
        if t1 < self.from_s:
            return 0.0, 0.0, 0.0, 0.0
        lo, hi, dlo, dhi = (self.scale * x for x in self.profile.range_over(max(t0, self.from_s), t1))
        if t0 < self.from_s:
            lo, hi, dlo, dhi = min(lo, 0.0), max(hi, 0.0), min(dlo, 0.0), max(dhi, 0.0)
        return lo, hi, dlo, dhi

    def step_times(self) -> list[float]:
        """When it jumps: its switching-in, its steps and its switching on and off (s)."""
        out = [self.from_s] if self.from_s > 0 else []
        return out + [t for t in self.profile.event_times() if t >= self.from_s]


class NetworkPlant:
    """A network scenario's circuit: state, breakers, and ``advance`` over one control period."""

    def __init__(self, net: NetworkScenario, impl: str = "auto"):
        self._steps = integrator(impl)
        self.sources = list(net.sources)
        self.buses = list(net.buses)
        self.line_names = list(net.lines)
        self.node_index = {name: k for k, name in enumerate(net.nodes())}
        v0 = net.nominal_v_V
        self.src = array("d")
        self.i_s, self.u_s = array("d"), array("d")
        for s in net.sources.values():
            self.src.extend((s.R_ohm, s.L_H, s.limits.u_min_V, s.limits.u_max_V,
                             s.limits.i_max_A if s.limits.i_max_A is not None else math.inf))
            self.i_s.append(0.0)
            self.u_s.append(min(max(s.v0_V or v0, s.limits.u_min_V), s.limits.u_max_V))
        self.node_C = array("d", [s.C_F for s in net.sources.values()] + [b.C_F for b in net.buses.values()])
        self.v_n = array("d", [s.v0_V or v0 for s in net.sources.values()] + [b.v0_V or v0 for b in
                                                                              net.buses.values()])
        self.lines = array("d")
        for ln in net.lines.values():
            self.lines.extend((ln.R_ohm, ln.L_H, self.node_index[ln.a], self.node_index[ln.b], float(ln.closed)))
        self.i_l = array("d", [0.0] * len(net.lines))
        # per node, (line, +1 if the line leaves the node at its a end, -1 at its b end): O(1) look-ups per node
        self._ends: list[list[tuple[int, float]]] = [[] for _ in self.node_index]
        for j, ln in enumerate(net.lines.values()):
            self._ends[self.node_index[ln.a]].append((j, 1.0))
            self._ends[self.node_index[ln.b]].append((j, -1.0))
        for name, s in net.sources.items():
            if not s.connected:
                for j in self.lines_at(name):
                    self.lines[LINE_W * j + 4] = 0.0
        self.load_list = list(net.loads.values())
        self.load_names = list(net.loads)
        self.load_scale = net.load_scale
        self.profiles = load_profiles(net)
        self.loads = array("d")
        for ld in self.load_list:
            G = net.load_scale / ld.R_ohm if ld.type == "resistive" else 0.0
            self.loads.extend((self.node_index[ld.bus], CPL if ld.type == "cpl" else RESISTIVE, G, 0.0, ld.v_min_V))
        self.r = array("d", [0.0] * len(self.sources))
        self.t = 0.0
        self._supplied: list[bool] | None = None  # supplied(), recomputed after a breaker moves

    def start_steady(self, shares: list[float], v_nom: float) -> None:
        """Start from a DC operating point instead of rest: the connected sources deliver the loads' current at t = 0
        in the given shares, lines carry the flow Ohm's law gives, the buses' mean voltage is v_nom, each source's
        u covers its own R drop (disconnected sources sit at v_nom with no current). Loads taken as currents at
        v_nom, so a small transient remains where the buses are not exactly at v_nom."""
        import numpy as np

        nn, ns = len(self.v_n), len(self.i_s)
        on = [j for j in range(ns) if self.connected(self.sources[j])]
        demand = 0.0
        inj = np.zeros(nn)
        for k, ld in enumerate(self.load_list):
            n = self.node_index[ld.bus]
            i = (self.profiles[k].value(0.0) / v_nom if ld.type == "cpl" else
                 (self.load_scale * v_nom / ld.R_ohm if ld.active_from_s <= 0.0 else 0.0))
            inj[n] -= i
            demand += i
        weight = sum(shares[j] for j in on) or 1.0
        for j in on:
            inj[j] += shares[j] / weight * demand
        lap = np.zeros((nn, nn))
        for j in range(len(self.i_l)):
            if self.closed(j):
                o = LINE_W * j
                a, b, g = int(self.lines[o + 2]), int(self.lines[o + 3]), 1.0 / max(self.lines[o], 1e-6)
                lap[a, a] += g
                lap[b, b] += g
                lap[a, b] -= g
                lap[b, a] -= g
        live = [n for n in range(nn) if lap[n, n] > 0.0]
        v = np.full(nn, v_nom)
        if live:
            buses = [n for n in live if n >= ns] or live
            sub_lap = lap[np.ix_(live, live)]
            mean_row = np.array([[1.0 / len(buses) if n in buses else 0.0 for n in live]])
            a_mat = np.vstack([sub_lap, mean_row])
            rhs = np.concatenate([inj[live], [v_nom]])
            v[live] = np.linalg.lstsq(a_mat, rhs, rcond=None)[0]
        for n in range(nn):
            self.v_n[n] = float(v[n])
        for j in range(len(self.i_l)):
            o = LINE_W * j
            a, b = int(self.lines[o + 2]), int(self.lines[o + 3])
            self.i_l[j] = float((v[a] - v[b]) / max(self.lines[o], 1e-6)) if self.closed(j) else 0.0
        for j in range(ns):
            im = self.src[SRC_W * j + 4]
            self.i_s[j] = min(max(float(inj[j]), -im), im) if j in on else 0.0  # within its current limit
            u = self.v_n[j] + self.src[SRC_W * j] * self.i_s[j]
            self.u_s[j] = min(max(u, self.src[SRC_W * j + 2]), self.src[SRC_W * j + 3])

    # ------------------------------------------------------------------ topology
    def lines_at(self, node: str) -> list[int]:
        """Indices of the lines with an end at this node."""
        return [j for j, _ in self._ends[self.node_index[node]]]

    def closed(self, j: int) -> bool:
        return self.lines[LINE_W * j + 4] != 0.0

    def set_breaker(self, j: int, closed: bool) -> None:
        """Open (the current drops to zero: an ideal breaker) or close line j's breaker."""
        self.lines[LINE_W * j + 4] = 1.0 if closed else 0.0
        self._supplied = None
        if not closed:
            self.i_l[j] = 0.0

    def supplied(self) -> list[bool]:
        """Per node (sources first, then buses): whether a source reaches it through closed lines. A source's own
        terminal always counts (its converter feeds it, breaker open or not); a bus whose every path to a source is
        open is unsupplied: its voltage falls as its loads drain it, which is a blackout, not a divergence."""
        if self._supplied is None:
            seen = [k < len(self.sources) for k in range(len(self.node_index))]
            todo = list(range(len(self.sources)))
            while todo:
                k = todo.pop()
                for j, _ in self._ends[k]:
                    if self.lines[LINE_W * j + 4] == 0.0:
                        continue
                    a, b = int(self.lines[LINE_W * j + 2]), int(self.lines[LINE_W * j + 3])
                    other = b if a == k else a
                    if not seen[other]:
                        seen[other] = True
                        todo.append(other)
            self._supplied = seen
        return self._supplied

    def connected(self, source: str) -> bool:
        """Whether any of the source's lines is closed."""
        return any(self.lines[LINE_W * j + 4] != 0.0 for j, _ in self._ends[self.node_index[source]])

    # ------------------------------------------------------------------ what sensors see
    def terminal_current(self, s: int) -> float:
        """i_out of source s: the current leaving its terminal into its lines (A), each line oriented out of it."""
        out = 0.0
        for j, sign in self._ends[s]:
            out += sign * self.i_l[j]
        return out

    def line_end_power(self, j: int, node: int) -> float:
        """The power line j draws from the node at one of its ends (W): v_a i_l at a, -v_b i_l at b."""
        o = LINE_W * j
        if int(self.lines[o + 2]) == node:
            return self.v_n[node] * self.i_l[j]
        return -self.v_n[node] * self.i_l[j]

    def load_power(self, k: int, t: float) -> float:
        """The power load k draws at time t (W), at its bus's present voltage for a resistive one."""
        ld = self.load_list[k]
        v = self.v_n[self.node_index[ld.bus]]
        if ld.type == "resistive":
            return self.load_scale * v * v / ld.R_ohm if t >= ld.active_from_s else 0.0
        P = self.profiles[k].value(t)
        return P if v >= ld.v_min_V else P * v * v / (ld.v_min_V * ld.v_min_V)

    # ------------------------------------------------------------------ dynamics
    def advance(self, r, T: float, n_sub: int) -> None:
        """Integrate over T seconds with the sources' commanded rates r (V/s, one per source), n_sub RK4 steps."""
        for j, x in enumerate(r):
            self.r[j] = x
        t = self.t
        for k, prof in enumerate(self.profiles):
            if prof is not None:
                Pa = prof.value(t)
                self.loads[LOAD_W * k + 2] = Pa
                self.loads[LOAD_W * k + 3] = (prof.value(t + T) - Pa) / n_sub
            else:  # resistive: switched in at the first period that starts at or after its time
                ld = self.load_list[k]
                self.loads[LOAD_W * k + 2] = self.load_scale / ld.R_ohm if t >= ld.active_from_s else 0.0
        self._steps(T / n_sub, n_sub, self.src, self.r, self.lines, self.node_C, self.loads, self.i_s, self.u_s,
                    self.i_l, self.v_n)
        self.t = t + T

    def stored_energy(self) -> float:
        """The energy in every inductor and capacitor (J): a check of the integration's bookkeeping."""
        e = 0.0
        for j in range(len(self.i_s)):
            e += 0.5 * self.src[SRC_W * j + 1] * self.i_s[j] ** 2
        for j in range(len(self.i_l)):
            e += 0.5 * self.lines[LINE_W * j + 1] * self.i_l[j] ** 2
        for n in range(len(self.v_n)):
            e += 0.5 * self.node_C[n] * self.v_n[n] ** 2
        return e

    def finite(self) -> bool:
        return all(math.isfinite(x) for arr in (self.i_s, self.u_s, self.i_l, self.v_n) for x in arr)
