"""Offline closed loop of a DC network: the network plant, one controller per source, the interconnection layer.

Each control period, for every source s: its sensor samples (i_s, v_s, u_s, i_out) with i_out the current
leaving its terminal into its lines; its controller (``service.core.source.SourceController`` around the same
core every driver uses) answers with du/dt; the command goes through the loop delay to the plant. What each
source follows, P^{r,in}_s (W, negative when it delivers), is made by the interconnection layer from the power
each source's lines draw at its terminal, P_s = v_s i_out_s (the line-end power oriented out of the source):

* ``layer.mode = "none"``: P^{r,in}_s = -P_s, the source's own lines (each regulates its own terminal);
* ``layer.mode = "live-sum"``: P^{r,in}_s = -alpha_s sum_k P_k, alpha_s = share_s / (sum of the shares of the
  connected sources that carry more than ``idle_power_W``): the load shared in the configured proportions,
  rescaled at once when a source trips; once per window every source's v_ref moves by ``v_ref_gain`` x
  (nominal - the buses' mean voltage over the window), which restores the bus voltage.

P^{r,in}_s reaches source s through its link (``links``): delayed by whole samples, lost with a seeded
probability (the source keeps the last value it got), or silent. Each message carries the value and its filtered
rate, and the source carries a late one forward by its age (at most ``layer.extrapolate_s``); one older than
STALE_S makes the source fall back to its own terminal (``fallback_s`` and ``first_fallback_t_s`` say when).
Events trip or close breakers; a ``connect`` event asks the layer, which checks
the source's forecast Z^{r,out} against Z^{r,in} of the current window (``service.forecast``) and closes its
breakers only if feasible. Pure: no clocks, no I/O; the same scenario and seed give the same bits.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from schemas.network import NetworkScenario
from service.core import core_metadata, make_core
from service.core.feasibility import FeasibilityMonitor
from service.core.interaction import outgoing_power_at
from service.core.source import ACTIVE, IDLE, SourceController
from service.metrics import network_metrics
from service.network.layer import InterconnectionLayer, Sharing, link_of
from service.network.netrig import NetworkRigModel
from service.plant.network import LoadForecast
from service.sim import check_trace_size

STALE_S = 0.01  # a P^{r,in} older than this (s) is stale: the source falls back to its own terminal
# per source and tick: the true state (i, v, u, i_out), the power its lines draw as measured (P), the P^{r,in} it
# followed, the rate its plant applied (du_dt), its mode and v_ref; and what its controller saw and answered (the
# sample meas_*, whether the core stepped, the answer cmd_du / cmd_du_next before the loop delay), which a log
# needs for replay
SOURCE_SIGNALS = ("i", "v", "u", "i_out", "P", "P_in", "du_dt", "mode", "v_ref",
                  "meas_i", "meas_v", "meas_u", "meas_i_load", "stepped", "cmd_du", "cmd_du_next")


@dataclass
class Event:
    """What happened at an event: its time, kind and target, and the layer's answer to a connect request."""

    t: float
    kind: str
    target: str
    accepted: bool = True
    reason: str = ""


@dataclass
class NetworkResult:
    net: NetworkScenario
    t: np.ndarray
    sources: dict[str, dict[str, np.ndarray]]  # per source: SOURCE_SIGNALS over time
    buses: dict[str, np.ndarray]  # bus voltages over time (V)
    lines: dict[str, np.ndarray]  # line currents over time (A, from a to b)
    events: list[Event]
    metrics: dict
    violations: dict[str, int] = field(default_factory=dict)  # feasibility excursions per source
    config_events: dict[str, list] = field(default_factory=dict)  # per source: (t, seq applied before, v_ref V)
    ranges: dict[str, list] = field(default_factory=dict)  # per source: (window, Z^{r,in} P lo/hi W, Qdot lo/hi W/s)
    cores: dict[str, str] = field(default_factory=dict)  # per source: its core's metadata JSON (core_metadata)


def run_network(net: NetworkScenario, impl: str = "auto", stop_on_divergence: bool = True) -> NetworkResult:
    """The network's closed loop offline (see the module docstring). impl: the cores' and the plant's
    implementation (service.core.make_core)."""
    tm, lay = net.timing, net.layer
    check_trace_size(int(round(tm.duration_s / (1.0 / tm.control_rate_hz))),  # before anything is allocated
                     1 + len(net.sources) * len(SOURCE_SIGNALS) + len(net.buses) + len(net.lines), net.name)
    rig = NetworkRigModel(net, impl)  # the plant side, as the network rig runs it
    plant, T, N, d = rig.plant, rig.T, rig.N, rig.d
    layer = InterconnectionLayer(net, LoadForecast(net))  # the layer, as the coordinator runs it
    names = list(net.sources)
    ns = len(names)
    cfgs = list(net.sources.values())
    ctls, feas = [], []
    for name, src in zip(names, cfgs, strict=True):
        core = make_core(src.controller, src.model_params(), T, d, impl)
        ctls.append(SourceController(core, T, idle_power_W=lay.idle_power_W, idle_tau_s=lay.idle_tau_s,
                                     hold_when_open=lay.open_idle == "hold", resume_ramp_s=lay.resume_ramp_s,
                                     fallback_idle_power_W=lay.fallback_idle_power_W,
                                     fallback=net.fallback_of(name)))
        feas.append(FeasibilityMonitor(lay.window_s))
    config_events: dict[str, list] = {name: [] for name in names}  # the layer's v_ref moves: (t, seq, v_ref V)
    ranges: dict[str, list] = {name: [] for name in names}  # per source: (window, Z^{r,in}) as set
    # links: per receiving source, (delay in samples, loss, silent from, silent until)
    links = []
    for name in names:
        ln = link_of(net, name)
        links.append((int(round(ln.delay_s / T)), ln.loss, ln.silent_from_s,
                      math.inf if ln.silent_until_s is None else ln.silent_until_s))
    link_rng = np.random.default_rng([net.seed, 0x11CC])
    # each source forms its P^{r,in} from the grid samples its link delivers (layer.Sharing, as its daemon does live).
    # A link that delivers every sample (delayed or not) gives the sharing the layer's own instance forms, stepped on
    # the same samples: that one's answer travels; a lossy or silenced link's source steps its own on what arrives
    own_sharing = [Sharing.of(net) if loss or silent is not None else None for _, loss, silent, _ in links]
    inbox: list[deque] = [deque() for _ in range(ns)]  # (arrival sample, t sent, P_in, its rate) or the grid sample
    got = [(-math.inf, 0.0, 0.0)] * ns  # (t sent, P_in W, its rate W/s) of the newest P^{r,in} each source received
    events: list[Event] = []
    per_window = layer.per_window

    def set_ranges(window: int) -> None:
        for j, z in enumerate(layer.ranges(window, rig.connected())):
            if z is not None:
                feas[j].set_range(window, z)
                ranges[names[j]].append((window, z))

    if layer.active:
        set_ranges(0)
    t_arr = np.zeros(N)
    sig = {name: {k: np.zeros(N) for k in SOURCE_SIGNALS} for name in names}
    bus_v = {b: np.zeros(N) for b in net.buses}
    line_i = {ln: np.zeros(N) for ln in net.lines}
    diverged_at = None
    P = [0.0] * ns
    n = 0
    for k in range(N):
        due = rig.begin(k)
        t = plant.t
        for ev in due:
            if ev.kind == "connect":  # the layer checks the source's forecast against its share of the window
                s = names.index(ev.target)
                f = layer.connect_check(s, ctls[s].core.cfg, k // per_window, rig.connected(), d, impl)
                if f.feasible:
                    rig.breaker(ev.target, True)
                events.append(Event(t, "connect", ev.target, f.feasible, "" if f.feasible else f.reason))
            else:
                events.append(Event(t, ev.kind, ev.target))
        if due and layer.active:  # the current window's ranges, for the sources connected now
            set_ranges(k // per_window)
        connected = rig.connected()
        samples = rig.sample(k)
        for j in range(ns):
            s = samples[j]
            P[j] = s.v * s.i_load if connected[j] else 0.0  # the power its lines draw, as measured
        want, want_rate = layer.allocate(k, P, connected)
        if k == 0 and net.start == "steady":  # a network already running: its messages from before t = 0 arrived
            got = [(t, want[j], 0.0) for j in range(ns)]
        grid = None
        # the links, then each controller
        for j in range(ns):
            delay_k, loss, silent, back = links[j]
            own = own_sharing[j]
            if not (silent is not None and silent <= t < back) and not (loss and link_rng.random() < loss):
                if own is None:
                    inbox[j].append((k + delay_k, t, want[j], want_rate[j]))
                else:  # the grid sample itself (its P and breakers), shared by the links it goes on
                    grid = grid or (k, list(P), list(connected))
                    inbox[j].append((k + delay_k, t, grid, None))
            q = inbox[j]
            while q and q[0][0] <= k:
                _, t_sent, value, rate = q.popleft()
                if own is not None:
                    w, r = own.step(*value)
                    value, rate = w[j], r[j]
                got[j] = (t_sent, value, rate)
            t_sent, value, rate = got[j]
            fresh = t - t_sent <= STALE_S
            P_in = outgoing_power_at(t, t_sent, value, rate, STALE_S, lay.extrapolate_s) if fresh else value
            du, du_next = ctls[j].step(samples[j], P_in, 0.0, connected[j], fresh)
            row = sig[names[j]]
            s = samples[j]
            row["meas_i"][k], row["meas_v"][k], row["meas_u"][k], row["meas_i_load"][k] = s.i, s.v, s.u, s.i_load
            row["stepped"][k], row["cmd_du"][k], row["cmd_du_next"][k] = ctls[j].mode != IDLE, du, du_next
            row["P_in"][k] = ctls[j].P_in_used
            r = rig.command(j, k, du, du_next)
            est = ctls[j].core.out.est
            if ctls[j].mode == ACTIVE and est is not None and t >= 5.0 * cfgs[j].controller.deriv_tau_s:
                feas[j].update(t, est.P_r_out_port, est.Qdot_r_out_port)
            row["i"][k], row["v"][k], row["u"][k] = plant.i_s[j], plant.v_n[j], plant.u_s[j]
            row["i_out"][k], row["P"][k] = plant.terminal_current(j), P[j]
            row["du_dt"][k], row["mode"][k], row["v_ref"][k] = r, ctls[j].mode, ctls[j].v_ref_V
        t_arr[k] = t
        for b, bi in zip(net.buses, rig.bus_idx, strict=True):
            bus_v[b][k] = plant.v_n[bi]
        for j, ln in enumerate(net.lines):
            line_i[ln][k] = plant.i_l[j]
        n = k + 1
        # the layer's window: move v_ref to restore the buses, set the next window's feasibility ranges
        fresh_now = [t - got[j][0] <= STALE_S for j in range(ns)]  # the layer's messages reach it: v_ref moves
        win_k, moves = layer.step(k, ([s.v for s in samples], None, connected, rig.bus_measurements(),
                                      rig.load_powers()), fresh_now, [c.mode == ACTIVE for c in ctls], P)
        for j, v_ref in moves:
            new = ctls[j].set_v_ref(v_ref)
            if new is not None:  # applied before the next tick: a log's v_ref event
                config_events[names[j]].append((t, k + 1, new.v_ref_V))
        if win_k is not None and layer.active:
            set_ranges(win_k)
        rig.advance()
        if diverged_at is None and rig.diverged():
            diverged_at = plant.t
            if stop_on_divergence:
                break
    sig = {name: {k: a[:n] for k, a in row.items()} for name, row in sig.items()}
    res = NetworkResult(net, t_arr[:n], sig, {b: a[:n] for b, a in bus_v.items()},
                        {ln: a[:n] for ln, a in line_i.items()}, events, {},
                        {name: f.count for name, f in zip(names, feas, strict=True)}, config_events, ranges,
                        {name: core_metadata(cfgs[j].controller, cfgs[j].model_params(), T, ctls[j].core.d)
                         for j, name in enumerate(names)})
    for j, prof in enumerate(plant.profiles):  # load steps are events of the metrics too
        if prof is not None:
            res.events += [Event(ts, "load", plant.load_names[j]) for ts in prof.step_times() if ts < tm.duration_s]
    res.events.sort(key=lambda e: e.t)
    res.metrics = network_metrics(res, diverged_at, ctls, rig.unsupplied, rig.why if diverged_at is not None else None)
    return res
