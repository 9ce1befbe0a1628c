"""The interconnection layer of a DC network: what each source is to deliver, its per-window v_ref correction, its
feasibility range, and the plug-in check. Pure: no clocks, no I/O.

It has two parts. The per-sample part, ``Sharing``, each source forms itself from the grid sample (the measured
power each source's lines draw, P_s = v_s i_out_s, W, and which sources are connected): P^{r,in}_s (W, negative when
the source delivers) and its filtered rate. Live, a source's daemon steps it on the rig's grid sample
(PREFIX/RIG/grid); offline (``service.network.netsim``) on what its link delivers; the same samples give the same
bits, so a lockstep run over Zenoh reproduces the offline run to the bit:

* ``layer.mode = "none"``: P^{r,in}_s = -P_s, the source's own lines (each regulates its own terminal);
* ``layer.mode = "live-sum"``: P^{r,in}_s = -alpha_s sum_k P_k, alpha_s = share_s / (sum of the shares of the
  connected sources that carry more than ``idle_power_W``): the load shared in the configured proportions,
  rescaled at once when a source trips.

The per-window part, ``InterconnectionLayer`` (``step(k, grid)`` after each sample), the coordinator runs and
sends once per window (schemas.messages.LayerWindow) as the offline network does:
Once per window (``window_s``, a whole number of periods) every source's v_ref moves by ``v_ref_gain`` x (nominal -
the buses' mean measured voltage over the window), within ``v_ref_max_offset_V`` of its configured value; this
restores the bus voltage while the terminals move to share the load; a disconnected source's v_ref goes to the
buses' mean instead (``open_v_ref = "bus"``: it waits at the voltage it will close onto). A source that connects
takes its share over ``plug_in_ramp_s``. Z^{r,in}[k] of each connected source is its share of the loads' box over
window k (``window_box``), through the paper's incoming range.
"""

from __future__ import annotations

from schemas.network import LinkConfig, NetworkScenario
from schemas.scenario import ControllerConfig
from service.core import effective_gain
from service.core.feasibility import incoming_range, load_box, tau_prime
from service.forecast import OutgoingForecast, forecast_outgoing, verdict
from service.plant.network import LoadForecast

RATE_TAU_S = 1e-3  # the filter on P^{r,in}'s rate, which a late message is carried forward with (s)
FORECAST_MARGIN = 0.05  # the layer's load box is widened by this fraction for the feasibility checks


class Sharing:
    """The layer's per-sample part, which each source forms itself from the grid sample (live: its daemon, from
    PREFIX/RIG/grid; offline: service.network.netsim, from what its link delivers): P^{r,in}_s and its filtered rate.

    * ``mode = "none"``: P^{r,in}_s = -P_s, the source's own lines;
    * ``mode = "live-sum"``: P^{r,in}_s = -alpha_s sum_k P_k over the connected sources carrying at least
      ``carry_power_W`` (|P_k|), alpha_s = share_s / (their shares' sum); a source that connected at sample k_c takes
      share_s min(1, (k - k_c) / plug_in_ramp ticks).

    Its rate dP^{r,in}/dt is filtered (RATE_TAU_S) over the samples since the previous step (none at the first): a
    late message is carried forward along it. Pure; the same grid samples in the same order give the same bits,
    whoever steps it, so a source that gets every sample forms what the layer's own instance forms."""

    def __init__(self, shares: list[float], T: float, mode: str, carry_power_W: float, plug_in_ramp_s: float,
                 connected: list[bool]):
        ns = self.ns = len(shares)
        self.shares, self.T, self.mode, self.carry_power_W = list(shares), T, mode, carry_power_W
        self.want_prev, self.want_rate = [0.0] * ns, [0.0] * ns
        self.k_prev: int | None = None  # the sample of the previous step
        self.ramp_ticks = int(round(plug_in_ramp_s / T))
        self.was_connected = list(connected)
        self.connected_at = [-1] * ns  # the sample each source last connected at (-1: connected from the start)
        self.rate_alpha = T / (T + RATE_TAU_S)
        self._want, self._shares_now = [0.0] * ns, [0.0] * ns  # step's results and ramped shares, reused

    @classmethod
    def of(cls, net: NetworkScenario) -> Sharing:
        """The sharing of a network scenario (its sources' shares, its layer's mode, idle power and plug-in ramp)."""
        return cls([s.share for s in net.sources.values()], 1.0 / net.timing.control_rate_hz, net.layer.mode,
                   net.layer.idle_power_W, net.layer.plug_in_ramp_s, [s.connected for s in net.sources.values()])

    @classmethod
    def of_role(cls, role, T: float) -> Sharing:
        """A network source daemon's (schemas.component.NetworkRole) at its sample period T (s)."""
        return cls(role.shares, T, role.sharing, role.carry_power_W, role.plug_in_ramp_s, role.sources_connected)

    def seed(self, connected: list[bool]) -> None:
        """Take the breakers as they are (connected: which sources are) as the ones it started with: no ramp for a
        source already connected. For a daemon started or restarted mid-run, at its first grid sample (a source that
        connected before then is not one that just connected)."""
        self.was_connected[:] = connected
        self.connected_at[:] = [-1] * self.ns

    def step(self, k: int, P: list[float], connected: list[bool]) -> tuple[list[float], list[float]]:
        """(P^{r,in} per source W, its filtered rate W/s) for sample k, from the power each source's lines draw (P,
        W; 0 for a disconnected source) and which are connected. Both lists are this instance's, updated in place
        at the next step: read them before it (copy to keep). A first step at k > 0 (a daemon, coordinator or
        replay started mid-run) takes the breakers as they are (seed): no plug-in ramp for sources already on."""
        ns = self.ns
        if k > 0 and self.k_prev is None:
            self.seed(connected)
        want = self._want  # updated in place: no list per sample on a daemon's loop thread
        if self.mode == "live-sum":
            shares = self.shares
            if self.ramp_ticks:  # a source that just connected takes its share over plug_in_ramp_s
                was, at, now, ramp = self.was_connected, self.connected_at, self._shares_now, self.ramp_ticks
                for j in range(ns):
                    if connected[j] and not was[j]:
                        at[j] = k
                    was[j] = connected[j]
                    now[j] = shares[j] * min(1.0, (k - at[j]) / ramp) if at[j] >= 0 else shares[j]
                shares = now
            # (summed in order from 0, as sum() over the carrying ones: the same bits)
            total = weight = 0.0
            carry = self.carry_power_W
            for j in range(ns):
                if connected[j] and abs(P[j]) >= carry:
                    total += P[j]
                    weight += shares[j]
            weight = weight or 1.0
            for j in range(ns):
                want[j] = -(shares[j] / weight) * total if connected[j] else 0.0
        else:
            for j in range(ns):
                want[j] = -P[j]
        # its rate, filtered: a message carries both, and a late one is carried forward by its age; over the samples
        # since the previous step (a source that misses grid samples skips some), none at the first
        k_prev = self.k_prev
        dt = (k - k_prev) * self.T if k_prev is not None and k > k_prev else 0.0
        for j in range(ns):
            raw = (want[j] - self.want_prev[j]) / dt if dt else 0.0
            self.want_rate[j] += self.rate_alpha * (raw - self.want_rate[j])
            self.want_prev[j] = want[j]
        self.k_prev = k
        return want, self.want_rate

    def alpha(self, connected: list[bool]) -> list[float]:
        """alpha_s over the connected sources (no ramp, no carrying threshold): what the window message states."""
        weight = sum(sh for sh, c in zip(self.shares, connected, strict=True) if c) or 1.0
        return [sh / weight if c else 0.0 for sh, c in zip(self.shares, connected, strict=True)]


class InterconnectionLayer:
    """The layer's state over a run (see the module docstring). ``loads``: the loads' forecast
    (service.plant.network.LoadForecast: their configs and profiles, for ``window_box``), not the plant."""

    def __init__(self, net: NetworkScenario, loads: LoadForecast):
        self.net, self.cfg, self.loads = net, net.layer, loads
        self.names = list(net.sources)
        ns = self.ns = len(self.names)
        self.shares = [s.share for s in net.sources.values()]
        self.T = 1.0 / net.timing.control_rate_hz
        self.per_window = max(1, int(round(self.cfg.window_s / self.T)))  # ticks per window: integer arithmetic
        self.v_ref0 = [s.controller.v_ref_V for s in net.sources.values()]
        self.v_ref = list(self.v_ref0)  # what each source's v_ref was last moved to (V)
        self.taus = source_taus(net)
        self.sharing = Sharing.of(net)
        self.win_sum, self.win_n = 0.0, 0  # the buses' mean measured voltage, summed over the window
        self.win_term = [0.0] * ns  # each source's measured terminal voltage, summed over the window
        self.win_delivered = self.win_load = 0.0
        self.loss_frac = 0.0  # line losses as a fraction of the load over the last window (Z^{r,in}'s allowance)
        self.next_window: int | None = None  # the window whose start closes the current one (None: no sample yet)

    @property
    def active(self) -> bool:
        return self.cfg.mode != "none"

    def allocate(self, k: int, P: list[float], connected: list[bool]) -> tuple[list[float], list[float]]:
        """(P^{r,in} per source W, its filtered rate W/s) for tick k: the layer's own Sharing (what every source that
        gets every grid sample forms itself)."""
        return self.sharing.step(k, P, connected)

    @property
    def want_rate(self) -> list[float]:
        return self.sharing.want_rate

    @property
    def want_prev(self) -> list[float]:
        return self.sharing.want_prev

    def step(self, k: int, grid: tuple, fresh: list[bool], active: list[bool], P: list[float] | None = None
             ) -> tuple[int | None, list]:
        """The layer after sample k: grid = (v, i_out, connected, bus_v, load_P) as the rig measured them (the grid
        sample); the window sums, and at a window's end the v_ref moves (source index, V; for the sources whose
        messages reach them: fresh) and the next window (window_end). The per-sample sharing is not here: each
        source forms it itself (Sharing), and the layer's own (allocate) is for its record. P: the lines' powers
        v i_out (0 when disconnected) if the caller has them already."""
        v, i_out, connected, bus_v, load_P = grid
        if P is None:
            P = [v[j] * i_out[j] if connected[j] else 0.0 for j in range(self.ns)]
        self.accumulate(bus_v, v, P, load_P)
        return self.window_end(k, connected, fresh, active)

    def accumulate(self, bus_meas: list[float], term_v: list[float], P: list[float], load_W: list[float]) -> None:
        """One tick's window sums: the buses as measured (V), each terminal as measured (V), the powers the sources'
        lines draw (W) and the loads' true powers (W; the line losses are measured against them)."""
        if bus_meas:
            self.win_sum += sum(bus_meas) / len(bus_meas)
            self.win_n += 1
            for j in range(self.ns):
                self.win_term[j] += term_v[j]
        self.win_delivered += sum(P)
        self.win_load += sum(load_W)

    def window_end(self, k: int, connected: list[bool], fresh: list[bool], active: list[bool]
                   ) -> tuple[int | None, list[tuple[int, float]]]:
        """After tick k: (the window that starts next, or None if k does not end one; the v_ref moves (source
        index, new v_ref V) to apply before tick k + 1). fresh: the source gets the layer's messages (a source that
        does not keeps its v_ref); active: it is regulating (per-source mode moves only those to their terminal)."""
        # the window closes when the window of k + 1 is past the one it is in (offline, which sees every sample: at
        # (k + 1) % per_window == 0; a realtime coordinator that skipped that sample closes it at the next it takes)
        nxt = (k + 1) // self.per_window
        if self.next_window is None:  # its first sample (a coordinator started mid-run: in the window of k)
            self.next_window = k // self.per_window + 1
        if nxt < self.next_window:
            return None, []
        self.next_window = nxt + 1
        lay = self.cfg
        if self.win_load > 0.0:
            self.loss_frac = max(0.0, self.win_delivered / self.win_load - 1.0)
        self.win_delivered = self.win_load = 0.0
        moves = []
        if lay.mode == "live-sum" and lay.v_ref_gain > 0 and self.win_n:
            correction = lay.v_ref_gain * (self.net.nominal_v_V - self.win_sum / self.win_n)
            for j in range(self.ns):
                if not fresh[j]:
                    continue
                if not connected[j] and lay.open_v_ref == "bus":
                    # waiting to connect: at the buses' voltage, so that closing its breaker moves little (a
                    # synchronising close); the common v_ref comes with its first window connected
                    target = self.win_sum / self.win_n
                elif lay.v_ref_mode == "per-source" and connected[j] and active[j]:
                    # where it sits (sharing exactly needs v_ref = v at its terminal), moved with the buses
                    target = self.win_term[j] / self.win_n + correction
                else:
                    target = self.v_ref[j] + correction
                lo, hi = self.v_ref0[j] - lay.v_ref_max_offset_V, self.v_ref0[j] + lay.v_ref_max_offset_V
                new = min(max(target, lo), hi)
                if new != self.v_ref[j]:
                    self.v_ref[j] = new
                    moves.append((j, new))
        self.win_sum, self.win_n = 0.0, 0
        self.win_term = [0.0] * self.ns
        return (k + 1) // self.per_window, moves

    def ranges(self, window: int, connected: list[bool]) -> list[tuple | None]:
        """Z^{r,in}[window] per source (P lo, P hi W, Qdot lo, Qdot hi W/s) from the shares of the sources connected
        now (a disconnected one gets None, and the others' shares grow)."""
        live = [sh if c else 0.0 for sh, c in zip(self.shares, connected, strict=True)]
        z = incoming_ranges(self.loads, self.net, self.taus, window, live, self.loss_frac)
        return [zj if sh > 0.0 else None for zj, sh in zip(z, live, strict=True)]

    def connect_offer(self, s: int, window: int, connected: list[bool]) -> tuple[tuple[float, ...], float]:
        """What source s would be asked to deliver over window if it connected now: its share (with the sources
        connected now and s) of the window's load box (P lo, P hi W, Pdot lo, Pdot hi W/s), and its tau' (s)."""
        weight = sum(self.shares[j] for j in range(self.ns) if connected[j] or j == s)
        box = window_box(self.loads, self.net, window, self.loss_frac)
        a = self.shares[s] / weight
        return tuple(a * x for x in box), self.taus[s]

    def connect_check(self, s: int, controller: ControllerConfig, window: int, connected: list[bool],
                      delay_samples: int, impl: str = "auto") -> OutgoingForecast:
        """The plug-in check of source s: its forecast Z^{r,out} (service.forecast) for its offer (connect_offer)
        against its Z^{r,in}. A live source forecasts the same itself and announces it (judge_announced)."""
        box, tau_p = self.connect_offer(s, window, connected)
        src = self.net.sources[self.names[s]]
        return forecast_outgoing(controller, src.model_params(), self.T, delay_samples, box, tau_p,
                                 max_ramp_s=self.cfg.window_s, impl=impl)


# an offer is good for an announcement this many windows on (realtime: the source's forecast takes 30-350 ms on a
# busy machine, 0.9 s once under the realtime processes; the window's line-loss estimate moves meanwhile, but its
# load box must not have moved far)
MAX_OFFER_AGE_WINDOWS = 10


STALE_OFFER = "no current offer"  # how a refusal for a stale offer begins (the source asks again)


def offer_staleness(offer: tuple[int, tuple] | None, window: int, connected) -> str:
    """The coordinator's refusal of an announcement arriving in window with the breakers connected whose offer (the
    window it was made for, the breakers then) no longer serves: f"{STALE_OFFER} (why): ask again"; "" if it
    does. Its replay recomputes the same."""
    if offer is None:
        why = "no offer"
    elif tuple(offer[1]) != tuple(connected):
        why = "the breakers changed"
    elif window - offer[0] > MAX_OFFER_AGE_WINDOWS:
        why = f"its offer is {window - offer[0]} windows old"
    else:
        return ""
    return f"{STALE_OFFER} ({why}): ask again"


def judge_announced(box: tuple, tau_p: float, P_out: tuple[float, float], Qdot_out: tuple[float, float],
                    saturation: str = "") -> tuple[str, tuple]:
    """The plug-in check of an announced Z^{r,out} (P_out W, Qdot_out W/s, and the saturation its forecast met)
    against the Z^{r,in} of the offer it was forecast for (box W and W/s, tau_p s; InterconnectionLayer.
    connect_offer): (reason, "" if feasible; Z^{r,in})."""
    z_in = incoming_range(*box, tau_p)
    return verdict(z_in, P_out, Qdot_out, saturation), z_in


def link_of(net: NetworkScenario, source: str) -> LinkConfig:
    """The link to a source: the '*' entry, with what the source's own entry sets on top of it."""
    base = net.links.get("*") or LinkConfig()
    own = net.links.get(source)
    return base if own is None else base.model_copy(update={k: getattr(own, k) for k in own.model_fields_set})


def window_box(loads: LoadForecast, net: NetworkScenario, k: int,
               loss_frac: float = 0.0) -> tuple[float, float, float, float]:
    """What the sources deliver over window k (W, W/s): the loads' box, resistive loads at nominal from their
    switching-in time, times 1 + loss_frac (the lines' losses as the layer last measured them), widened by
    FORECAST_MARGIN. loads: the loads' forecast (their configs and profiles)."""
    w = net.layer.window_s
    t0, t1 = k * w, min((k + 1) * w, net.timing.duration_s)
    lo = hi = dlo = dhi = 0.0
    for j, ld in enumerate(loads.load_list):
        if ld.type == "resistive":
            p = net.load_scale * net.nominal_v_V ** 2 / ld.R_ohm
            on_lo = 0.0 if ld.active_from_s > t0 else p  # switched in during the window: either
            on_hi = p if ld.active_from_s < t1 else 0.0
            lo, hi = lo + on_lo, hi + on_hi
        else:
            a, b, c, e = loads.profiles[j].range_over(t0, max(t1, t0 + 1e-9))
            lo, hi, dlo, dhi = lo + a, hi + b, dlo + c, dhi + e
    g = 1.0 + loss_frac
    return load_box(g * lo, g * hi, g * dlo, g * dhi, FORECAST_MARGIN)


def incoming_ranges(loads: LoadForecast, net: NetworkScenario, taus: list[float], k: int, shares: list[float],
                    loss_frac: float = 0.0) -> list[tuple[float, float, float, float]]:
    """Z^{r,in}[k] of every source (P lo, P hi W, Qdot lo, Qdot hi W/s): its share of what the sources deliver over
    window k (window_box), through the paper's incoming range with its tau' (taus)."""
    box = window_box(loads, net, k, loss_frac)
    total = sum(shares) or 1.0
    return [incoming_range(*(shares[j] / total * x for x in box), taus[j]) for j in range(len(shares))]


def source_taus(net: NetworkScenario) -> list[float]:
    """tau' of each source's controller on its own model (s): what its feasibility range is built with."""
    out = []
    for s in net.sources.values():
        model = s.model_params()
        out.append(tau_prime(model.L_H, model.R_ohm, effective_gain(s.controller, model)))
    return out
