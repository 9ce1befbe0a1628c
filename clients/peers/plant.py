"""Hardware-in-the-loop plant as a Zenoh peer (energyctl plant): the plant model sampled, measured and driven by
the controller's commands over the bus."""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from array import array
from pathlib import Path
from queue import Empty

import numpy as np

from clients.machine import ProcessCpu, StealMeter
from clients.peers.common import matched, wait_alive
from schemas.codec import CMD, MEAS, PLANT, DecodeError
from schemas.component import PlantPeerConfig
from service.daemon.bus import close_session, key, open_session, publisher, queued
from service.metrics import compute_metrics, max_dev_pct
from service.plant.rig import RigModel
from service.sim import profile_events, trace_divergence

PLANT_TRACE = ("t", "i", "v", "u", "i_load", "P_l", "i_meas", "v_meas", "u_meas", "i_load_meas", "du_dt",
               "du_dt_applied", "y_z_true", "y_ref_true")


def _trace_recorder(cfg: PlantPeerConfig, t_meas: str, t_cmd: str, t_plant: str):
    """The plant's trace (measurements, commands, true state) through a recorder process."""
    from service.logio.ring import RingRecorder

    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    topics = {t_meas: ("energyctl.Measurement", MEAS), t_cmd: ("energyctl.Command", CMD),
              t_plant: ("energyctl.Plant", PLANT)}
    return RingRecorder(out, topics, {"plant_config": {"json": cfg.model_dump_json()}})


class StampedInbox:
    """The realtime plant's command inbox: items (arrival monotonic ns, payload) from ``queued``, stamped by the
    subscriber's callback as they arrive. A command counts for a period if it arrived by that period's instant,
    whenever this process gets to read it: after a stall of the plant's own thread the queue holds commands that
    arrived in time (a converter's modulator would have had them), and reading the clock instead charged the
    controller with the rig's stall. The queue is in arrival order, so the first item stamped after the instant
    is held back (``held``) and everything behind it waits with it for a later period."""

    def __init__(self, q):
        self.q = q
        self.held = None

    def offer(self, item, deadline_ns: int, arrive) -> bool:
        """Hand ``item`` to ``arrive`` if it arrived by ``deadline_ns``; else hold it and return False."""
        if item[0] > deadline_ns:
            self.held = item
            return False
        arrive(item)
        return True

    def drain(self, deadline_ns: int, arrive) -> None:
        """Hand over, in order, everything queued that arrived by ``deadline_ns`` (the held item first)."""
        if self.held is not None:
            item, self.held = self.held, None
            if not self.offer(item, deadline_ns, arrive):
                return
        get = self.q.get_nowait
        while True:
            try:
                item = get()
            except Empty:
                return
            if not self.offer(item, deadline_ns, arrive):
                return


def rig_on_time_misses(sent_on_time, answered_in_time, samples: int, d: int) -> dict:
    """Of the samples j whose own sending and whose command's period j + d both found this stand-in on time
    (within half a period of the instant), how many were not answered in time: the misses that are the controller's
    and the transport's, not the rig's own stalls. Samples whose period fell after the run are not counted."""
    m = max(0, samples - d)
    sent = np.frombuffer(bytes(sent_on_time[:samples]), dtype=np.uint8).astype(bool)
    ok = sent[:m] & sent[d:d + m]
    answered = np.frombuffer(bytes(answered_in_time[:m]), dtype=np.uint8).astype(bool)
    return {"rig_on_time_samples": int(ok.sum()), "missed_or_late_rig_on_time": int((ok & ~answered).sum())}


class PlantRig:
    """One run of the plant stand-in: the plant model, its sensor and load, the bus, and what the run counts.

    ``run()`` connects (waits for the controller and the peers in ``wait_for``), then samples for
    ``cfg.duration_s``: lockstep waits for each sample's command (simulated time); realtime samples on the wall
    clock, from the controller's first answer on, and applies commands on a fixed schedule (CommandSchedule).
    It returns metrics, latency and counters (and writes ``cfg.out``)."""

    def __init__(self, cfg: PlantPeerConfig, stop: threading.Event, log=sys.stderr):
        self.cfg, self.stop, self.log = cfg, stop, log
        self.lockstep = cfg.pacing == "lockstep"
        self.T = 1.0 / cfg.sample_rate_hz
        # the plant side, as the offline loop runs it (service.sim): lockstep applies each answer through the same
        # delay line and schedule
        self.rig = RigModel(cfg.plant, cfg.load, cfg.disturbance, cfg.sensor, cfg.seed, cfg.base_dir, self.T,
                            cfg.plant_step_s, cfg.delay_samples, realtime=not self.lockstep,
                            apply_delay_samples=cfg.realtime_apply_delay_samples)
        self.load, self.plant, self.sched = self.rig.load, self.rig.plant, self.rig.sched
        self.N = N = int(round(cfg.duration_s / self.T))
        self.t_meas, self.t_cmd, self.t_plant = (key(cfg.prefix, cfg.controller_id, leaf)
                                                 for leaf in ("meas", "cmd", "plant"))
        self.timeout_ns = int(cfg.lockstep_timeout_s * 1e9)
        self.period_ns = int(round(self.T * 1e9))
        self.spin_ns = int(cfg.realtime_spin_us * 1e3)
        # the trace, PLANT_TRACE's columns row after row: 112 B a sample (a list of tuples took 496 B: 18 GB for an
        # hour at 10 kHz)
        self.rows = array("d")
        # missed: samples whose command never arrived (of those whose period is within the run: the commands answering
        # the last d samples of a realtime run act after it, and the plant stops before the last of them arrive);
        # late: arrived after its sampling instant (dropped); planned_periods: periods run on the plan the previous
        # command carried (its du_dt_next), its successor missing; stale_periods: periods with neither (u held)
        # plant_late_samples: realtime samples this plant sent more than half a period after their instant
        self.counters = {"samples": 0, "commands": 0, "timeouts": 0, "missed": 0, "rejected": 0,
                         "plant_late_samples": 0}
        self.send_ns = array("q", bytes(8 * N))
        # realtime: sample k sent within half a period of its instant (this stand-in's own punctuality), and the
        # command answering sample j taken at its period (in time): the controller's share of the misses
        self.sent_on_time, self.answered_in_time = bytearray(N), bytearray(N)
        self.arrived = bytearray(N)  # a command answering sample j came (in time or not)
        self.lat_ns = array("q")
        self.rec = self.pub = self.sub = self.cmd_q = self.inbox = None
        self.cpu = self.host = None

    # ---------------------------------------------------------------- the run
    def run(self) -> dict:
        cfg = self.cfg
        rec = self.rec = _trace_recorder(cfg, self.t_meas, self.t_cmd, self.t_plant) if cfg.out else None
        if rec is not None:
            rec.wait_ready()  # its start-up would otherwise compete with the first samples
        session = None
        try:
            session = open_session(cfg.zenoh)
            self.connect(session)
            if cfg.start_delay_s:
                self.stop.wait(cfg.start_delay_s)
            self.sample()
        except BaseException:
            if rec is not None:  # keep what was recorded
                rec.close()
            raise
        finally:
            if session is not None:
                close_session(session)
        return self.result()

    def connect(self, session) -> None:
        """Publisher and command subscriber; wait until the controller and the peers in wait_for are up and the
        measurements reach a subscriber."""
        cfg, stop = self.cfg, self.stop
        self.pub = publisher(session, self.t_meas)
        self.sub, self.cmd_q = queued(session, self.t_cmd)
        self.inbox = StampedInbox(self.cmd_q)
        for peer in [cfg.controller_id, *cfg.wait_for]:
            if not wait_alive(session, key(cfg.prefix, peer, "alive"), 15.0, stop):
                raise RuntimeError(f"{peer!r} not alive on the bus within 15 s")
        if not matched(self.pub, 15.0, stop):
            raise RuntimeError(f"no subscriber for {self.t_meas} within 15 s, though {cfg.controller_id!r} is alive")

    def sample(self) -> None:
        """The sampling loop: N samples, or until stop."""
        cfg, plant, sched, rec, pub = self.cfg, self.plant, self.sched, self.rec, self.pub
        sample, command, take, advance = self.rig.sample, self.rig.command, self.rig.take, self.rig.advance
        counters, send_ns, rows = self.counters, self.send_ns, self.rows
        sent_on_time, answered_in_time = self.sent_on_time, self.answered_in_time
        t_meas, t_cmd, t_plant = self.t_meas, self.t_cmd, self.t_plant
        poll_until, await_answer, stop = self.poll_until, self.await_answer, self.stop
        N, lockstep, period_ns = self.N, self.lockstep, self.period_ns
        R, v_ref = cfg.plant.R_ohm, cfg.v_ref_V
        now_ns = time.monotonic_ns
        next_ns = now_ns() + period_ns
        # the CPU budget over the samples: this process's share and how busy the machine's CPUs were (the stack's
        # three processes, their Zenoh threads and recorders, and anything else running)
        cpu = self.cpu = ProcessCpu().start()
        host = self.host = StealMeter().start()
        for k in range(N):
            if stop.is_set():
                break
            if not lockstep:  # wall-clock pacing against absolute time
                poll_until(next_ns)
                next_ns += period_ns
            t = plant.t
            s = sample(k)
            send_ns[k] = now_ns()
            if not lockstep and k > 0 and send_ns[k] - (next_ns - period_ns) > period_ns // 2:
                counters["plant_late_samples"] += 1  # this stand-in missed its own instant (the VM stalled it)
            else:
                sent_on_time[k] = 1
            pub.put(MEAS.encode(k, t, s.i, s.v, s.u, s.i_load))
            counters["samples"] += 1
            du_for_k = du_next = math.nan
            if lockstep:  # through the loop delay, as offline: a missing answer is the previous one's plan, or a hold
                r = await_answer(k)
                if r is None:
                    counters["timeouts"] += 1
                    r_apply = command(k, None)
                else:
                    du_for_k, du_next = r
                    r_apply = command(k, du_for_k, du_next)
            else:
                if k == 0:
                    # arm: the converter is enabled by the controller's first answer, and the sampling clock
                    # starts then (the stack's first round trips take 1-3 ms while its background work starts
                    # up; on the clock they left the first periods uncontrolled and the LC pair ringing)
                    r = await_answer(0)
                    if r is None:
                        counters["timeouts"] += 1
                    else:
                        sched.arrive(0, *r)
                    next_ns = now_ns() + period_ns
                # fixed schedule, as a digital modulator (CommandSchedule): the command answering sample k - d
                # acts over this period, else its predecessor's plan, else u is held
                r_apply, r_latest, fresh = take(k)
                if fresh:
                    du_for_k, du_next = r_latest, sched.prev[1]
                    if k >= sched.d:
                        answered_in_time[k - sched.d] = 1
            P_l, i2 = self.rig.P_l, self.rig.i_load
            pi, pv, pu = plant.i, plant.v, plant.u
            um = plant.u_m(t)
            rows.extend((t, pi, pv, pu, i2, P_l, s.i, s.v, s.u, s.i_load, du_for_k, r_apply,
                         R * pi * pi - (pu + um) * pi, -P_l * v_ref / pv))
            if rec is not None:  # streamed through the recorder process: a killed plant keeps its trace
                rec.offer(t_meas, t, (k, t, s.i, s.v, s.u, s.i_load))
                if du_for_k == du_for_k:  # NaN: no command answered this sample
                    rec.offer(t_cmd, t, (k, t, du_for_k, du_next, False))
                rec.offer(t_plant, t, (t, pi, pv, pu, P_l))
            advance()
        cpu.stop()
        host.stop()

    # ---------------------------------------------------------------- commands
    def take(self, item) -> tuple | None:
        """Decode one queued command (arrival ns, payload) and count it; the command if it answers a sample sent."""
        t_rx, payload = item
        try:
            c = CMD.decode(payload)
        except DecodeError:
            self.counters["rejected"] += 1
            return None
        send_ns = self.send_ns
        if 0 <= c[0] < self.N and send_ns[c[0]]:
            self.lat_ns.append(t_rx - send_ns[c[0]])
            self.counters["commands"] += 1
            self.arrived[c[0]] = 1
            return c
        return None

    def arrive(self, item) -> None:
        """A command that arrived in time for its period: onto the schedule."""
        c = self.take(item)
        if c is not None:
            self.sched.arrive(c[0], c[2], c[3])

    def poll_until(self, deadline_ns: int) -> None:
        """Wait for the next sampling instant, collecting the commands that arrived by it (StampedInbox: by
        their arrival stamps, so that one this process reads late, after its own stall, still counts in time,
        and one stamped after the instant waits for the next period)."""
        inbox, arrive, now_ns, spin_ns = self.inbox, self.arrive, time.monotonic_ns, self.spin_ns
        inbox.drain(deadline_ns, arrive)
        # one sleep, not a wait on the queue: that woke this thread for every command (5000 a second at 5 kHz,
        # each taking the GIL from the callback thread), and the plant sent 45-67 % of its samples late at
        # 5 kHz against 26-53 % so (docs/decisions)
        left = deadline_ns - now_ns()
        if left > spin_ns:
            time.sleep((left - spin_ns) * 1e-9)
        while now_ns() < deadline_ns:  # spin the last realtime_spin_us
            pass
        inbox.drain(deadline_ns, arrive)

    def await_answer(self, k: int) -> tuple | None:
        """Wait (up to lockstep_timeout_s) for the command answering sample k: (du/dt, planned du/dt), None if
        none came."""
        inbox, cmd_q, now_ns = self.inbox, self.cmd_q, time.monotonic_ns
        deadline = now_ns() + self.timeout_ns
        while True:
            item, inbox.held = inbox.held, None
            if item is None:
                try:
                    item = cmd_q.get(timeout=max(1e-6, (deadline - now_ns()) * 1e-9))
                except Empty:
                    return None
            c = self.take(item)
            if c is not None and c[0] == k:
                return c[2], c[3]

    # ---------------------------------------------------------------- the result
    def result(self) -> dict:
        """Metrics of the trace, counters, latency and CPU; closes the trace log (with the metrics in it)."""
        cfg, counters, sched, lat_ns, rec = self.cfg, self.counters, self.sched, self.lat_ns, self.rec
        cols = np.frombuffer(self.rows, dtype=np.float64).reshape(-1, len(PLANT_TRACE)).T
        trace = {f: cols[j].copy() for j, f in enumerate(PLANT_TRACE)}
        diverged = trace_divergence(trace["t"], trace["v"], cfg.v_ref_V, cfg.acceptance)
        metrics = compute_metrics(trace, cfg.v_ref_V, cfg.duration_s, diverged, 0, cfg.acceptance,
                                  profile_events(self.rig.load, self.rig.dist))
        in_run = max(0, counters["samples"] - sched.d)  # samples whose command's period is within the run
        counters["missed"] = in_run - sum(self.arrived[:in_run])
        counters.update(sched.counts)
        if not self.lockstep:
            counters.update(rig_on_time_misses(self.sent_on_time, self.answered_in_time, counters["samples"],
                                               sched.d))
        res = {"metrics": metrics, "counters": counters, "pacing": cfg.pacing, "sample_rate_hz": cfg.sample_rate_hz,
               "cpu": {"plant_pct": self.cpu.pct, "host_busy_pct": self.host.busy_pct,
                       "host_steal_pct": self.host.pct}}
        if lat_ns:
            lat = sorted(lat_ns)
            q = len(lat)
            res["latency_us"] = {"p50": lat[q // 2] / 1e3, "p99": lat[min(q - 1, int(q * 0.99))] / 1e3,
                                 "max": lat[-1] / 1e3, "n": q}
            # settled regulation: within +-2 % after 50 ms
            res["max_dev_after_50ms_pct"] = max_dev_pct(trace["t"], trace["v"], 0.05, math.inf, cfg.v_ref_V)
        if rec is not None:
            rec.add_metadata("metrics", {"json": json.dumps(res)})
            rec.close()
            if rec.error:
                print(f"energyctl plant: the trace log is incomplete: {rec.error}", file=self.log)
        res["trace"] = trace
        return res


def run_plant(cfg: PlantPeerConfig, stop: threading.Event, log=sys.stderr) -> dict:
    """Run the plant for cfg.duration_s; returns metrics, latency and counters (and writes cfg.out)."""
    return PlantRig(cfg, stop, log).run()
