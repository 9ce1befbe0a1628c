"""The plant side of a network's closed loop: the network plant, each source's sensor, loop delay and command
schedule, the scenario's breaker events and the layer's bus measurements. Pure: no clocks, no I/O.

The offline network (``service.network.netsim``) and the hardware-in-the-loop network rig (``energyctl plant --config
NETWORK``) drive this one class, so that both sample, delay and apply commands the same way to the bit. Per tick k:
``begin(k)`` applies the breaker events due (``trip``/``close``; a ``connect`` event is the layer's to answer and is
handed back), ``sample(k)`` measures every source, ``bus_measurements()`` and ``load_powers()`` give what the layer
sees, ``command(j, k, ...)`` takes source j's answer through its loop delay and returns the rate its converter
applies, and ``advance(r)`` integrates one period.
"""

from __future__ import annotations

import numpy as np

from schemas.network import EventConfig, NetworkScenario
from service.core.types import Sample
from service.plant.network import NetworkPlant
from service.plant.rig import CommandPath, substeps
from service.plant.rlc import CommandChannel, Sensor
from service.sim import divergence_why


class NetworkRigModel:
    """See the module docstring. ``plant`` is the NetworkPlant; ``names`` the sources in scenario order."""

    def __init__(self, net: NetworkScenario, impl: str = "auto", realtime: bool = False):
        """realtime: commands come when they come (``arrive``), and the one answering sample k acts over period
        k + d (the loop delay is the time the answer had); otherwise ``command`` puts each through a d-sample delay
        line (lockstep and offline)."""
        self.net = net
        tm = net.timing
        self.T = 1.0 / tm.control_rate_hz
        self.n_sub = substeps(self.T, tm.plant_step_s)
        self.N = int(round(tm.duration_s / self.T))
        self.d = tm.delay_samples
        self.plant = plant = NetworkPlant(net, impl)
        self.names = list(net.sources)
        ns = len(self.names)
        self.sensors = [Sensor(net.sensor, net.seed * 1000 + j) for j in range(ns)]
        # each source's commands: lockstep and offline through its d-sample delay line, timing's command disturbances
        # (per source its own draws) and its schedule; realtime the schedule alone, d samples behind (a realtime
        # stack has its own disturbances)
        self.paths = [CommandPath(0, None, True, self.d) if realtime else
                      CommandPath(self.d, CommandChannel(tm, [net.seed, j])) for j in range(ns)]
        self.scheds = [p.sched for p in self.paths]
        self.r = [0.0] * ns  # the rate each source's converter applies over the current period (V/s)
        if net.start == "steady":
            plant.start_steady([s.share for s in net.sources.values()], net.nominal_v_V)
        self.pending: list[EventConfig] = sorted(net.events, key=lambda e: e.t_s)
        self.bus_idx = [plant.node_index[b] for b in net.buses]
        self.unsupplied: dict[str, float] = {}  # bus -> first plant time no source reached it (diverged)
        self.nodes = net.nodes()
        self.why = ""  # why diverged() said so
        self.bus_rng = np.random.default_rng([net.seed, 0xB05])  # the layer's bus measurements: their own noise
        # both ends of every line: (line, node, line index, node index), found once (line_ends runs per sample)
        self._ends = [(name, node, j, plant.node_index[node]) for j, (name, ln) in enumerate(net.lines.items())
                      for node in (ln.a, ln.b)]

    def begin(self, k: int, kinds=("trip", "close", "connect")) -> list[EventConfig]:
        """Start tick k (t = k T, by index: an event at k T stays on tick k in a long run): the scenario's events due
        by k, of the given kinds (others are dropped), in time order; trips and closes are applied here, the rest
        handed back."""
        self.plant.t = k * self.T
        due = []
        while self.pending and int(round(self.pending[0].t_s / self.T)) <= k:
            ev = self.pending.pop(0)
            if ev.kind not in kinds:
                continue
            if ev.kind in ("trip", "close"):
                self.breaker(ev.target, ev.kind == "close")
            due.append(ev)
        return due

    def lines_of(self, target: str) -> list[int]:
        """The lines a breaker event names: a line, or every line at a source."""
        plant = self.plant
        return [plant.line_names.index(target)] if target in self.net.lines else plant.lines_at(target)

    def breaker(self, target: str, closed: bool) -> None:
        for j in self.lines_of(target):
            self.plant.set_breaker(j, closed)

    def connected(self) -> list[bool]:
        return [self.plant.connected(name) for name in self.names]

    def sample(self, k: int) -> list[Sample]:
        """Every source's measurement (i, v, u and i_out, the current leaving its terminal into its lines)."""
        p, t = self.plant, self.plant.t
        return [self.sensors[j].measure(k, t, p.i_s[j], p.v_n[j], p.u_s[j], p.terminal_current(j))
                for j in range(len(self.names))]

    def bus_measurements(self) -> list[float]:
        """The buses' voltages as the layer measures them (V; the sensors' voltage noise, its own stream)."""
        noise, v_n, rng = self.net.sensor.noise_v_V, self.plant.v_n, self.bus_rng
        return [v_n[bi] + (noise * rng.standard_normal() if noise else 0.0) for bi in self.bus_idx]

    def load_powers(self) -> list[float]:
        """Each load's true power now (W)."""
        p = self.plant
        return [p.load_power(q, p.t) for q in range(len(p.load_list))]

    def command(self, j: int, k: int, du: float | None, du_next: float = 0.0) -> float:
        """Source j's answer to sample k (du/dt, planned du/dt V/s; None: none came) through its loop delay and
        timing's command disturbances: the rate its converter applies over period k (V/s)."""
        self.r[j] = r = self.paths[j].command(k, self.plant.t, du, du_next)
        return r

    def arrive(self, j: int, seq: int, du: float, du_next: float) -> None:
        """Realtime: source j's answer to sample seq came."""
        self.paths[j].arrive(seq, du, du_next)

    def take(self, j: int, k: int) -> float:
        """Realtime: the rate source j's converter applies over period k (V/s): the answer to sample k - d, else
        its predecessor's plan, else a hold."""
        self.r[j] = r = self.paths[j].take(k)[0]
        return r

    def line_ends(self) -> list[tuple[str, str, float]]:
        """(line, node, the power the line draws there W) for both ends of every line."""
        p = self.plant
        return [(line, node, p.line_end_power(j, n)) for line, node, j, n in self._ends]

    def advance(self) -> None:
        self.plant.advance(self.r, self.T, self.n_sub)

    def diverged(self) -> bool:
        """A state not finite, or a node that a source supplies (NetworkPlant.supplied) further than the scenario's
        acceptance.diverge_dev_pct from nominal; ``why`` then says which, in words. Each bus no source reaches is
        noted in ``unsupplied`` (bus -> the first plant time, s) instead: a blackout, which the buses' band checks
        report, not a controller's divergence."""
        v_nom = self.net.nominal_v_V
        dev_max = self.net.acceptance.diverge_dev_pct / 100 * v_nom
        p = self.plant
        sup = p.supplied()
        if not all(sup):
            for name, k in zip(self.net.buses, self.bus_idx, strict=True):
                if not sup[k] and name not in self.unsupplied:
                    self.unsupplied[name] = p.t
        if not p.finite():
            self.why = "the state is not finite"
            return True
        for k, v in enumerate(p.v_n):
            if sup[k] and not abs(v - v_nom) <= dev_max:
                self.why = divergence_why(v, 0.0, v_nom, self.net.acceptance, f"node {self.nodes[k]}")
                return True
        return False
