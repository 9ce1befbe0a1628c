"""Hardware-in-the-loop stand-in of a whole network (energyctl plant --config NETWORK.toml).

The plant side of the offline network (service.network.netrig.NetworkRigModel: the network plant, each source's sensor,
loop delay and command schedule, the scenario's breaker events, the layer's bus measurements) behind Zenoh. Per
sample k it publishes, in this order, each line end's interaction variable (PREFIX/LINE/z/NODE), each load's
(PREFIX/LOAD/z), the layer's grid sample (PREFIX/RIG/grid) and each source's measurement (PREFIX/SOURCE/meas); it
takes each source's command from PREFIX/SOURCE/cmd and breaker commands from the query PREFIX/RIG/breaker
(``{"target", "closed", "at_seq"}``: a source's lines or one line, from sample at_seq, or the next sample).

* lockstep: sample k + 1 after every live source (its liveliness token up) answered sample k, or
  ``lockstep_timeout_s`` passed (counted; that source is not waited for again until it catches up). Its own
  disconnection is not every source leaving: when the tokens of every peer it saw up are gone at once, or its
  session has no router or peer left (its router restarting, its link down), it is cut off (counted in
  ``cut_off``): it takes no sample and steps nothing until those tokens are back, then sends the sample they may
  have missed again and goes on; cut off longer than ``wait_s`` it fails (exit 1). Realtime pacing runs on the wall
  clock through such an outage (the sources' commands are then missing, as they are);
* realtime: samples on the wall clock; the command answering sample k acts over period k + d (d the scenario's
  loop delay), else its predecessor's plan, else u is held.

Should its sampling or its breaker thread end by an exception nobody expected, it stops sampling (the daemons see
their measurements stop and hold), reports ``state: failed`` with the reason (service.daemon.failure), still writes
its log, and ``energyctl plant`` exits 1. A run that ends with the network diverged exits 1 as well.

At the end it writes its log (``out``) in the layout of ``energyctl sim NETWORK --out`` for the plant: each source's,
bus's and line's true state under PREFIX/NETWORK/ELEMENT/plant, the breaker events under PREFIX/NETWORK/layer/events,
in lockstep each source's answer to each sample under PREFIX/NETWORK/SOURCE/cmd (as ``energyctl sim --out`` logs
its controllers' answers: a lockstep run is checked against the offline one command for command),
the scenario and the metrics as metadata; ``energyctl report`` draws it and ``network_metrics`` recomputes from it.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from array import array
from queue import Empty

import numpy as np
import zenoh

from clients.machine import ProcessCpu
from clients.peers.common import matched, wait_alive
from schemas.codec import CMD, GRID, MEAS, DecodeError, Z
from schemas.netlive import NetworkRigConfig
from schemas.network import NetworkScenario
from service.daemon.bus import close_session, key, open_session, publisher, queued
from service.daemon.failure import Failure, guarded
from service.metrics import acceptance_checks, network_metrics
from service.network.netrig import NetworkRigModel
from service.network.netsim import Event, NetworkResult

_NO_ANSWER = (float("nan"), float("nan"))  # a lockstep sample a source did not answer, in the command log
CUT_WINDOW_S = 2.0  # sources whose tokens went this long before the rig found itself cut off went with the cut


class NetworkRig:
    """One run of the network stand-in (see the module docstring): ``run()`` returns metrics and counters."""

    def __init__(self, cfg: NetworkRigConfig, net: NetworkScenario, stop: threading.Event, impl: str = "auto",
                 log=sys.stderr):
        self.cfg, self.net, self.stop, self.log = cfg, net, stop, log
        self.lockstep = cfg.pacing == "lockstep"
        self.model = NetworkRigModel(net, impl, realtime=not self.lockstep)
        self.names = list(net.sources)
        self.N = self.model.N
        self.pending: list[tuple[int | None, str, bool, str]] = []  # breaker commands: (at_seq, target, closed, by)
        self.lock = threading.Lock()
        self.events: list[Event] = []
        self.counters = {"samples": 0, "commands": 0, "timeouts": 0, "rejected": 0, "late": 0, "breaker_commands": 0,
                         "missed": 0, "cut_off": 0, "resent": 0}
        # realtime: per source, how many commands came 0, 1, ... samples after the one they answer (the last bin: older)
        self.age_hist = {name: [0] * (2 * self.model.d + 3) for name in self.names}
        self.alive: dict[str, bool | None] = dict.fromkeys(self.names)
        self.lagging: set[str] = set()
        self.answered = {name: -1 for name in self.names}
        # every other process's token seen up (the sources', the coordinator's, ...), and when a source's went
        self.peers_up: set[str] = set()
        self._lost_at: dict[str, float] = {}  # monotonic s when each token went last
        self._awaited: set[str] = set()  # cut off: the processes whose tokens went with the cut
        self._resent_k = -1  # the last sample resent after a cut
        self.cut_off_since: float | None = None  # monotonic s: its own session lost the others (module docstring)
        self.cut_off_s = 0.0  # wall time spent cut off, all outages
        self._frames: tuple = (b"", [])  # the last sample's grid and measurement frames (resent after a cut)
        self.diverged_at: float | None = None
        self.failure = Failure(f"energyctl plant[{cfg.id}]")
        self.cpu = None
        ns, nb, nl = len(self.names), len(net.buses), len(net.lines)
        self._rows = array("d")  # per tick: t, per source (i, v, u, i_out, P, du_dt), per bus v, per line i
        self._width = 1 + 6 * ns + nb + nl
        # lockstep: per tick, per source the answer to that sample (du/dt, planned du/dt V/s; NaN: none came), as
        # offline's cmd_du/cmd_du_next, logged under SOURCE/cmd so a run can be checked command for command
        self._cmds = array("d")

    # ---------------------------------------------------------------- the run
    def run(self) -> dict:
        session = open_session(self.cfg.zenoh)
        try:
            self.connect(session)
            try:
                self.sample()
            except Exception as e:  # noqa: BLE001 - the run ends here, visibly, with what it has (result)
                self.failure.record("sample", e)
        finally:
            close_session(session)  # a close timing out on a stopped peer is not this run's failure
        return self.result()

    def connect(self, session) -> None:
        cfg, c, net = self.cfg, self.cfg, self.net
        p = c.prefix
        self.session = session
        self.meas_pubs = [publisher(session, key(p, name, "meas")) for name in self.names]
        self.grid_pub = publisher(session, key(p, cfg.id, "grid"))
        self.line_pubs = [publisher(session, f"{p}/{ln}/z/{node}") for ln, node, _ in self.model.line_ends()]
        self.load_pubs = [publisher(session, key(p, ld, "z")) for ld in net.loads]
        self.cmd = {name: queued(session, key(p, name, "cmd")) for name in self.names}
        self.alive_sub = session.liveliness().declare_subscriber(key(p, "*", "alive"), zenoh.handlers.FifoChannel(256),
                                                                 history=True)
        self.breaker_q = session.declare_queryable(key(p, cfg.id, "breaker"), zenoh.handlers.FifoChannel(64))
        self._breaker_thread = guarded(self.failure, "breaker", self._serve_breaker)  # its failure ends the sampling
        self._breaker_thread.start()
        self.token = session.liveliness().declare_token(key(p, cfg.id, "alive"))
        wait = [*cfg.wait_for, *[n for n, s in net.sources.items() if s.connected or self._asks(n)]]
        for peer in dict.fromkeys(wait):
            if not wait_alive(session, key(p, peer, "alive"), cfg.wait_s, self.stop):
                raise RuntimeError(f"{peer!r} not alive on the bus within {cfg.wait_s:g} s")
            if peer in self.alive:  # seen: waited for from sample 0 on (the token subscriber may tell later)
                self.alive[peer] = True
            self.peers_up.add(peer)
        for name, pub in zip(self.names, self.meas_pubs, strict=True):
            if (net.sources[name].connected or self._asks(name)) and not matched(pub, cfg.wait_s, self.stop):
                raise RuntimeError(f"no subscriber for {key(p, name, 'meas')} within {cfg.wait_s:g} s")
        if not matched(self.grid_pub, cfg.wait_s, self.stop) and "coordinator" in cfg.wait_for:
            raise RuntimeError(f"no subscriber for {key(p, cfg.id, 'grid')} within {cfg.wait_s:g} s")

    def _asks(self, name: str) -> bool:
        """A scenario source that starts disconnected but has a connect event: its daemon runs from the start."""
        return any(e.kind == "connect" and e.target == name for e in self.net.events)

    def sample(self) -> None:
        cfg, model = self.cfg, self.model
        plant, T, N = model.plant, model.T, self.N
        ns = len(self.names)
        period_ns = int(round(T * 1e9))
        spin_ns = int(cfg.realtime_spin_us * 1e3)
        now_ns = time.monotonic_ns
        rows, stop = self._rows, self.stop
        z_every = max(1, round(self.net.timing.control_rate_hz / cfg.interaction_rate_hz))
        # every process up and subscribed: the run starts (a line to wait on: clients.nethosts measures from here)
        print(f"energyctl plant: sampling, {N} samples ({cfg.pacing})", file=self.log, flush=True)
        self.cpu = ProcessCpu().start()
        t_wall0 = time.perf_counter()
        next_ns = now_ns() + period_ns
        for k in range(N):
            if stop.is_set() or self.failure:
                break
            if not self.lockstep:
                left = next_ns - now_ns()
                if left > spin_ns:
                    time.sleep((left - spin_ns) * 1e-9)
                while now_ns() < next_ns:
                    pass
                next_ns += period_ns
            self._poll_alive()
            due = model.begin(k, kinds=("trip", "close"))
            t = plant.t
            for ev in due:
                self.events.append(Event(t, ev.kind, ev.target, True, "scenario"))
            self._apply_breakers(k, t)
            samples = model.sample(k)
            connected = model.connected()
            if k % z_every == 0:  # the lines' and loads' interaction variables: for the daemons' status and logs
                for pub, (_, _, P) in zip(self.line_pubs, model.line_ends(), strict=True):
                    pub.put(Z.encode(k, t, P, 0.0, 0.0, 0.0, 0.0, 0, P, P, 0.0, 0.0))
                for q, pub in enumerate(self.load_pubs):
                    P = plant.load_power(q, t)
                    pub.put(Z.encode(k, t, P, 0.0, 0.0, 0.0, 0.0, 0, P, P, 0.0, 0.0))
            grid = GRID.encode(k, t, [s.v for s in samples], [s.i_load for s in samples], connected,
                               model.bus_measurements(), model.load_powers())
            meas = [MEAS.encode(k, t, s.i, s.v, s.u, s.i_load) for s in samples]
            if self.lockstep:
                if self.cut_off_since is not None:  # cut off before this sample went out: back first
                    self._ride_out_cut(k, resend=False)
                self._frames = (grid, meas)
            self.grid_pub.put(grid)
            for pub, m in zip(self.meas_pubs, meas, strict=True):
                pub.put(m)
            self.counters["samples"] += 1
            if self.lockstep:
                answers = self._await(k)
                r = [model.command(j, k, *(answers[j] if answers[j] is not None else (None, 0.0)))
                     for j in range(ns)]
                for a in answers:
                    self._cmds.extend(a if a is not None else _NO_ANSWER)
            else:
                if k == 0:
                    # arm: the converters are enabled by the sources' first answers, and the sampling clock starts
                    # then (as the single source's rig: the stack's first round trips are slow while it warms up)
                    for j, a in enumerate(self._await(0)):
                        if a is not None:
                            model.arrive(j, 0, *a)
                    next_ns = now_ns() + period_ns
                self._drain(k)
                r = [model.take(j, k) for j in range(ns)]
            rows.append(t)
            for j in range(ns):
                s = samples[j]
                rows.extend((plant.i_s[j], plant.v_n[j], plant.u_s[j], plant.terminal_current(j),
                             s.v * s.i_load if connected[j] else 0.0, r[j]))
            for bi in model.bus_idx:
                rows.append(plant.v_n[bi])
            rows.extend(plant.i_l)
            model.advance()
            if self.diverged_at is None and model.diverged():
                self.diverged_at = plant.t
                print(f"energyctl plant: the network diverged at t = {plant.t:.4f} s", file=self.log, flush=True)
                break
        self.wall_s = time.perf_counter() - t_wall0
        self.cpu.stop()

    # ---------------------------------------------------------------- commands
    def _poll_alive(self) -> None:
        gone = False
        while (tok := self.alive_sub.try_recv()) is not None:
            parts = str(tok.key_expr).split("/")
            if len(parts) < 2 or parts[-2] == self.cfg.id:
                continue
            name, up = parts[-2], tok.kind == zenoh.SampleKind.PUT
            if up:
                self.peers_up.add(name)
            else:
                gone = gone or name in self.peers_up
                self.peers_up.discard(name)
                self._lost_at[name] = time.monotonic()
                if self.cut_off_since is not None:
                    self._awaited.add(name)
            if name in self.alive:  # while cut off, a source's token going says nothing: unknown, waited for
                self.alive[name] = True if up else (None if self.cut_off_since is not None else False)
        if gone and self.lockstep and self.cut_off_since is None and (not self.peers_up or self._no_links()):
            self._cut_off()

    def _no_links(self) -> bool:
        """Its session has no router and no peer left (asked only when a token went: rare)."""
        try:
            info = self.session.info
            return not info.routers_zid() and not info.peers_zid()
        except Exception:  # noqa: BLE001 - a closing session: as good as none
            return True

    def _cut_off(self) -> None:
        """Every peer's token went at once, or its session lost every link: it is cut off, not they gone. The
        processes whose tokens went with it (within CUT_WINDOW_S) are waited for; its sources among them become
        unknown (None), not gone."""
        now = time.monotonic()
        self.cut_off_since = now
        self.counters["cut_off"] += 1
        self._awaited = {n for n, at in self._lost_at.items() if now - at <= CUT_WINDOW_S}
        for name in self._awaited & set(self.alive):
            self.alive[name] = None
        print(f"energyctl plant: cut off from the other processes at sample {self.counters['samples']} (every "
              f"token gone at once, or no link left): waiting up to {self.cfg.wait_s:g} s for "
              f"{', '.join(sorted(self._awaited))}", file=self.log, flush=True)

    def _ride_out_cut(self, k: int, resend: bool) -> None:
        """Lockstep, cut off: wait until every process whose token went with the cut is back; then, with ``resend``,
        send sample k's frames again (they may have gone nowhere). Cut off longer than wait_s: it fails."""
        t0 = self.cut_off_since
        deadline = t0 + self.cfg.wait_s
        while True:
            self._poll_alive()
            waiting = self._awaited - self.peers_up
            if not waiting and not self._no_links():
                break
            if self.stop.is_set() or self.failure:
                return
            if time.monotonic() > deadline:
                raise RuntimeError(f"cut off from the bus for {self.cfg.wait_s:g} s at sample {k}: "
                                   f"{', '.join(sorted(waiting)) or 'no link'} not back")
            time.sleep(0.01)
        # the tokens can be back before the subscriptions are routed again: a frame put before then goes nowhere
        for name, pub in zip(self.names, self.meas_pubs, strict=True):
            if name in self._awaited and not matched(pub, max(0.0, deadline - time.monotonic()), self.stop):
                raise RuntimeError(f"cut off: {name}'s token is back but nothing subscribes to its measurements")
        self.cut_off_s += time.monotonic() - t0
        self.cut_off_since = None
        print(f"energyctl plant: back on the bus after {time.monotonic() - t0:.2f} s, at sample {k}", file=self.log,
              flush=True)
        if resend:
            grid, meas = self._frames
            self.grid_pub.put(grid)
            for name, pub, m in zip(self.names, self.meas_pubs, meas, strict=True):
                if self.answered[name] < k:
                    pub.put(m)
            self.counters["resent"] += 1
            self._resent_k = k

    def _decode(self, name: str, payload: bytes) -> tuple | None:
        try:
            c = CMD.decode(payload)
        except DecodeError:
            with self.lock:
                self.counters["rejected"] += 1
            return None
        self.counters["commands"] += 1
        self.answered[name] = max(self.answered[name], c[0])
        return c

    def _await(self, k: int) -> list[tuple | None]:
        """Lockstep: each source's answer to sample k (None: not live, or no answer within the timeout)."""
        out: list[tuple | None] = []
        deadline = time.monotonic() + self.cfg.lockstep_timeout_s
        for name in self.names:
            _, q = self.cmd[name]
            got = None
            while True:
                if self.stop.is_set() or self.failure:
                    break
                if self.cut_off_since is not None:  # its own outage, not theirs: wait it out, resend, wait anew
                    self._ride_out_cut(k, resend=True)
                    deadline = time.monotonic() + self.cfg.lockstep_timeout_s
                    continue
                if self.alive[name] is not True and q.empty():
                    self._poll_alive()
                    if self.cut_off_since is not None:
                        continue
                    if self.alive[name] is not True:
                        break  # not running (or gone): nothing to wait for
                if name in self.lagging and q.empty():
                    break
                try:
                    _, payload = q.get(timeout=max(1e-4, min(0.05, deadline - time.monotonic())))
                except Empty:
                    self._poll_alive()
                    if self.cut_off_since is not None:
                        continue
                    if time.monotonic() >= deadline:
                        self.counters["timeouts"] += 1
                        if k != self._resent_k:  # a resent sample it had answered into the cut: no answer comes,
                            self.lagging.add(name)  # and it is not behind (a lagging source is not waited for)
                        break
                    continue
                c = self._decode(name, payload)
                if c is None:
                    continue
                if c[0] == k:
                    got = (c[2], c[3])
                    self.lagging.discard(name)
                    break
                if c[0] > k:  # cannot happen in lockstep; counted and dropped
                    self.counters["late"] += 1
            out.append(got)
        return out

    def _drain(self, k: int) -> None:
        """Realtime: every command that came, onto its source's schedule; its age (k - the sample it answers:
        in time for its period while <= the loop delay) into the source's histogram."""
        top = len(self.age_hist[self.names[0]]) - 1
        for j, name in enumerate(self.names):
            hist = self.age_hist[name]
            _, q = self.cmd[name]
            while True:
                try:
                    _, payload = q.get_nowait()
                except Empty:
                    break
                c = self._decode(name, payload)
                if c is not None:
                    self.model.arrive(j, c[0], c[2], c[3])
                    hist[min(max(k - c[0], 0), top)] += 1

    # ---------------------------------------------------------------- breakers
    def _serve_breaker(self) -> None:
        while True:
            try:
                query = self.breaker_q.recv()
            except Exception:  # noqa: BLE001 - closed at shutdown
                return
            try:
                raw = query.payload.to_bytes() if query.payload is not None else b"{}"
                if len(raw) > 64 * 1024:
                    raise ValueError(f"{len(raw)} bytes: too long")
                body = json.loads(raw)
                if not isinstance(body, dict):
                    raise ValueError("expected a JSON object {\"target\", \"closed\", \"at_seq\"}")
                target, closed, at = body.get("target"), body.get("closed"), body.get("at_seq")
                if not isinstance(target, str) or (target not in self.net.sources and target not in self.net.lines):
                    raise ValueError(f"target: {target!r} is not a source or a line of {self.net.name!r}")
                if not isinstance(closed, bool):
                    raise ValueError("closed: expected true or false")
                if at is not None and (type(at) is not int or at < 0):
                    raise ValueError("at_seq: expected a sample number or null (the next sample)")
                with self.lock:
                    self.pending.append((at, target, closed, str(body.get("by", ""))))
                    self.counters["breaker_commands"] += 1
                query.reply(key(self.cfg.prefix, self.cfg.id, "breaker"),
                            json.dumps({"target": target, "closed": closed, "at_seq": at}))
            except Exception as e:  # noqa: BLE001 - any bad query (deep JSON too): answered with why, counted
                with self.lock:
                    self.counters["rejected"] += 1
                try:
                    query.reply_err(json.dumps({"error": f"breaker: {type(e).__name__}: {e}"[:300]}))
                except Exception:  # noqa: BLE001 - the asker went away
                    pass
            finally:
                query.drop()

    def _apply_breakers(self, k: int, t: float) -> None:
        with self.lock:
            due = [p for p in self.pending if p[0] is None or p[0] <= k]
            self.pending = [p for p in self.pending if not (p[0] is None or p[0] <= k)]
        for _, target, closed, by in due:
            self.model.breaker(target, closed)
            # a close the coordinator made after a connect request is the plug-in; an open, a trip
            kind = ("connect" if by else "close") if closed else "trip"
            self.events.append(Event(t, kind, target, True, f"by {by}" if by else ""))

    # ---------------------------------------------------------------- the result
    def trace(self) -> NetworkResult:
        """The run as the offline result's shape (true state; modes and v_ref are the daemons', not known here)."""
        net = self.net
        ns = len(self.names)
        a = np.frombuffer(self._rows, dtype=np.float64).reshape(-1, self._width) if len(self._rows) else \
            np.zeros((0, self._width))
        t = a[:, 0].copy()
        sources = {}
        for j, name in enumerate(self.names):
            c = 1 + 6 * j
            sources[name] = {k: a[:, c + q].copy() for q, k in enumerate(("i", "v", "u", "i_out", "P", "du_dt"))}
        o = 1 + 6 * ns
        buses = {b: a[:, o + q].copy() for q, b in enumerate(net.buses)}
        o += len(net.buses)
        lines = {ln: a[:, o + q].copy() for q, ln in enumerate(net.lines)}
        if self.lockstep:  # the answers, as offline's cmd_du / cmd_du_next
            c = np.frombuffer(self._cmds, dtype=np.float64).reshape(-1, 2 * ns)[:len(t)] if len(self._cmds) else \
                np.zeros((0, 2 * ns))
            for j, name in enumerate(self.names):
                sources[name]["cmd_du"], sources[name]["cmd_du_next"] = c[:, 2 * j].copy(), c[:, 2 * j + 1].copy()
        return NetworkResult(net, t, sources, buses, lines, list(self.events), {})

    def result(self) -> dict:
        res = self.trace()
        add_load_events(res)
        res.metrics = network_metrics(res, self.diverged_at, None, self.model.unsupplied,
                                      self.model.why if self.diverged_at is not None else None)
        n = len(res.t)
        checks = acceptance_checks(res)
        self.counters["missed"] = sum(max(0, n - 1 - self.answered[s]) for s in self.names
                                      if self.net.sources[s].connected)
        for name, sched in zip(self.names, self.model.scheds, strict=True):  # late, planned and held periods
            for k, v in sched.counts.items():
                self.counters[f"{name}_{k}"] = v
        out = {"state": "failed" if self.failure else "done", "failure": self.failure.reason,
               "metrics": res.metrics, "counters": dict(self.counters), "pacing": self.cfg.pacing,
               "command_age": {s: age_summary(h, self.model.d) for s, h in self.age_hist.items() if sum(h)},
               "control_rate_hz": self.net.timing.control_rate_hz, "samples": n,
               "wall_s": getattr(self, "wall_s", None),
               "rate_achieved_hz": n / self.wall_s if getattr(self, "wall_s", 0) else None,
               "cpu": {"rig_pct": self.cpu.pct if self.cpu else None}, "checks": checks,
               "last_answered": dict(self.answered), "cut_off_s": round(self.cut_off_s, 3)}
        if self.cfg.out:
            write_rig_log(self.cfg.out, res, self.cfg.prefix, out)
        out["result"] = res
        return out


def age_summary(hist: list[int], d: int) -> dict:
    """A realtime rig's command ages (samples from the sample answered to the one the rig was about to take when
    the command was there; the last bin holds the older ones): median, 99th percentile, and the share that came
    after their period (older than the loop delay d)."""
    n = sum(hist)
    cum = np.cumsum(hist)
    return {"p50_samples": int(np.searchsorted(cum, 0.5 * n)), "p99_samples": int(np.searchsorted(cum, 0.99 * n)),
            "after_their_period_pct": 100.0 * sum(hist[d + 1:]) / n, "commands": n}


def add_load_events(res: NetworkResult) -> None:
    """The load steps of the scenario, as events of the metrics (as the offline run lists them)."""
    from service.plant.network import NetworkPlant

    plant = NetworkPlant(res.net)
    end = res.net.timing.duration_s
    for j, prof in enumerate(plant.profiles):
        if prof is not None:
            res.events += [Event(ts, "load", plant.load_names[j]) for ts in prof.step_times() if ts < end]
    res.events.sort(key=lambda e: e.t)


def write_rig_log(path: str, res: NetworkResult, prefix: str, summary: dict) -> None:
    """The rig's log in the offline network log's layout for the plant (module docstring)."""
    from service.logio.mcapfile import McapFile

    net = res.net
    base = f"{prefix}/{net.name}"
    f = McapFile(path)
    f.metadata("scenario", {"json": net.model_dump_json()})
    f.metadata("metrics", {"json": json.dumps(res.metrics)})
    f.metadata("rig", {"json": json.dumps({k: v for k, v in summary.items() if k != "metrics"})})
    for el in (*res.sources, *res.buses, *res.lines):
        f.channel(f"{base}/{el}/plant", "energyctl.Plant")
    cmds = {n for n, row in res.sources.items() if "cmd_du" in row}  # lockstep: each source's answers
    for n in res.sources:  # in scenario order: the same channel ids every run
        if n in cmds:
            f.channel(f"{base}/{n}/cmd", "energyctl.Command")
    f.channel(f"{base}/layer/events", "energyctl.Event")
    t = res.t.tolist()
    src = {n: {k: v.tolist() for k, v in row.items()} for n, row in res.sources.items()}
    buses = {b: v.tolist() for b, v in res.buses.items()}
    lines = {ln: v.tolist() for ln, v in res.lines.items()}
    for k, tk in enumerate(t):
        for n, c in src.items():
            f.add(f"{base}/{n}/plant", tk, {"t": tk, "i": c["i"][k], "v": c["v"][k], "u": c["u"][k], "P_l": c["P"][k]})
            if n in cmds and c["cmd_du"][k] == c["cmd_du"][k]:  # NaN: no answer came, nothing logged
                f.add(f"{base}/{n}/cmd", tk, {"seq": k, "t": tk, "du_dt": c["cmd_du"][k],
                                              "du_dt_next": c["cmd_du_next"][k], "limited": False})
        for b, v in buses.items():
            f.add(f"{base}/{b}/plant", tk, {"t": tk, "i": 0.0, "v": v[k], "u": 0.0, "P_l": 0.0})
        for ln, i in lines.items():
            f.add(f"{base}/{ln}/plant", tk, {"t": tk, "i": i[k], "v": 0.0, "u": 0.0, "P_l": 0.0})
    rate = net.timing.control_rate_hz
    for ev in res.events:
        if ev.kind == "load":
            continue
        f.add(f"{base}/layer/events", ev.t, {"t": ev.t, "seq": int(round(ev.t * rate)), "kind": ev.kind,
                                            "detail": json.dumps({"target": ev.target, "accepted": ev.accepted,
                                                                  "reason": ev.reason})})
    f.close()


def read_rig_log(path: str) -> NetworkResult:
    """A rig log back as the offline result's shape, with its metrics recomputed from the logged state."""
    from clients.report import network_series
    from service.logio.reader import scan

    meta = scan(path)["metadata"]
    net = NetworkScenario.model_validate_json(meta["scenario"]["json"])
    data = network_series(path)
    el = data["elements"]
    t = el[next(iter(net.sources))]["plant"]["t"]
    sources = {s: {"i": el[s]["plant"]["i"], "v": el[s]["plant"]["v"], "u": el[s]["plant"]["u"],
                   "P": el[s]["plant"]["P_l"]} for s in net.sources}
    for s in net.sources:  # a lockstep rig's log: each source's answers by sample (NaN: none came)
        cmd = el[s].get("cmd")
        if cmd is not None or any("cmd" in el[o] for o in net.sources):
            du, du_next = np.full(len(t), np.nan), np.full(len(t), np.nan)
            if cmd is not None:
                seq = cmd["seq"].astype(np.int64)
                du[seq], du_next[seq] = cmd["du_dt"], cmd["du_dt_next"]
            sources[s]["cmd_du"], sources[s]["cmd_du_next"] = du, du_next
    buses = {b: el[b]["plant"]["v"] for b in net.buses}
    lines = {ln: el[ln]["plant"]["i"] for ln in net.lines}
    events = [Event(e["t"], e["kind"], json.loads(e["detail"])["target"], json.loads(e["detail"])["accepted"],
                    json.loads(e["detail"])["reason"]) for e in data["events"]]
    res = NetworkResult(net, t, sources, buses, lines, events, {})
    add_load_events(res)
    v = np.concatenate([*buses.values(), *(s["v"] for s in sources.values())]) if len(t) else np.zeros(0)
    v_nom = net.nominal_v_V
    bad = np.nonzero(~np.isfinite(v) | (v <= 0.5 * v_nom) | (v >= 2 * v_nom))[0]
    res.metrics = network_metrics(res, float(t[bad[0] % len(t)]) if len(bad) else None, None)
    return res

