"""The controller daemon: the core behind a fixed-rate loop on Zenoh.

Threads:
* the loop thread reads the newest measurement and neighbour messages (ring-of-one subscribers
  polled with try_recv, no callbacks), steps the core, publishes du/dt; it records timing into
  preallocated arrays and never formats JSON, logs or serves queries;
* three query threads answer ``status``, ``config`` and ``config/set`` from channels; a config set is
  validated there (its size first: query_max_bytes) and handed to the loop, which applies it at the next tick boundary;
* with the sample trigger's queue, Zenoh's receiving thread refuses the measurements that can never be the next
  sample before they are queued (_admit: counted by reason), so that a flood of them costs the loop nothing;
* the main thread waits for SIGINT/SIGTERM and shuts down within one period.

Lifecycle: configured -> active <-> inactive (du/dt = 0 is published) -> shutdown; active -> degraded
(stale measurements: du/dt = 0) -> active by itself when fresh measurements return; any -> failed when the loop
thread (or the forecast worker's thread) ends by an unexpected exception: u held, nothing more published, the token
withdrawn, the reason in status and on stderr, and ``energyctl run`` exits 1 (service.daemon.failure).
"""

from __future__ import annotations

import gc
import json
import sys
import threading
import time
from array import array

import zenoh

from schemas.codec import CMD, MEAS, VERSION, DecodeError, Z
from schemas.component import ComponentConfig
from schemas.scenario import ControllerConfig
from service.core import core_metadata, effective_gain, make_core
from service.core.control import recovery_rate
from service.core.feasibility import FeasibilityMonitor, incoming_range, tau_prime
from service.core.interaction import outgoing_power_at as _outgoing_power_at
from service.daemon.bus import close_session, key, latest, open_session, publisher, queued, serve_queries, zenoh_config
from service.daemon.failure import Failure
from service.daemon.forecast_worker import ForecastWorker
from service.daemon.loop_stats import HIST, LoopStats
from service.daemon.neighbours import Neighbour
from service.daemon.queries import DaemonQueries
from service.priority import fill_tuple_free_lists

_CMD_PACK, _CMD_MAGIC, _VERSION = CMD.struct.pack, CMD.magic, VERSION  # CMD.encode without its call, on the tick
_now_ns = time.monotonic_ns
STATES = ("configured", "active", "inactive", "shutdown")
# the sample trigger's queue of arrived measurements keeps the newest this many (the loop answers the newest
# loop.catch_up <= 256): a stalled loop thread no longer piles up every sample that arrives meanwhile (memory)
MEAS_QUEUE_MAX = 1024
REJECT_EVENT_EVERY_NS = 10_000_000  # at most one recorded reject event per reason this often (all are counted)


SAMPLE_STALE_MIN_NS = 50_000_000  # sample trigger: a lockstep plant may pause this long without being stale


class Daemon(DaemonQueries):
    """One component's controller: the core behind the fixed-rate loop (see the module docstring)."""

    def __init__(self, cfg: ComponentConfig):
        self.cfg = cfg
        self.period_s = 1.0 / cfg.loop.rate_hz
        self.core = make_core(cfg.controller, cfg.model, self.period_s, cfg.delay_samples, cfg.core)
        self.stats = LoopStats(cfg.loop.stats_window)
        self.state = "configured"
        self.failure = Failure(f"energyctl[{cfg.id}]")  # the loop's (or the forecast thread's) unexpected end
        self.log_error = ""  # the recorder could not even start
        self.alive_sub = None
        self.rejected: dict[str, int] = {}
        self.last_reject = ""
        self.last_sample: tuple | None = None
        self.last_cmd: tuple | None = None
        self.config_version = 0
        self._pending: tuple[ControllerConfig, threading.Event, str] | None = None
        self.recorder = None
        self._fast = None  # the compiled stepped tick (open: _tick_writer)
        self.put_ns = 0  # the last tick's command put (ns)
        self.control_ns = 0  # the last tick's control computation (ns; LoopStats.control)
        self._idle = 0
        self.restarts = 0
        self.meas_skipped = 0  # frames the sample loop passed over for newer ones (catch_up), unchecked but counted
        self.late_ticks = 0  # ticks at which the core saw its commands not acting in time (late_detect_V)
        self.current_limited_ticks = 0  # ticks whose command the law shaped at limits.i_max_A (nested)
        self._ilim_out = None  # the core's output to read i_limited from, while a current limit is set
        self._watch_current_limit(cfg.controller)
        self._reject_events: dict[str, tuple[int, int]] = {}  # reason -> (loop ns of its last event, rejects since)
        self.degraded_reason = ""
        self.reference = "none"
        self._reference = None  # a pluggable reference (_step); None: the neighbours'
        self._held_du = 0.0  # a HELD tick's command (_reference), V/s
        self._pending_state: str | None = None
        self._stop = threading.Event()
        self._last_seq = -1
        # the plant's clock (docs/protocol.md, "The plant's clock"): the next sample is at most _max_gap samples after
        # the last one stepped on, and its t within _clock_tol of where that seq's sample time is; frames that are not
        # form a candidate clock (_chain: the newest one's seq and t, and how many agreed in a row), adopted once no
        # sample was stepped on for _resync_ns of the loop's clock (from _accepted_ns)
        self._u_max = cfg.meas_u_max_V
        self._max_gap = max(1, int(cfg.meas_max_gap_s * cfg.loop.rate_hz))
        self._clock_tol = (cfg.meas_clock_tolerance_s if cfg.meas_clock_tolerance_s is not None
                           else 0.5 * self.period_s)
        self._resync_ns = max(int(cfg.stale_periods * self.period_s * 1e9), SAMPLE_STALE_MIN_NS)
        self._accepted_ns = 0
        self._chain: tuple[int, float] | None = None
        self._chain_n = 0
        self.clock_resyncs = 0
        self.recovery_ticks = 0  # samples with v out of range answered by the recovery command (_hold)
        self._recovering_since = -1  # _accepted_ns when the current recovery began (one event per recovery)
        self.refused_requests = 0  # config/set requests above query_max_bytes
        # a neighbour's plausible powers (W) and rates (W/s): from the config (neighbour_P_max_W, else v_max x i_max)
        P_max = cfg.neighbour_P_max_W if cfg.neighbour_P_max_W is not None else cfg.meas_v_max_V * cfg.meas_i_max_A
        powers, rates = ("P_r_out", "P_min", "P_max"), ("P_r_out_dot", "Qdot_r_out", "P_dot_min", "P_dot_max")
        self._z_bounds = tuple((k, name, P_max if name in powers else P_max * cfg.loop.rate_hz)
                               for k, name in enumerate(Z.fields) if name in powers + rates)
        # measurements refused on receipt (the subscriber's thread, _admit): counted apart from the loop's own
        self.rx_rejected: dict[str, int] = {}
        self._rx_lock = threading.Lock()  # Zenoh may call the subscriber from more than one of its threads
        self._rx_logged = 0  # rx rejections already summarised in an event
        self._z_seq = 0
        self.feas = FeasibilityMonitor(cfg.forecast_window_s, keep_windows=100, keep_recent=5)
        self._tau_p = tau_prime(cfg.model.L_H, cfg.model.R_ohm, effective_gain(cfg.controller, cfg.model))
        self._z_every = max(1, round(cfg.loop.rate_hz / cfg.interaction_rate_hz))
        self._est_every = cfg.log_est_every
        self._est_phase = cfg.log_est_every // 2
        self._window = -1
        self._zin_window = -1  # the window whose incoming range the monitor holds
        self._fc_asked = -1  # the newest window a forecast was asked for
        self._nb_news = False  # a neighbour message arrived since the loop last looked at the ranges
        self.forecaster: ForecastWorker | None = None
        self.session: zenoh.Session | None = None
        # (seq, measured u, du/dt sent) of the last HIST ticks, for the measured loop delay (service/core/delay.py):
        # the loop stores, the status query estimates
        self._hist_seq = array("q", [-1] * HIST)
        self._hist_u = array("d", [0.0] * HIST)
        self._hist_r = array("d", [0.0] * HIST)
        self._loop_delay_cache: tuple[int, dict] | None = None

    # ---------------------------------------------------------------- setup / teardown
    def open(self) -> None:
        c = self.cfg
        self.session = s = open_session(c.zenoh)
        plant = c.plant_id or c.id
        if c.loop.trigger == "sample" and c.loop.wait == "block":
            # frames that can never be the next sample are refused on Zenoh's thread (_admit): under a flood of them
            # the loop's queue holds the plant's samples, and the loop does no work for them
            self.meas_sub, self.meas_q = queued(s, key(c.prefix, plant, "meas"), MEAS_QUEUE_MAX, admit=self._admit)
        else:
            self.meas_sub = latest(s, key(c.prefix, plant, "meas"), c.loop.catch_up)
        self.cmd_pub = publisher(s, key(c.prefix, c.id, "cmd"))
        self.z_pub = publisher(s, key(c.prefix, c.id, "z"))
        self.neighbours = [Neighbour(n, latest(s, key(c.prefix, n, "z"))) for n in c.neighbours]
        # config/set is a key of its own so that a router's ACL can let only operators set (docs/operations.md)
        serve = {"status": self._status_reply, "config": self._config_reply, "config/set": self._config_set_reply}
        self.queryables = {leaf: s.declare_queryable(key(c.prefix, c.id, leaf), zenoh.handlers.FifoChannel(64))
                           for leaf in serve}
        # neighbours' liveliness tokens: a channel the loop polls (no Python callback: dropping one at close
        # can deadlock zenoh-python against the GIL)
        self._by_id = {nb.id: nb for nb in self.neighbours}
        self.alive_sub = (s.liveliness().declare_subscriber(key(c.prefix, "*", "alive"),
                                                            zenoh.handlers.FifoChannel(64), history=True)
                          if self.neighbours else None)
        self.recorder = None
        if c.log_dir:
            try:
                self.recorder = self._open_recorder()
            except OSError as e:  # no shared memory, no process: control runs without a log, and says so
                self.log_error = f"recorder could not start: {e}"
                print(f"energyctl[{c.id}]: logging degraded: {self.log_error}", file=sys.stderr, flush=True)
            else:
                self.recorder.wait_ready()  # a failure shows in status as logging: degraded
        self._fast = self._tick_writer()
        if c.forecast.enabled and self.neighbours:  # a worker process: started (and imported) before the loop runs
            self.forecaster = ForecastWorker(c.model, self.period_s, self.core.d, c.forecast, c.forecast_window_s,
                                             on_result=self._forecast_done, impl=c.core, failure=self.failure,
                                             on_failure=self._stop.set)
            self.forecaster.start()
        self._threads = [threading.Thread(target=serve_queries, name=leaf, daemon=True,
                                          args=(self.queryables[leaf], key(c.prefix, c.id, leaf), fn))
                         for leaf, fn in serve.items()]
        for t in self._threads:
            t.start()
        self.state = "active"
        self.token = None  # declared by the loop once it is ready to tick (run_loop)

    def _open_recorder(self):
        from datetime import UTC, datetime

        from schemas.codec import EST, LOOP, TICK_IN
        from service.logio.mcapfile import git_revision
        from service.logio.ring import RingRecorder

        c = self.cfg
        base = f"{c.prefix}/{c.id}"
        self.t_meas, self.t_cmd, self.t_zin = f"{base}/meas", f"{base}/cmd", f"{base}/z_in"
        self.t_zout, self.t_est, self.t_ev = f"{base}/z_out", f"{base}/est", f"{base}/events"
        self.t_loop = f"{base}/loop"
        for nb in self.neighbours:
            nb.topic = f"{base}/z_nb/{nb.id}"
        topics = {self.t_meas: ("energyctl.Measurement", MEAS), self.t_cmd: ("energyctl.Command", CMD),
                  self.t_zin: ("energyctl.TickInput", TICK_IN), self.t_zout: ("energyctl.Interaction", Z),
                  self.t_est: ("energyctl.Estimate", EST), self.t_ev: ("energyctl.Event", None),
                  self.t_loop: ("energyctl.LoopRecord", LOOP)}
        for nb in self.neighbours:  # raw neighbour messages, as received
            topics[f"{base}/z_nb/{nb.id}"] = ("energyctl.Interaction", Z)
        topics.update(self._extra_topics())
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        path = f"{c.log_dir}/{c.id}-{stamp}.mcap"
        meta = {"config": {"json": c.model_dump_json()}, "core": {"json": core_metadata(
            self.core.cfg, c.model, self.period_s, self.core.d)}, "build": {"git": git_revision()}}
        self.log_path = path
        live = None
        if c.log_live_hz > 0:  # est, z_in and events live, from the writer's process (RingWriter.tap)
            z = c.zenoh  # a session of its own: it listens nowhere, it connects where the daemon does or listens
            reach = list(z.connect) + [e for e in z.listen if not e.endswith(":0")]
            if z.config_file is None and reach:
                zl = z.model_copy(update={"listen": [], "connect": reach})
                live = (str(zenoh_config(zl)), {t: key(c.prefix, c.id, t.rsplit("/", 1)[1])
                                                for t in (self.t_est, self.t_zin, self.t_ev)}, 1.0 / c.log_live_hz)
        return RingRecorder(path, topics, meta, slots=c.log_queue, rotate_bytes=c.log_rotate_bytes,
                            rotate_s=c.log_rotate_s, writer_cpus=c.log_writer_cpus,
                            groups=[(self.t_meas, self.t_zin, self.t_cmd)],  # offer_group(0, ...) in _tick
                            live=live)

    def _take_sample(self, v: tuple) -> None:
        """v is the next sample stepped on: back to active from degraded, the samples skipped before it counted."""
        seq = v[0]
        if self.state == "degraded":
            self.state = "active"
        if self._last_seq >= 0 and seq > self._last_seq + 1:
            self.stats.missing_samples += seq - self._last_seq - 1
        self._last_seq = seq
        self.last_sample = v

    def _extra_topics(self) -> dict:
        """Further recorded topics of a kind of daemon: topic -> (schema name, codec)."""
        return {}

    def _tick_writer(self):
        """With the compiled core: a service._kernel.TickWriter checking an ordinary sample (accept; _checked is its
        reference) and doing a stepped tick's step, command payload, history entry and recorder slot in one call (the
        Python lines in _tick are its reference); else None."""
        k = getattr(self.core, "_k", None)
        if k is None:
            return None
        from service._kernel import TickWriter

        ring = self.recorder.ring_args(0) if self.recorder is not None else {}
        c = self.cfg
        ranges = MEAS.half_open_ranges()  # accept admits what decode admits: seq in [0, 2^53), t in [0, 2^32)
        if set(ranges) != {"seq", "t"} or ranges["seq"][0] != 0:
            raise ValueError(f"TickWriter.accept checks seq < a limit and t in a range; the codec checks {ranges}")
        seq, t = ranges["seq"], ranges["t"]
        return TickWriter(k, self._hist_seq, self._hist_u, self._hist_r, CMD.struct.format, CMD.magic, VERSION,
                          **ring, meas_format=MEAS.struct.format, meas_magic=MEAS.magic, v_min=c.meas_v_min_V,
                          v_max=c.meas_v_max_V, i_max=c.meas_i_max_A, seq_limit=seq[1], t_min=t[0], t_limit=t[1],
                          u_max=self._u_max, max_gap=self._max_gap, period=self.period_s, clock_tol=self._clock_tol)

    def close(self) -> None:
        if not self.failure:
            self.state = "shutdown"
        if getattr(self, "_fast", None) is not None:
            self._fast.close()  # its view of the recorder's ring goes before the ring does
            self._fast = None
        if self.forecaster is not None:
            self.forecaster.close()
        if getattr(self, "recorder", None) is not None:
            self.recorder.close()
        if self.session is not None:
            try:
                if self.token is not None:
                    self.token.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
            close_session(self.session)  # also ends the query threads' blocking recv(); a timeout is not raised
            for t in self._threads:
                t.join(timeout=0.5)
            self.session = None

    def stop(self) -> None:
        """Ask the loop to end (it checks between ticks and polls)."""
        self._stop.set()

    # ---------------------------------------------------------------- loop
    def run_loop(self, max_ticks: int | None = None) -> None:
        fill_tuple_free_lists()  # the memory the loop keeps, taken now (service.priority)
        gc.collect()  # tens of ms with everything imported: before the first sample, not during it
        gc.freeze()
        if self.token is None and self.session is not None:
            # alive last: peers that wait for the token (the plant) start only when everything here is ready,
            # the loop included (announced from open(), the first 5-30 samples of a realtime plant were missed)
            c = self.cfg
            self.token = self.session.liveliness().declare_token(key(c.prefix, c.id, "alive"))
        try:
            if self.cfg.loop.trigger == "clock":
                self._clock_loop(max_ticks)
            else:
                self._sample_loop(max_ticks)
        except Exception as e:  # noqa: BLE001 - whatever ends the loop: the component fails, visibly (_safe_state)
            self.failure.record("loop", e)
        finally:
            gc.unfreeze()
            if self.failure:
                self._safe_state()

    def _safe_state(self) -> None:
        """After a failure (the loop's own, or another thread's that stopped it): hold u (one hold for the last sample
        answered, as a degrade does: a plant waiting for that answer applies du/dt = 0, and without commands it holds
        u after the last plan), publish nothing more (the loop has ended), withdraw the liveliness token (a plant, a
        coordinator, a supervisor sees the controller gone), and say so in status, the log and the events."""
        self.state = "failed"
        ls = self.last_sample
        for step in (lambda: ls is not None and self.cmd_pub.put(CMD.encode(ls[0], ls[1], 0.0, 0.0, True)),
                     lambda: self.token is not None and self.token.undeclare(),
                     lambda: self.recorder is not None and self.recorder.offer(
                         self.t_ev, ls[1] if ls else 0.0, (ls[1] if ls else 0.0, max(self._last_seq, 0), "failed",
                                                           self.failure.reason))):
            try:
                step()
            except Exception:  # noqa: BLE001 - each step on its own: one that fails does not skip the others
                pass
        self.token = None

    def _clock_loop(self, max_ticks: int | None) -> None:
        period = int(round(self.period_s * 1e9))
        margin = int(self.cfg.loop.spin_margin_s * 1e9)
        now_ns, sleep = time.monotonic_ns, time.sleep
        stats, stop = self.stats, self._stop
        nxt = now_ns() + period
        prev = 0
        while not stop.is_set():
            wait = nxt - now_ns()
            if wait > margin:
                sleep((wait - margin) * 1e-9)
            while now_ns() < nxt:
                pass
            start = now_ns()
            if self._pending is not None or self._pending_state is not None:
                self._apply_pending()
            s = self.meas_sub.try_recv()
            if s is None:
                stats.no_new_sample += 1
                self._poll_neighbours(start)
                self._idle += 1
                if self._idle == self.cfg.stale_periods and self.state == "active":
                    self._degrade("meas: stale")
            else:
                self._idle = 0
                self._tick(s.payload.to_bytes(), start)
            end = now_ns()
            stats.record(start - prev if prev else 0, end - start, self.put_ns if s is not None else 0,
                         self.control_ns if s is not None else 0)
            prev = start
            nxt += period
            if end > nxt:  # ran into the next period: skip whole periods, count them
                missed = (end - nxt) // period + 1
                stats.overruns += missed
                nxt += missed * period
            if max_ticks is not None and stats.ticks >= max_ticks:
                break

    def _sample_loop(self, max_ticks: int | None) -> None:
        """Tick on each measurement. Wakes on arrival (queue fed by a Zenoh callback); when several
        arrived, the newest loop.catch_up are answered in order (default 1: only the newest) and the others
        count as missing."""
        from queue import Empty

        now_ns = time.monotonic_ns
        stats, stop, q = self.stats, self._stop, getattr(self, "meas_q", None)
        lockstep = self.cfg.loop.lockstep
        timeout_ns = int(self.cfg.loop.lockstep_timeout_s * 1e9)
        spin = self.cfg.loop.wait == "spin"
        catch_up = self.cfg.loop.catch_up
        sub = self.meas_sub
        prev = idle = 0
        # no sample for this long -> degraded (every answered sample was already answered: nothing to publish)
        stale_ns = max(int(self.cfg.stale_periods * self.period_s * 1e9), SAMPLE_STALE_MIN_NS)

        def check_stale(now: int) -> None:
            self._poll_neighbours(now)
            if self.state == "active" and prev and now - prev > stale_ns:
                self._degrade("meas: stale", publish_hold=False)

        while not stop.is_set():
            if self._pending is not None or self._pending_state is not None:
                self._apply_pending()
            if spin:  # poll the ring: filled on Zenoh's side, no GIL needed to fill it
                try:
                    m = sub.try_recv()
                except Exception:  # noqa: BLE001 - the subscriber was closed: shutting down
                    break
                if m is None:
                    idle += 1
                    if idle & 0x3FF == 0:  # keep neighbour freshness and staleness current while no sample comes
                        check_stale(now_ns())
                    continue
                idle = 0
                payload = m.payload.to_bytes()
            else:
                try:
                    item = q.get(timeout=0.05)
                except Empty:
                    check_stale(now_ns())
                    continue
                while q.qsize() >= catch_up:  # keep the newest catch_up; this one first, the rest next round
                    item = q.get_nowait()
                    self.meas_skipped += 1  # the one passed over: counted (missing_samples counts seqs, not frames)
                payload = item[1]
            start = t_exec = now_ns()
            if lockstep and self.neighbours:
                # the sample is checked first; only one the core will step on waits for the neighbours' messages of
                # its seq: a frame rejected or held (malformed, out of range, a duplicate seq: none of them uses
                # P^{r,in}) is answered at once and never stalls the loop
                if (v := self._sample(payload, start)) is not None:
                    self._await_neighbours(v[0], start + timeout_ns)
                    t_exec = now_ns()
                    self._step(v, t_exec)
            else:
                self._tick(payload, t_exec)
            end = now_ns()
            stats.record(start - prev if prev else 0, end - t_exec, self.put_ns, self.control_ns)
            prev = start
            if max_ticks is not None and stats.ticks >= max_ticks:
                break

    def _await_neighbours(self, seq: int, deadline: int) -> None:
        """Lockstep: poll until every neighbour's newest message is for ``seq`` or later (not one whose token is gone
        nor one lagging), or the deadline (ns) passes: then count the timeout and mark the ones behind lagging."""
        nbs, now_ns, stop = self.neighbours, time.monotonic_ns, self._stop
        while any(nb.seq < seq and nb.alive is not False and not nb.lagging for nb in nbs) and not stop.is_set():
            self._poll_neighbours(now_ns())
            if now_ns() > deadline:  # a hung neighbour stalls one tick, not every tick
                self.stats.lockstep_timeouts += 1
                for nb in nbs:
                    nb.lagging = nb.lagging or nb.seq < seq
                break
            time.sleep(20e-6)
        for nb in nbs:  # keeping pace again (it answered the previous sample): wait for it from now on
            if nb.lagging and nb.seq >= seq - 1:
                nb.lagging = False

    def _reject(self, reason: str, now: int, detail: str = "") -> None:
        """Count by reason class (bounded keys); keep the detail of the last one; record it as a diagnostics
        event, at most one per reason per REJECT_EVENT_EVERY_NS of the loop's clock (``now``, ns; a diverged plant
        is rejected at every sample: a flood of events outgrew the recorder's event queue), saying how many it
        stands for."""
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        text = f"{reason} ({detail})" if detail else reason
        self.last_reject = text
        if self.recorder is not None:
            last_ns, held = self._reject_events.get(reason, (None, 0))
            if last_ns is not None and 0 <= now - last_ns < REJECT_EVENT_EVERY_NS:
                self._reject_events[reason] = (last_ns, held + 1)
                return
            self._reject_events[reason] = (now, 0)
            t = self.last_sample[1] if self.last_sample else 0.0
            if held:
                text = f"{text} [and {held} more since the last of these]"
            self.recorder.offer(self.t_ev, t, (t, max(self._last_seq, 0), "reject", text))

    def _poll_neighbours(self, now: int) -> None:
        if self.alive_sub is not None:
            while (tok := self.alive_sub.try_recv()) is not None:  # tokens appear and vanish rarely
                nb = self._by_id.get(str(tok.key_expr).split("/")[-2])
                if nb is not None:
                    nb.alive = tok.kind == zenoh.SampleKind.PUT
        for nb in self.neighbours:
            v = self._take_z(nb, now)
            if v is None:
                continue
            w = v[7]
            nb.ranges[w & 1] = (w, v[8:12])
            self._nb_news = True
            if w > self._fc_asked and self.forecaster is not None and (box := self._box(w)) is not None:
                # whatever the loop's state: a feed-forward check
                self.forecaster.request(w, box, self.core.cfg, self.config_version)
                self._fc_asked = w
            if self.recorder is not None:
                self.recorder.offer(nb.topic, v[1], v)

    def _take_z(self, nb: Neighbour, now: int) -> tuple | None:
        """A neighbour's newest interaction message, if one came: decoded into it (counted, stamped ``now``), or
        rejected by field."""
        z = nb.sub.try_recv()
        if z is None:
            return None
        try:
            v = Z.decode(z.payload.to_bytes())
        except DecodeError as e:
            self._reject(f"{nb.id}.{e.field}: invalid", now, e.reason)
            return None
        for k, name, bound in self._z_bounds:  # finite, but no power a component on this bus can carry
            if not abs(v[k]) <= bound:
                self._reject(f"{nb.id}.{name}: out of range", now, f"|{v[k]:g}| above {bound:g}")
                return None
        nb.seq, nb.t, nb.P, nb.P_dot, nb.Qdot = v[0], v[1], v[2], v[3], v[4]
        nb.rx_ns = now
        nb.count += 1
        return v

    def _watch_current_limit(self, ctl) -> None:
        """Count the ticks at the current limit only while the nested law has one (a read per tick then)."""
        self._ilim_out = self.core.out if ctl.kind == "nested" and ctl.limits.i_max_A is not None else None

    def _apply_pending(self) -> None:
        """Apply a validated config change or lifecycle transition (called between ticks)."""
        if self._pending is not None:
            new_cfg, ev, text = self._pending
            self.core.set_gains(new_cfg)
            self._watch_current_limit(new_cfg)
            self.config_version += 1
            self._tau_p = tau_prime(self.cfg.model.L_H, self.cfg.model.R_ohm, effective_gain(new_cfg, self.cfg.model))
            self._fc_asked = -1  # forecast again with the new gains (at the next neighbour message)
            self._pending = None
            if self.recorder is not None:  # applies before the next measurement
                t = self.last_sample[1] if self.last_sample else 0.0
                self.recorder.offer(self.t_ev, t, (t, self._last_seq + 1, "config", text))
            ev.set()
        if self._pending_state is not None:
            self.state, self._pending_state = self._pending_state, None

    def _forecast_done(self, window: int, f) -> None:
        """The forecast worker's thread: a window's Z^{r,out} forecast and verdict go to the log as an event."""
        if self.recorder is not None:
            t = window * self.cfg.forecast_window_s
            self.recorder.offer(self.t_ev, t, (t, max(self._last_seq, 0), "forecast",
                                               json.dumps({"window": window, **f.as_dict()})))
        if not f.feasible:
            print(f"energyctl[{self.cfg.id}]: window {window} forecast infeasible: {f.reason}", file=sys.stderr,
                  flush=True)

    def _neighbour_event(self, nb: Neighbour, t: float) -> None:
        nb.alive_seen = nb.alive
        if self.recorder is not None and nb.alive is not None:
            what = "neighbour_alive" if nb.alive else "neighbour_gone"
            self.recorder.offer(self.t_ev, t, (t, max(self._last_seq, 0), what, nb.id))

    def _degrade(self, why: str, publish_hold: bool = True) -> None:
        """Hold the source (du/dt = 0) until fresh measurements return; then back to active by itself."""
        self.state = "degraded"
        self.degraded_reason = why
        ls = self.last_sample
        if ls is not None and publish_hold:
            self.cmd_pub.put(CMD.encode(ls[0], ls[1], 0.0, 0.0, True))
        if self.recorder is not None:
            t = ls[1] if ls else 0.0
            self.recorder.offer(self.t_ev, t, (t, max(self._last_seq, 0), "degraded", why))

    def _hold(self, v: tuple, now: int, reason: str, detail: str = "", recover: bool = False) -> None:
        """A rejected measurement: counted, recorded, answered with du/dt = 0; the core never sees it. Nor is it
        told of the hold (replay could not repeat that: rejected samples are not in the log), so for this sample's
        period it predicts the plan sent with the previous answer: one period of model error, against bit-exact
        replay.

        ``recover`` (v out of range, the rest in range, the daemon active or degraded: _recoverable): once no sample
        was stepped on for the stale time, the answer is the recovery
        command instead (service.core.control.recovery_rate: u toward v_ref at v_ref / recovery_ramp_s), so a bus
        left out of range (0 V after a stall, a discharged start) is brought back into range and then regulated
        (its first sample in range a resync or the first sample); a glitch shorter than the stale time is held."""
        self._reject(reason, now, detail)
        du = 0.0
        ramp_s = self.cfg.recovery_ramp_s
        if recover and ramp_s is not None and now - self._accepted_ns >= self._resync_ns:
            ctl = self.core.cfg
            ramp = min(ctl.v_ref_V / ramp_s, ctl.limits.du_dt_max_V_per_s)
            du = recovery_rate(v[4], ctl.v_ref_V, ramp, self.period_s)
            if self._recovering_since != self._accepted_ns:
                self._recovering_since = self._accepted_ns  # one event per recovery
                if self.recorder is not None:
                    self.recorder.offer(self.t_ev, v[1], (v[1], v[0], "recovery", f"{reason} ({detail}): u ramped "
                                                                                  f"toward v_ref at {ramp:g} V/s"))
            self.recovery_ticks += 1
        self.cmd_pub.put(CMD.encode(v[0], v[1], du, du, True))
        self.last_cmd = (v[0], v[1], du, du, True)
        self._remember(v[0], v[4], du)

    def _remember(self, seq: int, u: float, du: float) -> None:
        j = seq & (HIST - 1)
        self._hist_seq[j], self._hist_u[j], self._hist_r[j] = seq, u, du

    def _admit(self, payload: bytes) -> bool:
        """The measurement subscriber's thread (Zenoh's, not the loop's): whether a frame goes on the loop's queue.
        One that does not decode, or of a seq already passed while the loop is stepping on samples (no resync can be
        due), is counted here by reason (rx_rejected) and dropped: a flood of them neither displaces the plant's
        samples from the queue nor costs the loop any work. The loop's _checked stays the reference for the rest."""
        try:
            v = MEAS.decode(payload)
        except DecodeError as e:
            self._count_rx(f"meas.{e.field}: invalid", e.reason)
            return False
        seq, last = v[0], self._last_seq
        if seq <= last and not (seq == 0 and last > 0) and _now_ns() - self._accepted_ns < self._resync_ns:
            self._count_rx("meas.seq: duplicate or not increasing", "")
            return False
        return True

    def _count_rx(self, reason: str, detail: str) -> None:
        with self._rx_lock:
            rx = self.rx_rejected
            rx[reason] = rx.get(reason, 0) + 1
        self.last_reject = f"{reason} ({detail})" if detail else reason

    def _out_of_range(self, v: tuple) -> tuple[str, str] | None:
        """(reason, detail) of a measurement whose values are not plausible (config meas_*), else None."""
        c = self.cfg
        if not c.meas_v_min_V <= v[3] <= c.meas_v_max_V:
            return "meas.v: out of range", f"{v[3]:g} V not in [{c.meas_v_min_V:g}, {c.meas_v_max_V:g}]"
        if abs(v[2]) > c.meas_i_max_A or abs(v[5]) > c.meas_i_max_A:
            field = "i" if abs(v[2]) > c.meas_i_max_A else "i_load"
            return f"meas.{field}: out of range", f"beyond ±{c.meas_i_max_A:g} A"
        if not abs(v[4]) <= self._u_max:
            return "meas.u: out of range", f"{v[4]:g} V beyond ±{self._u_max:g} V"
        return None

    def _recoverable(self, v: tuple) -> bool:
        """Whether a sample held for its v may be answered by the recovery command: the daemon controls (active or
        degraded, not inactive) and the values the command reads or that say the plant is sane (u, i, i_load) are
        in their ranges."""
        c = self.cfg
        return (self.state in ("active", "degraded") and abs(v[4]) <= self._u_max and abs(v[2]) <= c.meas_i_max_A
                and abs(v[5]) <= c.meas_i_max_A)

    def _follows(self, seq: int, t: float, v: tuple) -> bool:
        """Whether v is on the clock of a sample (seq, t): at most _max_gap samples after it, its t within _clock_tol
        of t + gap x period (the plant's clock; docs/protocol.md)."""
        g = v[0] - seq
        return 0 < g <= self._max_gap and abs((v[1] - t) - g * self.period_s) <= self._clock_tol

    def _clock_candidate(self, v: tuple, now: int) -> bool:
        """A frame in range refused for its seq or t: one more of a candidate clock if it follows the previous such
        frame; whether the candidate is to be adopted now (meas_resync_frames in a row, and no sample stepped on for
        the stale time: a lone forged frame, or a few among the plant's samples, never are)."""
        ch = self._chain
        self._chain_n = self._chain_n + 1 if ch is not None and self._follows(ch[0], ch[1], v) else 1
        self._chain = (v[0], v[1])
        return self._chain_n >= self.cfg.meas_resync_frames and now - self._accepted_ns >= self._resync_ns

    def _resync(self, v: tuple) -> tuple:
        """Adopt v's clock: the core re-initialised and v the first sample of a new history (as at a plant restart),
        counted (clock_resyncs) and recorded."""
        self.core.reset()
        old = self._last_seq
        self._last_seq = -1
        self._chain, self._chain_n = None, 0
        self.clock_resyncs += 1
        if self.recorder is not None:
            self.recorder.offer(self.t_ev, v[1], (v[1], v[0], "clock_resync", json.dumps(
                {"from_seq": old, "to_seq": v[0], "t": v[1]})))
        return v

    def _checked(self, payload: bytes, now: int) -> tuple | None:
        """The measurement's values if it is the next sample to step on (a restart re-initialises the core first, a
        resync too); else None, after rejecting it (counted, named; malformed, a seq already passed, a frame off the
        plant's clock: no answer) or holding it (answered with du/dt = 0: out of range, time not advancing)."""
        try:
            v = MEAS.decode(payload)
        except DecodeError as e:
            self._reject(f"meas.{e.field}: invalid", now, e.reason)
            return None
        seq, t = v[0], v[1]
        restart = seq == 0 and self._last_seq > 0
        # a seq already passed, whatever its values: no plant waits for its answer, so it gets none (a hold would answer
        # a sample long gone, one more put on the command key, whose puts drop under congestion: decision 0031)
        if seq <= self._last_seq and not restart:
            if self._out_of_range(v) is None and self._clock_candidate(v, now):
                return self._resync(v)
            self._reject("meas.seq: duplicate or not increasing", now)
            return None
        bad = self._out_of_range(v)
        if bad is not None:
            return self._hold(v, now, *bad, recover=bad[0] == "meas.v: out of range" and self._recoverable(v))
        if restart:  # the plant restarted: its history is not ours any more
            self.core.reset()
            self._last_seq = -1
            self.restarts += 1
            if self.recorder is not None:
                self.recorder.offer(self.t_ev, t, (t, 0, "plant_restart", "{}"))
        ls = self.last_sample
        if ls is not None and self._last_seq >= 0:
            if t <= ls[1]:
                if self._clock_candidate(v, now):
                    return self._resync(v)
                return self._hold(v, now, "meas.t: not after the previous sample")
            if not self._follows(self._last_seq, ls[1], v):
                if self._clock_candidate(v, now):
                    return self._resync(v)
                g = seq - self._last_seq
                if g > self._max_gap:
                    self._reject("meas.seq: jump", now, f"{g} samples after the last one stepped on, above "
                                                        f"{self._max_gap}")
                else:
                    self._reject("meas.t: off the plant's clock", now,
                                 f"t {t!r} s, {g} samples after t {ls[1]!r} s at {self.period_s:g} s each")
                return None
        return v

    def _tick(self, payload: bytes, now: int) -> None:
        """One measurement: checked (_sample), then stepped on and answered (_step) if it is the next sample."""
        if (v := self._sample(payload, now)) is not None:
            self._step(v, now)

    def _sample(self, payload: bytes, now: int) -> tuple | None:
        """The tick's first half: the neighbours polled, the measurement's values if the core is to step on it; else
        None, the payload rejected or held (_checked)."""
        self.put_ns = self.control_ns = 0
        self._poll_neighbours(now)
        fast = self._fast
        # an ordinary next sample passes the compiled check (TickWriter.accept, the same conditions as _checked);
        # anything else goes through _checked, which names and counts what it refuses
        if fast is not None:
            ls = self.last_sample
            v = fast.accept(payload, self._last_seq, ls[1] if ls else 0.0)
            if v is not None:
                self._accepted_ns = now
                self._chain_n = 0
                return v
        v = self._checked(payload, now)
        if v is not None:
            self._accepted_ns = now
            self._chain_n = 0
        return v

    # what a tick does with a pluggable reference (self._reference, None for this daemon's own: the neighbours):
    # step the core on it, hold u (du/dt = 0, the core told here), or send the reference's own command
    # (self._held_du; the core was told by whoever made it: an idle network source)
    STEP, HOLD, HELD = 0, 1, 2

    def _begin(self, v: tuple) -> None:
        """With a pluggable reference: before sample v is taken (a network source forgets a run the rig
        restarted)."""

    def _before_publish(self, seq: int, t: float) -> None:
        """With a pluggable reference: after the command is made, before it goes out (a network source's plug-in
        request, which in lockstep must be made before the rig gets this answer)."""

    def _step(self, v: tuple, now: int) -> None:
        """The tick's second half, for the sample v (_sample's): the reference, the core's step on it (the compiled
        tick when there is one), the command, the record; ``now``: the loop's clock (ns) for the neighbours'
        freshness. The reference is this daemon's own, P^{r,in} = -sum_j P_j^{r,out} of the neighbours at this
        sample's time (service.core.interaction) or the local reference while they are not fresh (config
        local_reference_W; none fresh: hold), unless a subclass plugs its own in (self._reference(v, now) ->
        (P^{r,in} W, its rate W/s, STEP / HOLD / HELD): a network source's share formed from the grid sample,
        service.daemon.netsource), with the _begin and _before_publish hooks around it."""
        fast = self._fast
        t_control = _now_ns()
        seq, t = v[0], v[1]
        plugged = self._reference
        if plugged is None:
            self._take_sample(v)
            stale_s, horizon_s = self.cfg.neighbour_stale_s, self.cfg.neighbour_extrapolate_s
            stale_ns = int(stale_s * 1e9)
            P_in = P_in_dot = 0.0
            fresh = True
            for nb in self.neighbours:
                if not nb.fresh(now, stale_ns):
                    fresh = False
                if nb.alive is not nb.alive_seen:
                    self._neighbour_event(nb, t)
                # P^{r,in} = -sum_j P_j^{r,out} at this sample's time (service.core.interaction)
                P_in -= _outgoing_power_at(t, nb.t, nb.P, nb.P_dot, stale_s, horizon_s)
                P_in_dot -= nb.P_dot
            self.reference = "neighbours" if fresh else "none"
            local = self.cfg.local_reference_W
            if not fresh and local is not None:  # flagged in status
                P_in = -v[3] * v[5] if local == "measured" else -local
                P_in_dot, fresh = 0.0, True
                self.reference = "local"
            stepped = self.state == "active" and fresh
            held = False
        else:
            self._begin(v)
            self._take_sample(v)
            P_in, P_in_dot, what = plugged(v, now)
            stepped, held = what == 0, what == 2  # STEP, HELD
        rec = self.recorder
        if stepped and fast is not None:  # the compiled core: the lines below, in C, in one call (_tick_writer)
            cmd, du, du_next, limited, late, P_out, Qdot_out, dropped = fast.step(seq, t, v[2], v[3], v[4], v[5],
                                                                                  P_in, P_in_dot)
            if dropped:
                rec.dropped_group(0)
        else:
            if stepped:
                du, du_next, limited, late, P_out, Qdot_out = self.core.step_values(seq, t, v[2], v[3], v[4], v[5],
                                                                                    P_in, P_in_dot)
            else:
                if held:  # the reference's own command (an idle network source's), the core told already
                    du = self._held_du
                else:  # inactive, or no fresh reference: hold the source voltage
                    du = 0.0
                    self.core.hold(seq)
                du_next, limited = 0.0, False
                late, P_out = False, None
            cmd = _CMD_PACK(_CMD_MAGIC, _VERSION, seq, t, du, du_next, limited)
            self._remember(seq, v[4], du)
            if rec is not None:  # values only: encoding and I/O happen in the recorder's process
                # meas, z_in and cmd in one ring slot (RingRecorder groups)
                rec.offer_group(0, t, *v, seq, t, P_in, P_in_dot, stepped, seq, t, du, du_next, limited)
        if plugged is not None:
            self._before_publish(seq, t)
        t_put = _now_ns()
        self.control_ns = t_put - t_control  # LoopStats "control_us"
        self.cmd_pub.put(cmd)
        self.put_ns = _now_ns() - t_put  # the transport's share of the tick (LoopStats "publish_us")
        self.last_cmd = (seq, t, du, du_next, limited)
        if late:
            self.late_ticks += 1
        if self._ilim_out is not None and stepped and self._ilim_out.i_limited:
            self.current_limited_ticks += 1
        if P_out is not None:
            self._feasibility(t, P_out, Qdot_out)
        self._rarer_work(t, stepped and P_out is not None)

    def _rarer_work(self, t: float, estimated: bool) -> None:
        """The rarer work, on different ticks (each costs a few us; on one tick together they made its 99th
        percentile): interaction every _z_every ticks from 0, the estimator record (when this tick stepped with an
        estimate: ``estimated``) every log_est_every from half of that, the loop record every 1000 from 1."""
        n = self.stats.ticks
        rec = self.recorder
        if rec is not None:
            if n % 1000 == 1:
                st = self.stats
                rec.offer(self.t_loop, t, (t, n, st.overruns, st.no_new_sample, st.missing_samples,
                                           st.window_exec_max, st.window_period_max))
                st.window_exec_max = st.window_period_max = 0
                rx = sum(self.rx_rejected.values())
                if rx != self._rx_logged:  # frames refused on receipt, summarised (at most one event a 1000 ticks)
                    rec.offer(self.t_ev, t, (t, max(self._last_seq, 0), "reject",
                                             f"{rx - self._rx_logged} measurements refused on receipt "
                                             f"(last: {self.last_reject})"))
                    self._rx_logged = rx
            if estimated and n % self._est_every == self._est_phase:
                rec.offer(self.t_est, t, (t, *self.core.est_record()))
        if n % self._z_every == 0 and self.core.out.est is not None:
            self._publish_z(t)

    def _box(self, window: int) -> tuple | None:
        """The neighbours' forecast boxes for this window, summed (W, W/s), once every neighbour announced it."""
        lo = hi = dlo = dhi = 0.0
        for nb in self.neighbours:
            b = nb.box(window)
            if b is None:
                return None
            lo, hi, dlo, dhi = lo + b[0], hi + b[1], dlo + b[2], dhi + b[3]
        return (lo, hi, dlo, dhi) if self.neighbours else None

    def _feasibility(self, t: float, P_out: float, Qdot_out: float) -> None:
        """Run-time check of the outgoing rates P^{r,out} (W) and Qdot^{r,out} (W/s) at the port against this
        window's incoming range (paper Eqn FeasibilityConds), from the neighbours' boxes announced for it."""
        k = int(t // self.cfg.forecast_window_s)
        if k != self._window:
            self._window = k
            self._nb_news = True  # the range for k may have come before k started
        if self._nb_news:
            self._nb_news = False
            if self._zin_window != k and (box := self._box(k)) is not None:
                self.feas.set_range(k, incoming_range(*box, self._tau_p))
                self._zin_window = k
        self.feas.update(t, P_out, Qdot_out)

    def _publish_z(self, t: float) -> None:
        P, P_dot, Qdot, z0, z1 = self.core.interaction()
        fc = self.forecaster.result if self.forecaster is not None else None
        if fc is not None and fc[0] >= self._window:  # the forecast Z^{r,out} of the current or the next window
            f = fc[1]
            w, rng = fc[0], (f.P_lo, f.P_hi, f.P_dot_lo, f.P_dot_hi)
        else:  # none yet: the present value is the range
            w, rng = max(self._window, 0), (P, P, P_dot, P_dot)
        self._z_seq += 1
        vals = (self._z_seq, t, P, P_dot, Qdot, z0, z1, w, *rng)
        self.z_pub.put(Z.encode(*vals))
        if self.recorder is not None:
            self.recorder.offer(self.t_zout, t, vals)

    # ---------------------------------------------------------------- queries (query thread)
