"""The interconnection layer as a Zenoh service (energyctl coordinator).

It is off the per-sample path: each source's daemon forms its P^{r,in} = -alpha_s sum_k P_k itself from the rig's
grid sample (service.network.layer.Sharing). The coordinator's loop thread takes the same grid sample
(PREFIX/RIG/grid: each source's measured v and i_out, its breaker, the buses' measured voltages, the loads' powers)
and drives the same pure layer as the offline run (service.network.layer.InterconnectionLayer.step): once per window
it moves v_ref and sets the next window's ranges, and publishes each source's LayerWindow on PREFIX/SOURCE/window
(alpha_s, v_ref, its breaker, Z^{r,in}): at the first sample it takes, at each window's end and when a breaker
changes. It judges plug-ins and trips.

* **Plug-in handshake** (PREFIX/ID/connect, JSON): an offer request (``{"source", "controller", "at_seq",
  "offer": true}``) is answered with what the source would be asked to deliver over the current window (its share
  of the window's load box, tau', the v_ref the layer holds for it; ``connect_offer``), kept per source; the
  announcement (``"Z_out"``, ``"saturation"``: the source's own forecast for that box) is judged against that
  offer's Z^{r,in}, refused if the offer is older than MAX_OFFER_AGE_WINDOWS windows or the breakers changed since,
  and only if Z^{r,out} is inside Z^{r,in} the rig is asked to close the breaker (PREFIX/RIG/breaker); the answer
  carries the verdict, the reason and both ranges; a request with neither is refused (no forecast runs on the
  loop thread for a peer). In lockstep a request for sample k is answered after sample k - 1 was fully processed,
  so the breaker closes at k as offline.
* **Trip on lost liveliness**: a connected source whose token PREFIX/SOURCE/alive disappears is tripped: the rig is
  asked to open its breaker, and from the sample that shows it open its share goes to the others.
* **Coming back**: at start it asks each source's daemon for its config and resumes from the v_ref it reports; the
  sources, meanwhile, kept sharing from the grid sample with their last v_ref (service.daemon.netsource).

Query handling, JSON and logging stay off the loop thread's per-sample path except for the connect check, which is
rare and, in lockstep, must happen between two samples.

A bad grid sample or request is rejected, counted and answered; an exception nobody expected, in the loop or in a
trip's or a liveliness re-check's thread, fails the coordinator (service.daemon.failure): it publishes no more
window messages (each source keeps sharing from the grid sample with the last window's v_ref), withdraws its
token, says why on stderr and in status (state failed, failure), and ``energyctl coordinator`` exits 1.
"""

from __future__ import annotations

import json
import sys
import threading
from collections import deque
from math import isfinite
from queue import Empty, Queue

import zenoh

from schemas.codec import GRID, LAYER_SRC, LAYER_TICK, WINDOW, DecodeError
from schemas.netlive import CoordinatorConfig
from schemas.network import NetworkScenario
from schemas.scenario import ControllerConfig
from service.core.feasibility import incoming_range
from service.daemon.bus import answer, close_session, key, open_session, publisher, queued, request, serve_queries
from service.daemon.failure import Failure, guarded
from service.network.layer import InterconnectionLayer, judge_announced, offer_staleness
from service.plant.network import LoadForecast

MAX_REQUEST_BYTES = 64 * 1024  # a connect request larger than this is refused unread
I_MAX_A = 10_000.0  # a grid sample's current beyond this (A) is refused, named
P_MAX_W = 10_000_000.0  # a load's power beyond this (W) is refused, named
_NO_RANGE = (0.0, 0.0, 0.0, 0.0)  # Z^{r,in} in a LayerWindow without a range (has_range false)


class Coordinator:
    """See the module docstring. ``open()``, then ``run(stop)`` on a thread, then ``close()``."""

    def __init__(self, cfg: CoordinatorConfig, net: NetworkScenario, impl: str = "auto"):
        if net.layer.v_ref_mode == "per-source" and net.layer.idle_power_W > 0.0:
            raise ValueError("layer.v_ref_mode: 'per-source' with layer.idle_power_W > 0 needs each source's mode "
                             "every sample, which only its daemon knows; live, use idle_power_W = 0 (a connected "
                             "source is then active) or v_ref_mode = 'common'")
        if any(ln.delay_s or ln.loss or ln.silent_from_s is not None for ln in net.links.values()):
            raise ValueError("links: delay, loss and silence of the interaction messages are an offline model; live, "
                             "the network is the link (remove the links table)")
        self.cfg, self.net, self.impl = cfg, net, impl
        self.layer = InterconnectionLayer(net, LoadForecast(net))
        self.names = list(net.sources)
        self.ns = len(self.names)
        self.d = net.timing.delay_samples
        self.seq, self.t = -1, 0.0
        self.connected = [s.connected for s in net.sources.values()]
        self.alive: dict[str, bool | None] = dict.fromkeys(self.names)
        self.window = 0
        self.zin: list[tuple | None] = [None] * self.ns
        self.want = [0.0] * self.ns
        self.verdicts: deque = deque(maxlen=20)
        self.trips: deque = deque(maxlen=20)
        self.counters = {"grid_samples": 0, "missing_samples": 0, "rejected": 0, "connect_requests": 0,
                         "accepted": 0, "refused": 0, "trips": 0, "restarts": 0, "windows_sent": 0}
        self.last_reject = ""
        self.resumed: dict[str, float] = {}
        self.sizes = (self.ns, len(net.buses), len(net.loads))
        self._behind = 0  # grid samples in a row not after the newest one taken
        self._jump = -2  # the last grid sample refused for coming more than a window after the newest
        self._tripping: set[str] = set()  # sources asked to trip, until a sample shows their breaker open
        self.rig_alive: bool | None = None  # the rig's token: gone means this coordinator may be the one cut off
        self._alive_checked: Queue = Queue()
        self.v_nom = net.nominal_v_V
        self._connects: Queue = Queue()
        # per source: the newest offer (window, box, tau', the breakers then), until announced
        self._offers: dict[str, tuple] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.failure = Failure(f"energyctl coordinator[{cfg.id}]")
        self.session = None
        self.token = None
        self.recorder = None
        self.log_path = None

    # ---------------------------------------------------------------- setup / teardown
    def open(self) -> None:
        c = self.cfg
        self.session = s = open_session(c.zenoh)
        self.grid_sub, self.grid_q = queued(s, key(c.prefix, c.rig, "grid"), 0 if c.lockstep else 4)
        self.pubs = [publisher(s, key(c.prefix, name, "window")) for name in self.names]
        self.alive_sub = s.liveliness().declare_subscriber(key(c.prefix, "*", "alive"),
                                                           zenoh.handlers.FifoChannel(256), history=True)
        if c.out:
            self.recorder = self._open_recorder()
        self._resume()
        self.queryables = {leaf: s.declare_queryable(key(c.prefix, c.id, leaf), zenoh.handlers.FifoChannel(64))
                           for leaf in ("status", "connect")}
        self._threads = [threading.Thread(target=self._serve, args=(leaf,), name=leaf, daemon=True)
                         for leaf in self.queryables]
        for t in self._threads:
            t.start()
        self.token = s.liveliness().declare_token(key(c.prefix, c.id, "alive"))

    def _open_recorder(self):
        from service.logio.mcapfile import git_revision
        from service.logio.ring import RingRecorder

        c = self.cfg
        base = f"{c.prefix}/{c.id}"
        self.t_tick, self.t_ev = f"{base}/layer/tick", f"{base}/events"
        self.t_src = [f"{base}/layer/{name}" for name in self.names]
        self.t_win = [f"{base}/window/{name}" for name in self.names]  # every LayerWindow sent, as sent
        topics = {self.t_tick: ("energyctl.LayerTick", LAYER_TICK), self.t_ev: ("energyctl.Event", None)}
        for t in self.t_src:
            topics[t] = ("energyctl.LayerSource", LAYER_SRC)
        for t in self.t_win:
            topics[t] = ("energyctl.LayerWindow", WINDOW)
        self.log_path = c.out
        meta = {"scenario": {"json": self.net.model_dump_json()}, "coordinator": {"json": c.model_dump_json()},
                "build": {"git": git_revision()}}
        rec = RingRecorder(c.out, topics, meta)
        rec.wait_ready()
        return rec

    def _implausible(self, v, i_out, bus_v, load_P) -> str:
        """What in a grid sample no network of this scenario can show (a field named), or ''."""
        hi = 2.5 * self.v_nom
        for name, xs, ok in (("v", v, lambda x: 0.0 <= x <= hi), ("bus_v", bus_v, lambda x: 0.0 <= x <= hi),
                             ("i_out", i_out, lambda x: abs(x) <= I_MAX_A), ("load_P", load_P,
                                                                             lambda x: abs(x) <= P_MAX_W)):
            for j, x in enumerate(xs):
                if not ok(x):
                    return f"grid.{name}[{j}]: {x!r} out of range"
        return ""

    def _resume(self) -> None:
        """Each source's v_ref as its daemon reports it (a coordinator that comes back resumes from them)."""
        c = self.cfg
        for j, name in enumerate(self.names):
            ok, reply = request(self.session, key(c.prefix, name, "config"), None, c.resume_timeout_s)
            v_ref = reply.get("controller", {}).get("v_ref_V") if ok and isinstance(reply.get("controller"),
                                                                                       dict) else None
            lo = self.layer.v_ref0[j] - self.net.layer.v_ref_max_offset_V
            hi = self.layer.v_ref0[j] + self.net.layer.v_ref_max_offset_V
            if isinstance(v_ref, int | float) and isfinite(v_ref):
                self.layer.v_ref[j] = min(max(float(v_ref), lo), hi)
                self.resumed[name] = self.layer.v_ref[j]
        if self.resumed:
            self._event(0.0, 0, "resume", {"v_ref_V": self.resumed})

    def close(self) -> None:
        self._stop.set()
        if self.recorder is not None:
            self.recorder.close()
        if self.session is not None:
            try:
                if self.token is not None:
                    self.token.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
            close_session(self.session)
            for t in self._threads:
                t.join(timeout=0.5)
            self.session = None

    def stop(self) -> None:
        self._stop.set()

    # ---------------------------------------------------------------- the loop
    def run(self, max_samples: int | None = None) -> None:
        """The loop thread: grid samples and connect requests until stop; an unexpected exception (or another
        thread's failure, which stops it) ends it in the safe state (the module docstring)."""
        try:
            self._loop(max_samples)
        except Exception as e:  # noqa: BLE001 - the layer in an unknown state: it fails, visibly
            self.failure.record("loop", e)
        finally:
            if self.failure:
                self._safe_state()

    def _loop(self, max_samples: int | None) -> None:
        q, stop = self.grid_q, self._stop
        while not stop.is_set():
            self._poll_alive()
            self._take_connects()
            try:
                _, payload = q.get(timeout=0.005)
            except Empty:
                continue
            self.grid(payload)
            self._take_connects()
            if max_samples is not None and self.counters["grid_samples"] >= max_samples:
                break

    def _safe_state(self) -> None:
        """No window message after the failure (the loop has ended): the sources keep the last window's v_ref; the
        token withdrawn, so that they (and an operator) see the coordinator gone at once."""
        self._stop.set()
        try:
            if self.token is not None:
                self.token.undeclare()
                self.token = None
        except Exception:  # noqa: BLE001 - a closed session: nothing more to withdraw
            pass
        self._event(self.t, self.seq, "failed", {"failure": self.failure.reason})

    def grid(self, payload: bytes) -> None:
        """One grid sample: the sharing for the record, the window sums, a window message when the breakers changed
        or a window ends."""
        try:
            seq, t, v, i_out, connected, bus_v, load_P = GRID.decode(payload)
        except DecodeError as e:
            self._reject(f"grid.{e.field}: invalid ({e.reason})")
            return
        sizes = (len(v), len(bus_v), len(load_P))
        if sizes != self.sizes:
            self._reject(f"grid: {sizes[0]} sources, {sizes[1]} buses, {sizes[2]} loads; the scenario has "
                         f"{self.sizes[0]}, {self.sizes[1]}, {self.sizes[2]}")
            return
        T = self.layer.T
        if abs(t - seq * T) > 0.5 * T:
            self._reject(f"grid.t: {t!r} s is not seq x T ({seq} x {T:g} s)")
            return
        bad = self._implausible(v, i_out, bus_v, load_P)
        if bad:
            self._reject(bad)
            return
        if seq <= self.seq:
            self._behind += 1
            if seq != 0 and self._behind < self.layer.per_window:
                self._reject(f"grid.seq: {seq} not after {self.seq}")
                return
            # the rig restarted (seq 0), or a window of samples all behind one that came from nowhere: a new run
            self.counters["restarts"] += 1
            self.layer = InterconnectionLayer(self.net, self.layer.loads)
            self.seq = -1
            self._offers.clear()  # made in the run that ended
        elif self.seq >= 0 and seq > self.seq + self.layer.per_window and seq != self._jump + 1:
            # more than a window ahead: taken when the next sample follows it (a rig seen again after an outage),
            # not from one alone (a stray sender's would stop every window message until the rig's caught up)
            self._jump = seq
            self._reject(f"grid.seq: {seq} is {seq - self.seq} samples after {self.seq}; taken if the next follows")
            return
        elif self.seq >= 0 and seq > self.seq + 1:
            self.counters["missing_samples"] += seq - self.seq - 1
        self._behind = 0
        layer, ns = self.layer, self.ns
        topology = connected != self.connected or self.seq < 0
        self.seq, self.t, self.connected = seq, t, connected
        self.counters["grid_samples"] += 1
        if topology and layer.active:
            self.window = seq // layer.per_window
            self.zin = layer.ranges(self.window, connected)
        P = [v[j] * i_out[j] if connected[j] else 0.0 for j in range(ns)]
        want, rate = layer.allocate(seq, P, connected)
        if not all(map(isfinite, want)) or not all(map(isfinite, rate)):  # a backstop: never send these
            layer.want_rate[:] = [0.0] * ns
            layer.want_prev[:] = [0.0] * ns
            self._reject("grid: the allocation came out not finite")
            return
        for j, name in enumerate(self.names):  # a closed breaker whose controller is gone: trip it (again)
            if not connected[j]:
                self._tripping.discard(name)
            elif self.alive[name] is False and self.cfg.trip_on_loss and name not in self._tripping:
                self._trip(name)
        self.want[:] = want  # (the layer's list, updated in place at its next step)
        if topology:  # the range for the new breakers, from this sample on (a lockstep source waits for it)
            self._send_window(seq, t)
        rec = self.recorder
        if rec is not None:
            v_ref = layer.v_ref
            for j in range(ns):
                rec.offer(self.t_src[j], t, (seq, t, v[j], i_out[j], connected[j], want[j], rate[j], v_ref[j]))
            rec.offer(self.t_tick, t, (seq, t, sum(bus_v) / len(bus_v) if bus_v else 0.0, sum(load_P),
                                       bool(bus_v)))
        # with idle_power_W = 0 a connected source is active (it idles only while disconnected)
        win_k, moves = layer.step(seq, (v, i_out, connected, bus_v, load_P), [True] * ns, list(connected), P)
        if win_k is not None:
            self.window = win_k
            if layer.active:
                self.zin = layer.ranges(win_k, connected)
            self._send_window(seq + 1, t)  # the next window's v_ref and range, before its first sample

    def _send_window(self, seq: int, t: float) -> None:
        """Each source's LayerWindow from sample seq on: its alpha_s, v_ref, breaker and Z^{r,in} for the window."""
        w, zin, v_ref, connected = self.window, self.zin, self.layer.v_ref, self.connected
        alpha = self.layer.sharing.alpha(connected)
        rec = self.recorder
        for j in range(self.ns):
            z = zin[j]
            m = (seq, t, w, alpha[j], v_ref[j], connected[j], z is not None, *(z if z is not None else _NO_RANGE))
            self.pubs[j].put(WINDOW.encode(*m))
            if rec is not None:  # what was sent, for the replay (values only, as the other offers)
                rec.offer(self.t_win[j], t, m)
        self.counters["windows_sent"] += 1

    # ---------------------------------------------------------------- plug-in and trips
    def _take_connects(self) -> None:
        """Answer the connect requests that are due: in lockstep one for sample k once sample k - 1 is done."""
        lockstep = self.cfg.lockstep
        held = []
        try:
            while True:
                try:
                    query, body = self._connects.get_nowait()
                except Empty:
                    break
                at = body.get("at_seq")
                if lockstep and at is not None and self.seq < at - 1:
                    held.append((query, body))
                    continue
                self._connect(query, body)
        finally:  # a request that broke _connect must not take the waiting ones with it
            for item in held:
                self._connects.put(item)

    def _connect(self, query, body: dict) -> None:
        try:
            self._connect_checked(query, body)
        except Exception as e:  # noqa: BLE001 - whatever a request does, it gets an answer and the loop goes on
            self.last_reject = f"connect: {type(e).__name__}: {e}"[:300]
            self._answer(query, False, {"error": self.last_reject})

    def _connect_checked(self, query, body: dict) -> None:
        c = self.cfg
        self.counters["connect_requests"] += 1
        try:
            name = body.get("source")
            if name not in self.names:
                raise ValueError(f"source: {name!r} is not a source of {self.net.name!r}")
            s = self.names.index(name)
            controller = ControllerConfig.model_validate(body.get("controller") or {})
            announced = None if body.get("Z_out") is None else announced_z_out(body)
        except (ValueError, TypeError, OverflowError) as e:
            self._answer(query, False, {"error": str(e)})
            return
        at = body.get("at_seq")
        k = at if isinstance(at, int) else self.seq + 1
        window = k // self.layer.per_window
        if self.connected[s]:
            reply = {"accepted": True, "reason": "already connected", "window": window}
            self._answer(query, True, reply)
            return
        if self.alive.get(name) is not True:  # (its request may come before its token: it asks again)
            reply = {"source": name, "accepted": False, "window": window, "at_seq": at,
                     "reason": f"{name}: its controller's liveliness token is not up"}
            self.counters["refused"] += 1
            self.verdicts.append({"t": self.t, "seq": self.seq, **reply})
            self._event(self.t, k, "connect", {**reply, "checked": False})  # refused before the layer's check
            self._answer(query, True, reply)
            return
        # the v_ref the layer holds for it (it may have moved it at the end of sample k - 1)
        controller = controller.model_copy(update={"v_ref_V": self.layer.v_ref[s]})
        if body.get("offer"):  # the handshake's first step: what it would be asked for, to forecast against
            box, tau_p = self.layer.connect_offer(s, window, self.connected)
            self._offers[name] = (window, box, tau_p, tuple(self.connected))  # its announcement is judged on this
            # logged at the sample it was computed before (the layer as after self.seq): replay recomputes it there
            self._event(self.t, self.seq + 1, "offer", {"source": name, "window": window, "at_seq": at,
                                                        "box": list(box), "tau_prime_s": tau_p,
                                                        "v_ref_V": self.layer.v_ref[s],
                                                        "connected": list(self.connected)})
            self._answer(query, True, {"source": name, "offer": True, "window": window, "at_seq": at,
                                       "box": list(box), "tau_prime_s": tau_p, "v_ref_V": self.layer.v_ref[s],
                                       "window_s": self.layer.cfg.window_s})
            return
        if announced is not None:  # its own forecast Z^{r,out}, checked against the Z^{r,in} of the offer it had
            P_out, Qdot_out, saturation = announced
            offer = self._offers.pop(name, None)
            stale = offer_staleness(None if offer is None else (offer[0], offer[3]), window, self.connected)
            if stale:
                offer = (window, *self.layer.connect_offer(s, window, self.connected))
                reason, z_in = stale, incoming_range(*offer[1], offer[2])
            else:
                reason, z_in = judge_announced(offer[1], offer[2], P_out, Qdot_out, saturation)
            reply = {"source": name, "accepted": reason == "", "reason": reason, "window": offer[0], "at_seq": at,
                     "Z_out": {"P": list(P_out), "Qdot": list(Qdot_out)}, "saturation": saturation,
                     "Z_in": {"P": list(z_in[:2]), "Qdot": list(z_in[2:])}, "announced": True,
                     "offer": {"box": list(offer[1]), "tau_prime_s": offer[2]}}
        else:  # no forecast of its own: none is run for it here (that would take the loop thread 30-350 ms)
            self._answer(query, False, {"error": "Z_out: announce the Z^{r,out} you forecast for an offer (ask with "
                                                 "\"offer\": true first)"})
            return
        if reply["accepted"]:
            ok, r = request(self.session, key(c.prefix, c.rig, "breaker"),
                            {"target": name, "closed": True, "at_seq": at, "by": c.id}, 5.0)
            if not ok:
                reply.update(accepted=False, reason=f"the rig did not close the breaker: {r.get('error', r)}")
        self.counters["accepted" if reply["accepted"] else "refused"] += 1
        self.verdicts.append({"t": self.t, "seq": self.seq, **reply})
        self._event(self.t, k, "connect", {**reply, "controller": controller.model_dump(),
                                          "connected": list(self.connected), "loss_frac": self.layer.loss_frac})
        self._answer(query, True, reply)

    def _poll_alive(self) -> None:
        """The liveliness tokens. The rig's first: while it is gone this coordinator may itself be cut off (its
        router restarting, its link down), and a token seen going then says nothing about its source; those
        become unknown (None), never a trip. When the rig's token is back, one liveliness query says who is up."""
        events = []
        while (tok := self.alive_sub.try_recv()) is not None:
            parts = str(tok.key_expr).split("/")
            events.append((parts[-2] if len(parts) >= 2 else "", tok.kind == zenoh.SampleKind.PUT))
        for name, up in events:
            if name == self.cfg.rig:
                if not up:
                    for n in self.alive:
                        self.alive[n] = None
                elif self.rig_alive is False:
                    self._recheck_alive()
                self.rig_alive = up
        while not self._alive_checked.empty():  # the re-check's answer: who holds a token now
            up_now = self._alive_checked.get_nowait()
            for n in self.alive:
                if self.alive[n] is None:
                    self.alive[n] = n in up_now
        for name, up in events:
            if name not in self.alive:
                continue
            if self.rig_alive is False:
                self.alive[name] = True if up else None
                continue
            was = self.alive[name]
            self.alive[name] = up
            if not up and was is not False and self.cfg.trip_on_loss and self.connected[self.names.index(name)] \
                    and name not in self._tripping:
                self._trip(name)

    def _recheck_alive(self) -> None:
        """Ask who holds a token (a thread; the answer comes back through a queue to the loop)."""
        c = self.cfg

        def ask() -> None:
            up = set()
            try:
                for r in self.session.liveliness().get(key(c.prefix, "*", "alive"), timeout=1.0):
                    if r.ok is not None:
                        parts = str(r.ok.key_expr).split("/")
                        up.add(parts[-2] if len(parts) >= 2 else "")
            except Exception:  # noqa: BLE001 - closing: nothing to report
                return
            self._alive_checked.put(up)

        guarded(self.failure, "recheck-alive", ask, on_failure=self.stop).start()

    def _trip(self, name: str) -> None:
        """Its daemon is gone: the rig opens its breaker (a thread: the loop keeps allocating meanwhile)."""
        c = self.cfg
        self.counters["trips"] += 1
        t, seq = self.t, self.seq
        self._tripping.add(name)

        def ask() -> None:
            ok, r = False, {"error": "not asked"}
            try:
                ok, r = request(self.session, key(c.prefix, c.rig, "breaker"),
                                {"target": name, "closed": False, "at_seq": None, "by": c.id}, 5.0)
            finally:
                if not ok:  # asked again at the next sample that still shows it closed; else when a sample shows it
                    self._tripping.discard(name)  # open (grid)
            item = {"t": t, "seq": seq, "source": name, "reason": "liveliness token lost", "rig_ok": ok,
                    "applied_at_seq": r.get("at_seq") if ok else None, "error": "" if ok else r.get("error", "")}
            self.trips.append(item)
            self._event(t, seq, "trip", item)
            how = "the rig opened its breaker" if ok else "the rig did not answer: " + item["error"]
            print(f"energyctl coordinator: {name} lost its liveliness at t = {t:.4f} s: tripped ({how})",
                  file=sys.stderr, flush=True)

        guarded(self.failure, f"trip-{name}", ask, on_failure=self.stop).start()

    # ---------------------------------------------------------------- queries (their own threads)
    def _serve(self, leaf: str) -> None:
        own = key(self.cfg.prefix, self.cfg.id, leaf)

        def handle(query):
            if leaf != "connect":
                return True, self.status()
            raw = query.payload.to_bytes() if query.payload is not None else b"{}"
            if len(raw) > MAX_REQUEST_BYTES:
                raise ValueError(f"{len(raw)} bytes, more than {MAX_REQUEST_BYTES}")
            body = json.loads(raw)
            if not isinstance(body, dict):
                raise ValueError("expected a JSON object {\"source\", \"controller\", \"at_seq\"}")
            at = body.get("at_seq")
            if at is not None and (type(at) is not int or at < 0):
                raise ValueError(f"at_seq: expected a sample number or null, got {at!r}")
            if at is not None and at > self.seq + 2 * self.layer.per_window + 1 and self.seq >= 0:
                raise ValueError(f"at_seq: {at} is more than two windows ahead of sample {self.seq}")
            self._connects.put((query, body))  # the loop thread answers (and drops) it
            return None

        def refused(e: Exception) -> str:
            self._reject(f"{leaf}: {type(e).__name__}: {e}"[:300])
            return f"{leaf}: {e}"[:300]

        serve_queries(self.queryables[leaf], own, handle, refused)

    def _answer(self, query, ok: bool, body: dict) -> None:
        answer(query, ok, body, key(self.cfg.prefix, self.cfg.id, "connect"))

    def status(self) -> dict:
        layer, net, zin, connected = self.layer, self.net, list(self.zin), list(self.connected)
        weight = sum(sh for sh, c in zip(layer.shares, connected, strict=True) if c) or 1.0
        return {
            "id": self.cfg.id, "state": "failed" if self.failure else "active", "failure": self.failure.reason,
            "network": net.name, "seq": self.seq, "t": self.t, "window": self.window,
            "window_s": net.layer.window_s, "mode": net.layer.mode, "loss_frac": layer.loss_frac,
            "sources": {name: {"share": layer.shares[j], "share_now": layer.shares[j] / weight if connected[j]
                               else 0.0, "connected": connected[j], "alive": self.alive[name],
                               "P_r_in": self.want[j], "v_ref_V": layer.v_ref[j],
                               "Z_in": list(zin[j]) if zin[j] is not None else None,
                               "not_connected": None if connected[j] else self._why_not_connected(name)}
                        for j, name in enumerate(self.names)},
            "verdicts": list(self.verdicts), "trips": list(self.trips), "resumed_v_ref": self.resumed,
            "counters": dict(self.counters), "last_reject": self.last_reject,
            "logging": None if self.recorder is None else {"path": self.log_path, "written": self.recorder.written,
                                                           "drops": dict(self.recorder.drops)},
        }

    # ---------------------------------------------------------------- helpers
    def _why_not_connected(self, name: str) -> str:
        """Why a source's breaker is open, from what this coordinator saw last: a trip, a refused request, or none."""
        trip = next((t for t in reversed(list(self.trips)) if t["source"] == name), None)
        verdict = next((v for v in reversed(list(self.verdicts)) if v["source"] == name), None)
        if verdict is not None and (trip is None or verdict["t"] >= trip["t"]) and not verdict.get("accepted"):
            return f"its last connect request (t = {verdict['t']:.3f} s) was refused: {verdict.get('reason', '')}"
        if trip is not None:
            return (f"tripped at t = {trip['t']:.3f} s ({trip['reason']}); its daemon has not asked to connect since "
                    "(it asks by itself once restarted, or with --connect-at)")
        if self.alive.get(name) is not True:
            return "no daemon holds its liveliness token"
        return "open; its daemon has not asked to connect"

    def _reject(self, text: str) -> None:
        with self._lock:  # the loop thread and the query threads
            self.counters["rejected"] += 1
            self.last_reject = text

    def _event(self, t: float, seq: int, kind: str, detail: dict) -> None:
        if self.recorder is not None:
            self.recorder.offer(self.t_ev, t, (t, max(seq, 0), kind, json.dumps(detail)))


def _finite_number(x) -> bool:
    """An int or float (not a bool) that is finite as a float (a 400-digit int is not: float() overflows)."""
    if not isinstance(x, int | float) or isinstance(x, bool):
        return False
    try:
        return isfinite(float(x))
    except OverflowError:
        return False


def announced_z_out(body: dict) -> tuple[tuple[float, float], tuple[float, float], str]:
    """A connect request's announced Z^{r,out}: ((P lo, P hi) W, (Qdot lo, Qdot hi) W/s, the saturation its
    forecast met); ValueError naming the field that is not two finite numbers in order, or not text."""
    z = body.get("Z_out")
    if not isinstance(z, dict):
        raise ValueError("Z_out: expected an object {\"P\": [lo, hi], \"Qdot\": [lo, hi]}")
    out = []
    for part in ("P", "Qdot"):
        v = z.get(part)
        if not (isinstance(v, list) and len(v) == 2 and all(_finite_number(x) for x in v) and v[0] <= v[1]):
            raise ValueError(f"Z_out.{part}: expected [lo, hi], two finite numbers, lo <= hi (got {v!r:.80})")
        out.append((float(v[0]), float(v[1])))
    saturation = body.get("saturation", "")
    if not isinstance(saturation, str) or len(saturation) > 500:
        raise ValueError("saturation: expected text (what the forecast met, \"\" for nothing)")
    return out[0], out[1], saturation


def run_coordinator(cfg: CoordinatorConfig, net: NetworkScenario, stop: threading.Event, impl: str = "auto",
                    log=sys.stderr) -> dict:
    """Open, run until stop (or until the loop ends by itself: a failure), close; the final status."""
    co = Coordinator(cfg, net, impl)
    co.open()
    loop = threading.Thread(target=co.run, name="loop", daemon=True)
    loop.start()
    print(f"energyctl coordinator: {cfg.id} for {net.name!r} ({len(co.names)} sources, window "
          f"{net.layer.window_s:g} s, {'lockstep' if cfg.lockstep else 'newest sample'})"
          + (f", resumed v_ref from {sorted(co.resumed)}" if co.resumed else ""), file=log, flush=True)
    while not stop.is_set() and loop.is_alive():
        stop.wait(0.05)
    died = not stop.is_set()  # the loop ended by itself: a failure, whatever the status says
    if died:
        print(f"energyctl coordinator: {cfg.id} failed, no more window messages: "
              f"{co.failure.reason or 'its loop ended by itself'}", file=log, flush=True)
    co.stop()
    loop.join(timeout=6.0)  # a plug-in check under way asks the rig with a 5 s timeout
    status = co.status()
    status["loop_ended_by_itself"] = died
    co.close()
    return status
