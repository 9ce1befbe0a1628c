"""A source on a live network: today's daemon, forming its P^{r,in} itself from the rig's grid sample.

What differs from a single component's daemon (service.daemon.daemon):

* each sample it takes the rig's grid sample (PREFIX/RIG/grid: every source's measured v and i_out and breaker) and
  forms P^{r,in} = -alpha_s sum_k P_k and its filtered rate through the layer's own pure code
  (service.network.layer.Sharing, with the shares, carrying threshold and plug-in ramp of its NetworkRole): the
  coordinator is not on the per-sample path. P^{r,in} is carried forward along its rate by the grid sample's age (at
  most ``network.extrapolate_s``); its breaker is the grid sample's;
* once per window (and at a breaker change, and at the coordinator's first sample) the coordinator's LayerWindow on
  PREFIX/ID/window brings the v_ref the layer moved and Z^{r,in} for the window, which its feasibility monitor
  checks P^{r,out} against; each is applied from the sample it names. A coordinator gone leaves it sharing with the
  last window's v_ref;
* around the core it runs the offline network's source controller (service.core.source.SourceController): idle
  mode when disconnected or asked for little, and the fallback when the grid sample is older than
  ``network.stale_s`` of sample time;
* the line ends at its terminal (PREFIX/LINE/z/ID) are its neighbours: shown in status and logged, not followed;
* the plug-in handshake: from ``network.connect_at_s`` on (unset: from its first grid sample, if that shows its
  breaker open although the scenario has it connected from the start: a daemon restarted after its source was
  tripped), while its breaker is open, it asks the coordinator
  (PREFIX/COORDINATOR/connect) for its offer (its share of the window's load box), forecasts its own Z^{r,out} for
  that and announces it; the coordinator checks it against the offer's Z^{r,in} and only then has the rig close
  its breaker. In lockstep the request is made
  inside the tick before its answer goes out (the rig waits for that answer, so the breaker closes at the next
  sample, as offline); in realtime a thread makes it and the loop goes on.

In lockstep it waits for the grid sample of its sample, and for the window message only where one is due (a
window's first sample, a breaker change the grid sample shows, and unless the coordinator's token is gone). The
same inputs give the same commands as the offline network (service.network.netsim), so a lockstep run over Zenoh
equals the offline run to the bit, and its log replays identical (idle periods as held rows, v_ref moves as
events).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections import deque

import zenoh

from schemas.codec import GRID, WINDOW, DecodeError, Z
from schemas.component import ComponentConfig
from service.core.interaction import outgoing_power_at
from service.core.source import ACTIVE, MODES, SourceController
from service.core.types import Sample
from service.daemon.bus import key, latest, request
from service.daemon.daemon import Daemon, _now_ns
from service.daemon.forecast_worker import start_background_pool
from service.daemon.neighbours import Neighbour
from service.forecast import forecast_outgoing
from service.network.layer import Sharing

I_MAX_A = 10_000.0  # a grid sample's current beyond this (A) is refused, named (as the coordinator's)

FALLBACK_REFERENCE = {"last-allocation": "last allocation (fallback)", "own-terminal": "own terminal (fallback)"}
WINDOW_PENDING_MAX = 8  # window messages held until their sample comes (lockstep: at most the next one)
GRID_RING = 64  # grid samples kept between two polls (a lockstep daemon polls every sample)


class _Keep(Exception):  # noqa: N818 - a held grid sample still ahead of the measurements: kept held
    pass


class NetworkSourceDaemon(Daemon):
    """See the module docstring."""

    def __init__(self, cfg: ComponentConfig):
        if cfg.network is None:
            raise ValueError("network: a network source daemon needs its network role (energyctl run --network)")
        super().__init__(cfg.model_copy(update={"neighbours": []}))
        self.role = cfg.network
        self.ctl = SourceController(self.core, self.period_s, idle_power_W=self.role.idle_power_W,
                                    idle_tau_s=self.role.idle_tau_s,
                                    hold_when_open=self.role.open_idle == "hold", resume_ramp_s=self.role.resume_ramp_s,
                                    fallback_idle_power_W=self.role.fallback_idle_power_W,
                                    fallback=self.role.fallback)
        r = self.role
        self.grid = Neighbour(r.rig, None)  # the newest grid sample taken: seq, t, P = P^{r,in}, P_dot its rate
        self.sharing = Sharing.of_role(r, self.period_s)
        self.grid_connected: list[bool] | None = None  # the breakers of the newest grid sample
        self._changed_at = -1  # the grid sample whose breakers differ from the one before it
        self._meas_seq = -1  # the measurements' clock: the sample stepped on or waited for (-1: none yet)
        self._grid_held: deque = deque(maxlen=GRID_RING)  # grid samples not judged yet: no measurement, or ahead
        self._grid_ahead_n = 1 + int(round(r.stale_s / self.period_s))  # samples a grid sample may lead them by
        self._grid_behind: tuple | None = None  # (seq, how many in a row follow one another) refused as not after
        self.grid_dropped = 0  # held grid samples pushed out unjudged
        self.grid_new_runs = 0  # new runs taken from grid samples refused in a row
        self._grid_zero: tuple | None = None  # a grid seq 0 mid-run: the rig's restart if seq 1 or meas 0 follows
        self.win = Neighbour(r.coordinator, None)  # the newest window message: seq (applies from), alive
        self.win_vals: tuple | None = None  # the window message applied (schemas.codec.WINDOW order)
        self._win_pending: deque = deque(maxlen=WINDOW_PENDING_MAX)  # received, for a sample still to come
        self.win_dropped = 0  # window messages pushed out of _win_pending before their sample
        self.per_window = max(1, int(round(r.window_s / self.period_s)))
        self.lines: list[Neighbour] = []
        self.connected: bool | None = None  # its breaker as the newest grid sample shows it (None: none yet)
        self.v_ref_moves = 0
        self.fallback_ticks = 0
        self._range: tuple | None = None  # (window, Z^{r,in}) the feasibility monitor holds
        self._t_prev = 0.0  # the previous sample's time (a v_ref event is dated there)
        self._reference = self._share  # the tick's reference: the share formed from the grid sample
        self._seen_restarts = 0
        k_connect = None if self.role.connect_at_s is None else round(self.role.connect_at_s / self.period_s)
        self._connect_seq = k_connect  # the sample from which the breaker is to close
        self._auto_connect = False  # restarted after a trip: asks from its first grid sample on (module docstring)
        self._first_grid = True
        self._next_request_t = -1.0  # sample time of the next connect request allowed
        self.handshake: dict = {"requests": 0, "last": None}
        self._asking = threading.Event()  # realtime: a request is under way in its thread
        self._pool = None  # realtime: the process its plug-in forecast runs in (off the loop's GIL)

    # ---------------------------------------------------------------- setup
    def _extra_topics(self) -> dict:
        c = self.cfg
        base = f"{c.prefix}/{c.id}"
        self.t_window = f"{base}/window"
        out = {self.t_window: ("energyctl.LayerWindow", WINDOW)}
        for ln in self.role.lines:
            out[f"{base}/z_nb/{ln}"] = ("energyctl.Interaction", Z)
        return out

    def open(self) -> None:
        super().open()  # with the compiled tick: the controller plans each tick, the compiled tick steps the core
        c, s, r = self.cfg, self.session, self.role
        # a ring of the newest grid samples: the sharing steps on each that came (its rate over the ones missed); deep
        # enough that a burst of bad frames on the key does not push out the sample a lockstep tick waits for
        self.grid.sub = latest(s, key(c.prefix, r.rig, "grid"), GRID_RING)
        self.grid.topic = f"{c.prefix}/{r.rig}/grid"
        self.win.sub = latest(s, key(c.prefix, c.id, "window"), WINDOW_PENDING_MAX)
        self.win.topic = f"{c.prefix}/{c.id}/window"
        self.lines = [Neighbour(ln, latest(s, f"{c.prefix}/{ln}/z/{c.id}")) for ln in r.lines]
        for nb in self.lines:
            nb.topic = f"{c.prefix}/{c.id}/z_nb/{nb.id}"
        self.neighbours = [self.grid]  # a lockstep tick waits for the grid sample of its sample (_await_neighbours)
        self._by_id = {r.coordinator: self.win}
        self.alive_sub = s.liveliness().declare_subscriber(key(c.prefix, r.coordinator, "alive"),
                                                           zenoh.handlers.FifoChannel(64), history=True)
        if self._connect_seq is not None and not c.loop.lockstep:
            # started and waited for now, before the loop and its token: its imports cost a second of CPU, and a
            # plug-in that came first waited for them (544 ms of a handshake)
            self._pool = start_background_pool()

    def close(self) -> None:
        super().close()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    # ---------------------------------------------------------------- inputs
    def _poll_neighbours(self, now: int) -> None:
        while (tok := self.alive_sub.try_recv()) is not None:
            self.win.alive = tok.kind == zenoh.SampleKind.PUT
        g = self.grid
        while (m := g.sub.try_recv()) is not None:
            try:
                self._take_grid(m.payload.to_bytes(), now)
            except DecodeError as e:
                self._reject(f"grid.{e.field}: invalid", now, e.reason)
        w = self.win
        while (m := w.sub.try_recv()) is not None:
            try:
                v = WINDOW.decode(m.payload.to_bytes())
                self._check_window(v)
            except DecodeError as e:
                self._reject(f"window.{e.field}: invalid", now, e.reason)
                continue
            if len(self._win_pending) == WINDOW_PENDING_MAX:  # the oldest pushed out: counted
                self.win_dropped += 1
            self._win_pending.append(v)
            w.seq, w.t, w.rx_ns = v[0], v[1], now
            w.count += 1
            if w.lagging and v[0] >= self._last_seq:
                w.lagging = False
            if self.recorder is not None:
                self.recorder.offer(self.t_window, v[1], v)
        for nb in self.lines:
            v = self._take_z(nb, now)
            if v is not None and self.recorder is not None:
                self.recorder.offer(nb.topic, v[1], v)

    def _take_grid(self, payload: bytes, now: int) -> None:
        """One grid sample: checked (DecodeError naming the field), then judged against the measurements' clock
        (_judge_grid)."""
        gv = GRID.decode(payload)
        seq, t, v, i_out = gv[0], gv[1], gv[2], gv[3]
        r = self.role
        ns = len(r.shares)
        if len(v) != ns:
            raise DecodeError("GridSample", "v", f"{len(v)} sources; the network has {ns}")
        T = self.period_s
        if abs(t - seq * T) > 0.5 * T:
            raise DecodeError("GridSample", "t", f"{t!r} s is not seq x T ({seq} x {T:g} s)")
        hi = self.cfg.meas_v_max_V
        for j in range(ns):
            if not 0.0 <= v[j] <= hi:
                raise DecodeError("GridSample", f"v[{j}]", f"{v[j]!r} V out of [0, {hi:g}]")
            if not abs(i_out[j]) <= I_MAX_A:
                raise DecodeError("GridSample", f"i_out[{j}]", f"|{i_out[j]!r}| A above {I_MAX_A:g}")
            if not abs(v[j] * i_out[j]) <= r.P_max_W:
                raise DecodeError("GridSample", f"i_out[{j}]", f"|v i_out| {abs(v[j] * i_out[j]):g} W above "
                                                              f"{r.P_max_W:g}")
        if self._meas_seq < 0:  # no measurement yet: nothing to judge its seq by; judged when the first comes
            if len(self._grid_held) == self._grid_held.maxlen:
                self.grid_dropped += 1
            self._grid_held.append((gv, False))
            return
        self._judge_grid(gv, now, counted=False)

    def _judge_grid(self, gv: tuple, now: int, counted: bool) -> None:
        """A checked grid sample judged by its seq against the measurements' clock (self._meas_seq: the measurement
        stepped on or waited for), then the sharing stepped on it. More than ``ahead_n`` samples ahead of the
        measurements it is refused (DecodeError; once: counted says it was) and held, taken if the measurements catch up
        with it (a rig seen again after this daemon was cut off: its measurements jump with it); forged frames far
        ahead never are. A seq not after the newest taken is refused, unless ``per_window`` such refusals in a row
        follow one another on the measurements' clock: then they are a new run (as the coordinator's rule)."""
        seq = gv[0]
        g = self.grid
        if seq > self._meas_seq + self._grid_ahead_n:
            if not counted:
                if len(self._grid_held) == self._grid_held.maxlen:
                    self.grid_dropped += 1
                self._grid_held.append((gv, True))
                raise DecodeError("GridSample", "seq", f"{seq} is ahead of the measurements (at {self._meas_seq}); "
                                                       f"taken if they come to it")
            raise _Keep
        if seq == 1 and self._grid_zero is not None and g.seq >= 1:  # the candidate seq 0 followed: a new run
            self._new_sharing()
            self._step_sharing(self._grid_zero, now)
            self._grid_zero = None
        if seq <= g.seq:
            if seq == 0:  # a candidate: the rig restarted only if grid seq 1 or the measurement's seq 0 follows it
                self._grid_zero = gv
                if self._meas_seq != 0:
                    return
                self._grid_zero = None
            else:  # (a passed sample, or a stray sender's: the sharing steps on each sample once, in order)
                b = self._grid_behind
                follows = b is not None and seq == b[0] + 1
                self._grid_behind = (seq, b[1] + 1 if follows else 1)
                if self._grid_behind[1] < self.per_window:
                    raise DecodeError("GridSample", "seq", f"{seq} not after {g.seq}")
                self.grid_new_runs += 1  # a window of samples in a row behind one taken: that one was not the rig's
            self._new_sharing()  # (seq 0 again, with the measurement's: the rig restarted)
        elif self._grid_zero is not None:  # a seq 0 not followed by 1 nor by the measurement's 0: a stray one
            self._grid_zero = None
            self._reject("grid.seq: invalid", now, "0 mid-run, followed by neither grid seq 1 nor the measurement's 0")
        self._grid_behind = None
        self._step_sharing(gv, now)

    def _step_sharing(self, gv: tuple, now: int) -> None:
        seq, t, v, i_out, connected = gv[0], gv[1], gv[2], gv[3], gv[4]
        r, g = self.role, self.grid
        ns = len(r.shares)
        P = [v[j] * i_out[j] if connected[j] else 0.0 for j in range(ns)]
        want, rate = self.sharing.step(seq, P, connected)
        if self.grid_connected is not None and connected != self.grid_connected:
            self._changed_at = seq
        self.grid_connected = connected
        i = r.index
        g.seq, g.t, g.P, g.P_dot = seq, t, want[i], rate[i]
        g.rx_ns = now
        g.count += 1

    def _set_clock(self, seq: int, now: int) -> None:
        """The measurements' clock is at ``seq`` (the sample stepped on or waited for): the grid samples held (before
        the first measurement, or ahead of the measurements) judged again. While the grid samples taken keep pace
        with the measurements, those refused as ahead are not the rig's (a stray sender's): dropped, counted already."""
        self._meas_seq = seq
        if seq == 0 and self._grid_zero is not None:  # the measurement's seq 0 follows the candidate: a new run
            gz, self._grid_zero = self._grid_zero, None
            self._new_sharing()
            self._step_sharing(gz, now)
        held = self._grid_held
        if not held:
            return
        if self.grid.seq >= seq - 1 and all(counted for _gv, counted in held):
            held.clear()
            return
        items = sorted(held, key=lambda h: h[0][0])
        held.clear()
        for gv, counted in items:
            try:
                self._judge_grid(gv, now, counted)
            except _Keep:
                held.append((gv, True))
            except DecodeError as e:
                self._reject(f"grid.{e.field}: invalid", now, e.reason)

    def _new_sharing(self) -> None:
        g = self.grid
        self.sharing = Sharing.of_role(self.role, self.period_s)
        g.seq, g.count, g.t, g.P, g.P_dot = -1, 0, 0.0, 0.0, 0.0
        self.grid_connected = None
        self._changed_at = -1

    def _check_window(self, v: tuple) -> None:
        """Refuse (DecodeError naming the field) a window message no layer of this network sends: a v_ref outside
        the layer's bounds, a range whose ends are not in order, a sample more than two windows ahead of the newest
        one stepped on."""
        r = self.role
        if (r.v_ref_min_V is not None and v[4] < r.v_ref_min_V) or (r.v_ref_max_V is not None and v[4] > r.v_ref_max_V):
            raise DecodeError("LayerWindow", "v_ref_V", f"{v[4]:g} V outside [{r.v_ref_min_V}, {r.v_ref_max_V}]")
        if v[6]:  # a range: its ends in order
            if not v[7] <= v[8]:
                raise DecodeError("LayerWindow", "Z_P_min", f"{v[7]:g} W above Z_P_max {v[8]:g} W")
            if not v[9] <= v[10]:
                raise DecodeError("LayerWindow", "Z_Qdot_min", f"{v[9]:g} W/s above Z_Qdot_max {v[10]:g} W/s")
        ls = self.last_sample
        if ls is not None and v[0] > ls[0] + 2 * self.per_window + 1:  # the coordinator sends at most a window ahead
            raise DecodeError("LayerWindow", "seq", f"{v[0]} is ahead of the samples (newest {ls[0]})")

    def _await_neighbours(self, seq: int, deadline: int) -> None:
        """Lockstep: poll until the grid sample for ``seq`` came, then, where a window message is due (a window's
        first sample, a breaker change that sample shows), until the coordinator's for ``seq`` came (at a breaker
        change: the one made after that sample; not while its token is gone nor while it lags), or the deadline (ns)
        passes: then count the timeout."""
        now_ns, stop, g, w = time.monotonic_ns, self._stop, self.grid, self.win
        self._set_clock(seq, now_ns())
        while g.seq < seq and not g.lagging and not stop.is_set():
            self._poll_neighbours(now_ns())
            if g.seq >= seq:
                break
            if now_ns() > deadline:
                self.stats.lockstep_timeouts += 1
                g.lagging = True
                break
            time.sleep(20e-6)
        if g.lagging and g.seq >= seq - 1:
            g.lagging = False
        if seq % self.per_window and self._changed_at != seq:
            return
        # at a breaker change, the message made after that sample (t >= t(seq)): on a window's first sample the
        # window-end message made after the sample before it is for seq too, and the breakers' comes after it
        t_min = (seq - 0.5) * self.period_s if self._changed_at == seq else -1.0
        while (w.seq < seq or w.t < t_min) and w.alive is not False and not w.lagging and not stop.is_set():
            self._poll_neighbours(now_ns())
            if w.seq >= seq and w.t >= t_min:
                break
            if now_ns() > deadline:
                self.stats.lockstep_timeouts += 1
                w.lagging = True  # until a window message for a sample now comes
                break
            time.sleep(20e-6)

    def _forget_run(self, seq: int) -> None:
        """The rig restarted (seq: the new run's sample): what this daemon knew of its run (sharing, window,
        breaker, handshake) is not this run's; a grid sample or window message of the new run already taken stays."""
        if self.grid.seq > seq:
            self._new_sharing()
        self.win_vals = None
        keep = [w for w in self._win_pending if w[0] <= seq]
        self._win_pending.clear()
        self._win_pending.extend(keep)
        self.win.seq = max((w[0] for w in keep), default=-1)
        self.connected = None
        self._next_request_t = -1.0
        self._range = None
        self._seen_restarts = self.restarts
        self._first_grid = True
        self.ctl.reset_fallback()  # the previous run's kept share is not this run's
        if self._auto_connect:  # a new run: its start decides again
            self._connect_seq, self._auto_connect = None, False

    # ---------------------------------------------------------------- the tick (Daemon._step, with these parts)
    def _begin(self, v: tuple) -> None:
        """A new run (the rig restarted) forgets the previous one's; the previous sample's time, for a v_ref event."""
        if v[0] != self._meas_seq:
            self._set_clock(v[0], _now_ns())
        if self.restarts != self._seen_restarts:
            self._forget_run(v[0])
        self._t_prev = self.last_sample[1] if self.last_sample is not None else v[1]

    def _share(self, v: tuple, now: int) -> tuple[float, float, int]:
        """This daemon's reference (plugged into Daemon._step): the window messages due at this sample applied
        (v_ref, Z^{r,in}), its breaker from the grid sample, and P^{r,in} as it formed it from the grid sample
        (carried forward by its age) through the source controller's plan (idle, fallback, the ramp back): the core
        steps on what the plan gives it (the compiled tick, in Daemon._step), or the controller's idle command goes
        out."""
        seq, t = v[0], v[1]
        role, ctl, rec, g = self.role, self.ctl, self.recorder, self.grid
        pend = self._win_pending
        due = [wv for wv in pend if wv[0] <= seq] if pend else ()
        if due:  # the window messages from this sample on, in order (a later one stays until its sample)
            keep = [wv for wv in pend if wv[0] > seq]
            pend.clear()
            pend.extend(keep)
        for wv in due:
            self.win_vals = wv
            new = ctl.set_v_ref(wv[4])  # the layer's move, applied before this sample as offline
            if new is not None:
                self.v_ref_moves += 1
                if rec is not None:
                    t_prev = self._t_prev
                    rec.offer(self.t_ev, t_prev, (t_prev, seq, "config", json.dumps({"v_ref_V": new.v_ref_V})))
            if wv[6] and (wv[2], wv[7:11]) != self._range:  # a new window's range, or this one's after an event
                self._range = (wv[2], wv[7:11])
                self.feas.set_range(wv[2], wv[7:11])
        if self.grid_connected is not None and g.count:
            self.connected = bool(self.grid_connected[role.index])
            if self._first_grid:
                self._first_grid = False
                if not self.connected and self._connect_seq is None and self.role.connected_at_start:
                    self._connect_seq, self._auto_connect = seq, True  # restarted after a trip: back by itself
        age = t - g.t
        # (one from ahead of this sample by more than stale_s is not this run's: a rig restarted, a stray sender)
        fresh = g.count > 0 and -role.stale_s <= age <= role.stale_s
        P_in = outgoing_power_at(t, g.t, g.P, g.P_dot, role.stale_s, role.extrapolate_s) if fresh else g.P
        self.reference = "sharing" if fresh else FALLBACK_REFERENCE[role.fallback]
        if self.state != "active":  # inactive: hold the source voltage
            return ctl.P_in_used, 0.0, self.HOLD
        connected = True if self.connected is None else self.connected  # unknown: its own terminal decides
        P, P_dot, r = ctl.plan(Sample(seq, t, v[2], v[3], v[4], v[5]), P_in, 0.0, connected, fresh)
        if r is not None:  # idle: its own command, the core told
            self._held_du = r
            return P, 0.0, self.HELD
        if not fresh:
            self.fallback_ticks += 1
        return P, P_dot, self.STEP

    def _before_publish(self, seq: int, t: float) -> None:
        if self._connect_seq is not None and self.connected is False:
            self._maybe_connect(seq, t)

    def _feasibility(self, t: float, P_out: float, Qdot_out: float) -> None:
        """A stepped tick's P^{r,out} and Qdot^{r,out} against Z^{r,in} of the window message (not in fallback, and
        after the estimate's derivative filter has settled)."""
        if self.ctl.mode == ACTIVE and t >= 5.0 * self.core.cfg.deriv_tau_s:
            self.feas.update(t, P_out, Qdot_out)

    # ---------------------------------------------------------------- the plug-in handshake
    def _maybe_connect(self, seq: int, t: float) -> None:
        """Ask to connect when due (its breaker open, connect_at reached, not asked within connect_retry_s)."""
        if seq + 1 < self._connect_seq or t < self._next_request_t or self._asking.is_set():
            return
        self._next_request_t = t + self.role.connect_retry_s
        body = {"source": self.cfg.id, "controller": self.core.cfg.model_dump(), "t": t,
                "at_seq": seq + 1 if self.cfg.loop.lockstep else None}
        if self.cfg.loop.lockstep:  # the rig waits for this tick's answer: the breaker closes at the next sample
            self._ask(body)
        else:
            self._asking.set()
            threading.Thread(target=self._ask, args=(body,), name="connect", daemon=True).start()

    def _ask(self, body: dict) -> None:
        """The plug-in handshake: ask what it would be asked to deliver over the current window (the offer), forecast
        its own Z^{r,out} for that (service.forecast, as the offline layer does), announce it; the coordinator
        checks it against the offer's Z^{r,in} and has the rig close the breaker before it answers. Whatever goes
        wrong (no answer, a reply that is not an object, a broken forecast) is a refusal it reports and retries."""
        c = self.cfg
        where = key(c.prefix, self.role.coordinator, "connect")
        t0 = time.perf_counter()
        forecast_ms = None
        try:
            ok, reply = request(self.session, where, {**body, "offer": True}, 5.0)
            if not isinstance(reply, dict):
                raise ValueError(f"the offer's reply: expected an object, got {type(reply).__name__}")
            if ok and reply.get("offer"):
                t1 = time.perf_counter()
                f = self._forecast(reply)
                forecast_ms = (time.perf_counter() - t1) * 1e3
                ok, reply = request(self.session, where, {
                    **body, "saturation": f.saturation,
                    "Z_out": {"P": [f.P_lo, f.P_hi], "Qdot": [f.Qdot_lo, f.Qdot_hi]}}, 5.0)
                if not isinstance(reply, dict):
                    raise ValueError(f"the verdict's reply: expected an object, got {type(reply).__name__}")
        except Exception as e:  # noqa: BLE001 - a bad offer or a broken forecast: a refusal it reports, not a crash
            ok, reply = False, {"error": f"{type(e).__name__}: {e}"}
        finally:
            self._asking.clear()
        self.handshake["requests"] += 1
        self.handshake["last"] = {"t": body["t"], "accepted": bool(ok and reply.get("accepted")),
                                  "reason": reply.get("reason") or reply.get("error", ""),
                                  "Z_out": reply.get("Z_out"), "Z_in": reply.get("Z_in"),
                                  "forecast_ms": forecast_ms, "handshake_ms": (time.perf_counter() - t0) * 1e3}
        if self.recorder is not None:
            self.recorder.offer(self.t_ev, body["t"], (body["t"], max(self._last_seq, 0), "connect",
                                                       json.dumps(self.handshake["last"])))
        if not self.handshake["last"]["accepted"]:
            print(f"energyctl[{c.id}]: connect refused: {self.handshake['last']['reason']}", file=sys.stderr,
                  flush=True)

    def _forecast(self, offer: dict):
        """Its Z^{r,out} for the offer (box W and W/s, tau' s, v_ref V, window s): the offline layer's forecast, here
        (lockstep: in the tick; realtime: in its own process)."""
        box = tuple(float(x) for x in offer["box"])
        if len(box) != 4:
            raise ValueError(f"offer.box: expected 4 numbers, got {len(box)}")
        ctl = self.core.cfg.model_copy(update={"v_ref_V": float(offer["v_ref_V"])})
        args = (ctl, self.cfg.model, self.period_s, self.cfg.delay_samples, box, float(offer["tau_prime_s"]))
        kw = {"max_ramp_s": float(offer["window_s"]), "impl": self.cfg.core}
        if self._pool is None:
            return forecast_outgoing(*args, **kw)
        try:
            return self._pool.submit(forecast_outgoing, *args, **kw).result(timeout=30)
        except Exception:  # a worker killed or stuck: a new one for the next request (this one is refused)
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = start_background_pool()
            raise

    # ---------------------------------------------------------------- status
    def status(self) -> dict:
        out = super().status()
        now = _now_ns()
        g, w, wv = self.grid, self.win, self.win_vals
        last_t = self.last_sample[1] if self.last_sample else None
        out["network"] = {
            "network": self.role.network,
            "mode": MODES[self.ctl.mode],
            "breaker": None if self.connected is None else ("closed" if self.connected else "open"),
            "sharing": None if g.count == 0 else {
                "from": self.role.rig, "seq": g.seq, "t": g.t, "P_r_in": g.P, "P_r_in_dot": g.P_dot,
                "age_s": None if last_t is None else last_t - g.t,
                "stale": last_t is None or abs(last_t - g.t) > self.role.stale_s,
                "received_ago_s": (now - g.rx_ns) / 1e9},
            "window": {
                "from": self.role.coordinator, "coordinator_alive": w.alive, "messages": w.count,
                **({} if wv is None else {
                    "seq": wv[0], "window": wv[2], "alpha": wv[3], "v_ref_V": wv[4], "connected": bool(wv[5]),
                    "Z_in": list(wv[7:11]) if wv[6] else None, "received_ago_s": (now - w.rx_ns) / 1e9})},
            "P_r_in_used": self.ctl.P_in_used, "v_ref_V": self.ctl.v_ref_V, "v_ref_moves": self.v_ref_moves,
            "fallback_ticks": self.fallback_ticks, "mode_switches": self.ctl.switches,
            "grid_held": len(self._grid_held), "grid_dropped": self.grid_dropped, "grid_new_runs": self.grid_new_runs,
            "window_dropped": self.win_dropped,
            "lines": {nb.id: {"P_r_out": nb.P, "messages": nb.count} for nb in self.lines},
            "handshake": dict(self.handshake),
            "not_connected": self._why_not_connected(),
        }
        return out

    def _why_not_connected(self) -> str | None:
        """Why its breaker is not closed, for the operator (None: it is, or no grid sample said yet)."""
        if self.connected is not False:
            return None
        if self._connect_seq is None:
            return ("breaker open; this daemon does not ask to connect (no --connect-at, no connect event for it in "
                    "the scenario, and it did not start connected): start it with --connect-at 0")
        period = self.period_s
        last = self.handshake["last"]
        if last is not None and not last["accepted"]:
            return (f"breaker open; its last connect request (t = {last['t']:.3f} s) was refused: {last['reason']}; "
                    f"it asks again from t = {self._next_request_t:.3f} s")
        since = self._connect_seq * period
        how = "restarted after a trip: it asks by itself" if self._auto_connect else "connect_at"
        if self.handshake["requests"] == 0:
            return f"breaker open; asking to connect from t = {since:.3f} s ({how})"
        return f"breaker open; asking to connect ({how}; {self.handshake['requests']} requests so far)"
