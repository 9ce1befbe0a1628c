"""A source on a live network: today's daemon, its P^{r,in} coming from the coordinator's allocation.

What differs from a single component's daemon (service.daemon.daemon):

* each tick it follows the newest allocation on PREFIX/ID/alloc (schemas.messages.Allocation): P^{r,in} carried
  forward along its rate by its age (at most ``network.extrapolate_s``), the v_ref the layer moved, its breaker as
  the rig reported it, and Z^{r,in} for the window, which its feasibility monitor checks P^{r,out} against;
* around the core it runs the offline network's source controller (service.core.source.SourceController): idle
  mode when disconnected or asked for little, and the fallback to its own terminal power when the allocation is
  older than ``network.stale_s`` of sample time — a coordinator gone or cut off leaves it on its last v_ref, falling
  back as the offline design does;
* the line ends at its terminal (PREFIX/LINE/z/ID) are its neighbours: shown in status and logged, not followed;
* the plug-in handshake: from ``network.connect_at_s`` on (unset: from its first allocation, if that shows its
  breaker open although the scenario has it connected from the start: a daemon restarted after its source was
  tripped), while its breaker is open, it asks the coordinator
  (PREFIX/COORDINATOR/connect) for its offer (its share of the window's load box), forecasts its own Z^{r,out} for
  that and announces it; the coordinator checks it against the offer's Z^{r,in} and only then has the rig close
  its breaker. In lockstep the request is made
  inside the tick before its answer goes out (the rig waits for that answer, so the breaker closes at the next
  sample, as offline); in realtime a thread makes it and the loop goes on.

The same inputs give the same commands as the offline network (service.network.netsim), so a lockstep run over
Zenoh equals the offline run to the bit, and its log replays identical (idle periods as held rows, v_ref moves as
events).
"""

from __future__ import annotations

import json
import sys
import threading
import time

import zenoh

from schemas.codec import ALLOC, CMD, DecodeError, Z
from schemas.component import ComponentConfig
from service.core.interaction import outgoing_power_at
from service.core.source import ACTIVE, IDLE, MODES, SourceController
from service.core.types import Sample
from service.daemon.bus import key, latest, request
from service.daemon.daemon import Daemon, _now_ns
from service.daemon.forecast_worker import start_background_pool
from service.daemon.neighbours import Neighbour
from service.forecast import forecast_outgoing

FALLBACK_REFERENCE = {"last-allocation": "last allocation (fallback)", "own-terminal": "own terminal (fallback)"}


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
        self.alloc = Neighbour(self.role.coordinator, None)
        self.alloc_vals: tuple | None = None  # the newest allocation's values (schemas.codec.ALLOC order)
        self.lines: list[Neighbour] = []
        self.connected: bool | None = None  # its breaker as the newest allocation reported it (None: none yet)
        self.v_ref_moves = 0
        self.fallback_ticks = 0
        self._range: tuple | None = None  # (window, Z^{r,in}) the feasibility monitor holds
        self._seen_restarts = 0
        k_connect = None if self.role.connect_at_s is None else round(self.role.connect_at_s / self.period_s)
        self._connect_seq = k_connect  # the sample from which the breaker is to close
        self._auto_connect = False  # restarted after a trip: asks from its first allocation on (module docstring)
        self._first_alloc = True
        self._next_request_t = -1.0  # sample time of the next connect request allowed
        self.handshake: dict = {"requests": 0, "last": None}
        self._asking = threading.Event()  # realtime: a request is under way in its thread
        self._pool = None  # realtime: the process its plug-in forecast runs in (off the loop's GIL)

    # ---------------------------------------------------------------- setup
    def _extra_topics(self) -> dict:
        c = self.cfg
        base = f"{c.prefix}/{c.id}"
        self.t_alloc = f"{base}/alloc"
        out = {self.t_alloc: ("energyctl.Allocation", ALLOC)}
        for ln in self.role.lines:
            out[f"{base}/z_nb/{ln}"] = ("energyctl.Interaction", Z)
        return out

    def open(self) -> None:
        super().open()
        if self._fast is not None:  # the compiled tick steps the bare core; this daemon steps the source controller
            self._fast.close()
            self._fast = None
        c, s = self.cfg, self.session
        self.alloc.sub = latest(s, key(c.prefix, c.id, "alloc"))
        self.alloc.topic = f"{c.prefix}/{c.id}/alloc"
        self.lines = [Neighbour(ln, latest(s, f"{c.prefix}/{ln}/z/{c.id}")) for ln in self.role.lines]
        for nb in self.lines:
            nb.topic = f"{c.prefix}/{c.id}/z_nb/{nb.id}"
        self.neighbours = [self.alloc]  # a lockstep tick waits for the allocation for its sample (not the lines)
        self._by_id = {self.role.coordinator: self.alloc}
        self.alive_sub = s.liveliness().declare_subscriber(key(c.prefix, self.role.coordinator, "alive"),
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
            self.alloc.alive = tok.kind == zenoh.SampleKind.PUT
        a = self.alloc
        m = a.sub.try_recv()
        if m is not None:
            try:
                v = ALLOC.decode(m.payload.to_bytes())
                self._check_alloc(v)
            except DecodeError as e:
                self._reject(f"alloc.{e.field}: invalid", now, e.reason)
            else:
                a.seq, a.t, a.P, a.P_dot = v[0], v[1], v[2], v[3]
                self.alloc_vals = v
                a.rx_ns = now
                a.count += 1
                if self.recorder is not None:
                    self.recorder.offer(a.topic, v[1], v)
        for nb in self.lines:
            v = self._take_z(nb, now)
            if v is not None and self.recorder is not None:
                self.recorder.offer(nb.topic, v[1], v)

    def _check_alloc(self, v: tuple) -> None:
        """Refuse (DecodeError naming the field) an allocation that no layer of this network sends: a v_ref outside
        the layer's bounds, a power beyond the source's."""
        r = self.role
        if (r.v_ref_min_V is not None and v[4] < r.v_ref_min_V) or (r.v_ref_max_V is not None and v[4] > r.v_ref_max_V):
            raise DecodeError("Allocation", "v_ref_V", f"{v[4]:g} V outside [{r.v_ref_min_V}, {r.v_ref_max_V}]")
        if abs(v[2]) > r.P_max_W:
            raise DecodeError("Allocation", "P_r_in", f"|{v[2]:g}| W above {r.P_max_W:g}")

    def _forget_run(self) -> None:
        """The rig restarted: what this daemon knew of its run (allocation, breaker, handshake) is not this run's."""
        a = self.alloc
        a.seq, a.count, a.t, a.P, a.P_dot = -1, 0, 0.0, 0.0, 0.0
        self.alloc_vals = None
        self.connected = None
        self._next_request_t = -1.0
        self._range = None
        self._seen_restarts = self.restarts
        self._first_alloc = True
        self.ctl.reset_fallback()  # the previous run's kept share is not this run's
        if self._auto_connect:  # a new run: its start decides again
            self._connect_seq, self._auto_connect = None, False

    # ---------------------------------------------------------------- the tick
    def _step(self, v: tuple, now: int) -> None:
        """The tick's second half for this daemon (the first, Daemon._sample, checks the sample alone: no compiled
        tick here): the source controller steps on the sample with the allocation's P^{r,in}."""
        t_control = _now_ns()
        seq, t = v[0], v[1]
        if self.restarts != self._seen_restarts:
            self._forget_run()
        t_prev = self.last_sample[1] if self.last_sample is not None else t
        self._take_sample(v)
        role, ctl, rec, a = self.role, self.ctl, self.recorder, self.alloc
        av = self.alloc_vals
        if av is not None:
            new = ctl.set_v_ref(av[4])  # the layer's move, applied before this sample as offline
            if new is not None:
                self.v_ref_moves += 1
                if rec is not None:
                    rec.offer(self.t_ev, t_prev, (t_prev, seq, "config", json.dumps({"v_ref_V": new.v_ref_V})))
            self.connected = bool(av[5])
            if self._first_alloc:
                self._first_alloc = False
                if not self.connected and self._connect_seq is None and self.role.connected_at_start:
                    self._connect_seq, self._auto_connect = seq, True  # restarted after a trip: back by itself
            if av[7] and (av[6], av[8:12]) != self._range:  # a new window's range, or this one's after an event
                self._range = (av[6], av[8:12])
                self.feas.set_range(av[6], av[8:12])
        age = t - a.t
        # (one from ahead of this sample by more than stale_s is not this run's: a rig restarted, a stray sender)
        fresh = a.count > 0 and -role.stale_s <= age <= role.stale_s
        P_in = outgoing_power_at(t, a.t, a.P, a.P_dot, role.stale_s, role.extrapolate_s) if fresh else a.P
        connected = True if self.connected is None else self.connected  # unknown: its own terminal decides
        limited = False
        if self.state == "active":
            du, du_next = ctl.step(Sample(seq, t, v[2], v[3], v[4], v[5]), P_in, 0.0, connected, fresh)
            stepped = ctl.mode != IDLE
            if stepped:
                limited = self.core.out.limited
                if not fresh:
                    self.fallback_ticks += 1
        else:  # inactive: hold the source voltage
            du = du_next = 0.0
            stepped = False
            self.core.hold(seq)
        self.reference = "allocation" if fresh else FALLBACK_REFERENCE[role.fallback]
        if self._connect_seq is not None and not connected:
            self._maybe_connect(seq, t)
        cmd = CMD.encode(seq, t, du, du_next, limited)
        self._remember(seq, v[4], du)
        if rec is not None:
            rec.offer_group(0, t, *v, seq, t, ctl.P_in_used, 0.0, stepped, seq, t, du, du_next, limited)
        t_put = _now_ns()
        self.control_ns = t_put - t_control
        self.cmd_pub.put(cmd)
        self.put_ns = _now_ns() - t_put
        self.last_cmd = (seq, t, du, du_next, limited)
        est = self.core.out.est
        if stepped and ctl.mode == ACTIVE and est is not None and t >= 5.0 * self.core.cfg.deriv_tau_s:
            self.feas.update(t, est.P_r_out_port, est.Qdot_r_out_port)
        self._rarer_work(t, stepped and est is not None)

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
        a = self.alloc
        av = self.alloc_vals
        last_t = self.last_sample[1] if self.last_sample else None
        out["network"] = {
            "network": self.role.network,
            "mode": MODES[self.ctl.mode],
            "breaker": None if self.connected is None else ("closed" if self.connected else "open"),
            "allocation": None if av is None else {
                "from": self.role.coordinator, "seq": av[0], "t": av[1], "P_r_in": av[2], "P_r_in_dot": av[3],
                "v_ref_V": av[4], "window": av[6], "Z_in": list(av[8:12]) if av[7] else None,
                "age_s": None if last_t is None else last_t - av[1],
                "stale": last_t is None or abs(last_t - av[1]) > self.role.stale_s,
                "coordinator_alive": a.alive, "received_ago_s": (now - a.rx_ns) / 1e9},
            "P_r_in_used": self.ctl.P_in_used, "v_ref_V": self.ctl.v_ref_V, "v_ref_moves": self.v_ref_moves,
            "fallback_ticks": self.fallback_ticks, "mode_switches": self.ctl.switches,
            "lines": {nb.id: {"P_r_out": nb.P, "messages": nb.count} for nb in self.lines},
            "handshake": dict(self.handshake),
            "not_connected": self._why_not_connected(),
        }
        return out

    def _why_not_connected(self) -> str | None:
        """Why its breaker is not closed, for the operator (None: it is, or no allocation said yet)."""
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
