"""Hardware-in-the-loop plant and neighbour load as Zenoh peers (energyctl plant / energyctl load)."""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from array import array
from collections import deque
from pathlib import Path
from queue import Empty

import numpy as np

from clients.machine import ProcessCpu, StealMeter
from schemas.codec import CMD, MEAS, PLANT, DecodeError, Z
from schemas.component import LoadPeerConfig, PlantPeerConfig
from service.core.feasibility import announced_window, load_box
from service.daemon.bus import key, latest, open_session, publisher, queued
from service.plant.profiles import Profile
from service.plant.rlc import CommandSchedule, RLCPlant, Sensor, load_current
from service.sim import compute_metrics, substeps

PLANT_TRACE = ("t", "i", "v", "u", "i_load", "P_l", "i_meas", "v_meas", "u_meas", "i_load_meas", "du_dt",
               "du_dt_applied", "y_z_true", "y_ref_true")


def wait_alive(session, key_expr: str, timeout_s: float, stop: threading.Event) -> bool:
    """Block until a liveliness token matching key_expr exists (or timeout / stop)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop.is_set():
        for r in session.liveliness().get(key_expr, timeout=0.5):
            if r.ok is not None:
                return True
        stop.wait(0.05)
    return False


def matched(pub, timeout_s: float, stop: threading.Event) -> bool:
    """Block until the publisher's puts are routed to a subscriber.

    A peer's liveliness token can be seen here before its subscription is routed (a peer answers a liveliness
    query from what it already knows); a sample published before then goes nowhere. (The realtime arm on the
    first answer, in run_plant, is what made sample 0 reliably answered; this only rules out the race.)"""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop.is_set():
        if pub.matching_status.matching:
            return True
        stop.wait(0.01)
    return False


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


def run_plant(cfg: PlantPeerConfig, stop: threading.Event, log=sys.stderr) -> dict:
    """Run the plant for cfg.duration_s; returns metrics, latency and counters (and writes cfg.out)."""
    load = Profile(cfg.load, cfg.base_dir)
    dist = Profile(cfg.disturbance, cfg.base_dir) if cfg.disturbance is not None else None
    plant = RLCPlant(cfg.plant, load, dist)
    sensor = Sensor(cfg.sensor, cfg.seed)
    T = 1.0 / cfg.sample_rate_hz
    n_sub = substeps(T, cfg.plant_step_s)
    N = int(round(cfg.duration_s / T))
    t_meas, t_cmd, t_plant = (key(cfg.prefix, cfg.controller_id, leaf) for leaf in ("meas", "cmd", "plant"))
    rec = _trace_recorder(cfg, t_meas, t_cmd, t_plant) if cfg.out else None
    if rec is not None:
        rec.wait_ready()  # its start-up would otherwise compete with the first samples
    session = None
    try:
        session = open_session(cfg.zenoh)
        pub = publisher(session, t_meas)
        sub, cmd_q = queued(session, t_cmd)
        for peer in [cfg.controller_id, *cfg.wait_for]:
            if not wait_alive(session, key(cfg.prefix, peer, "alive"), 15.0, stop):
                raise RuntimeError(f"{peer!r} not alive on the bus within 15 s")
        if not matched(pub, 15.0, stop):
            raise RuntimeError(f"no subscriber for {t_meas} within 15 s, though {cfg.controller_id!r} is alive")
        if cfg.start_delay_s:
            stop.wait(cfg.start_delay_s)
        # the trace, PLANT_TRACE's columns row after row: 112 B a sample (a list of tuples took 496 B: 18 GB for an
        # hour at 10 kHz)
        rows = array("d")
        # missed: samples whose command never arrived (of those whose period is within the run: the commands answering
        # the last d samples of a realtime run act after it, and the plant stops before the last of them arrive);
        # late: arrived after its sampling instant (dropped); planned_periods: periods run on the plan the previous
        # command carried (its du_dt_next), its successor missing; stale_periods: periods with neither (u held)
        # plant_late_samples: realtime samples this plant sent more than half a period after their instant
        counters = {"samples": 0, "commands": 0, "timeouts": 0, "missed": 0, "rejected": 0, "plant_late_samples": 0}
        send_ns = array("q", bytes(8 * N))
        # realtime: sample k sent within half a period of its instant (this stand-in's own punctuality), and the
        # command answering sample j taken at its period (in time): the controller's share of the misses
        sent_on_time, answered_in_time = bytearray(N), bytearray(N)
        arrived = bytearray(N)  # a command answering sample j came (in time or not)
        lat_ns = array("q")
        delay: deque[float] = deque([0.0] * cfg.delay_samples)
        r_latest = 0.0
        now_ns, sleep = time.monotonic_ns, time.sleep
        lockstep = cfg.pacing == "lockstep"
        timeout_ns = int(cfg.lockstep_timeout_s * 1e9)
        period_ns = int(round(T * 1e9))
        spin_ns = int(cfg.realtime_spin_us * 1e3)
        next_ns = now_ns() + period_ns
        sched = CommandSchedule(0 if lockstep else cfg.realtime_apply_delay_samples)

        def take(item) -> tuple | None:
            t_rx, payload = item
            try:
                c = CMD.decode(payload)
            except DecodeError:
                counters["rejected"] += 1
                return None
            if 0 <= c[0] < N and send_ns[c[0]]:
                lat_ns.append(t_rx - send_ns[c[0]])
                counters["commands"] += 1
                arrived[c[0]] = 1
                return c
            return None

        inbox = StampedInbox(cmd_q)

        def arrive(item) -> None:
            c = take(item)
            if c is not None:
                sched.arrive(c[0], c[2], c[3])

        def poll_until(deadline_ns: int) -> None:
            """Wait for the next sampling instant, collecting the commands that arrived by it (StampedInbox: by
            their arrival stamps, so that one this process reads late, after its own stall, still counts in time,
            and one stamped after the instant waits for the next period)."""
            inbox.drain(deadline_ns, arrive)
            # one sleep, not a wait on the queue: that woke this thread for every command (5000 a second at 5 kHz,
            # each taking the GIL from the callback thread), and the plant sent 45-67 % of its samples late at
            # 5 kHz against 26-53 % so (README)
            left = deadline_ns - now_ns()
            if left > spin_ns:
                sleep((left - spin_ns) * 1e-9)
            while now_ns() < deadline_ns:  # spin the last realtime_spin_us
                pass
            inbox.drain(deadline_ns, arrive)

        def await_answer(k: int) -> tuple | None:
            """Wait (up to lockstep_timeout_s) for the command answering sample k: (du/dt, planned du/dt), None if
            none came."""
            deadline = now_ns() + timeout_ns
            while True:
                item, inbox.held = inbox.held, None
                if item is None:
                    try:
                        item = cmd_q.get(timeout=max(1e-6, (deadline - now_ns()) * 1e-9))
                    except Empty:
                        return None
                c = take(item)
                if c is not None and c[0] == k:
                    return c[2], c[3]

        # the CPU budget over the samples: this process's share and how busy the machine's CPUs were (the stack's
        # three processes, their Zenoh threads and recorders, and anything else running)
        cpu, host = ProcessCpu().start(), StealMeter().start()
        for k in range(N):
            if stop.is_set():
                break
            if not lockstep:  # wall-clock pacing against absolute time
                poll_until(next_ns)
                next_ns += period_ns
            t = plant.t
            P_l = load.value(t)
            i2 = load_current(P_l, plant.v, plant.v_min)
            s = sensor.measure(k, t, plant.i, plant.v, plant.u, i2)
            send_ns[k] = now_ns()
            if not lockstep and k > 0 and send_ns[k] - (next_ns - period_ns) > period_ns // 2:
                counters["plant_late_samples"] += 1  # this stand-in missed its own instant (the VM stalled it)
            else:
                sent_on_time[k] = 1
            pub.put(MEAS.encode(k, t, s.i, s.v, s.u, s.i_load))
            counters["samples"] += 1
            du_for_k = math.nan
            if lockstep:
                r = await_answer(k)
                if r is None:
                    counters["timeouts"] += 1  # no answer: the previous command's plan, else hold the source voltage
                else:
                    sched.arrive(k, *r)
                r_latest, fresh = sched.take(k)
                if fresh:
                    du_for_k = r_latest
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
                r_latest, fresh = sched.take(k)
                if fresh:
                    du_for_k = r_latest
                    if k >= sched.d:
                        answered_in_time[k - sched.d] = 1
            if cfg.delay_samples:
                delay.append(r_latest)
                r_apply = delay.popleft()
            else:
                r_apply = r_latest
            pi, pv, pu = plant.i, plant.v, plant.u
            um = plant.u_m(t)
            rows.extend((t, pi, pv, pu, i2, P_l, s.i, s.v, s.u, s.i_load, du_for_k, r_apply,
                         cfg.plant.R_ohm * pi * pi - (pu + um) * pi, -P_l * cfg.v_ref_V / pv))
            if rec is not None:  # streamed through the recorder process: a killed plant keeps its trace
                rec.offer(t_meas, t, (k, t, s.i, s.v, s.u, s.i_load))
                if du_for_k == du_for_k:  # NaN: no command answered this sample
                    rec.offer(t_cmd, t, (k, t, du_for_k, sched.prev[1], False))
                rec.offer(t_plant, t, (t, pi, pv, pu, P_l))
            plant.advance(r_apply, T, n_sub)
        cpu.stop()
        host.stop()
    except BaseException:
        if rec is not None:  # keep what was recorded
            rec.close()
        raise
    finally:
        if session is not None:
            session.close()
    cols = np.frombuffer(rows, dtype=np.float64).reshape(-1, len(PLANT_TRACE)).T
    trace = {f: cols[j].copy() for j, f in enumerate(PLANT_TRACE)}
    diverged = bool(len(trace["v"]) and not (0.5 * cfg.v_ref_V < trace["v"].min()
                                              and trace["v"].max() < 2 * cfg.v_ref_V))
    metrics = compute_metrics(trace, cfg.v_ref_V, cfg.duration_s, diverged, 0)
    in_run = max(0, counters["samples"] - sched.d)  # samples whose command's period is within the run
    counters["missed"] = in_run - sum(arrived[:in_run])
    counters.update(sched.counts)
    if not lockstep:
        counters.update(rig_on_time_misses(sent_on_time, answered_in_time, counters["samples"], sched.d))
    res = {"metrics": metrics, "counters": counters, "pacing": cfg.pacing, "sample_rate_hz": cfg.sample_rate_hz,
           "cpu": {"plant_pct": cpu.pct, "host_busy_pct": host.busy_pct, "host_steal_pct": host.pct}}
    if lat_ns:
        lat = sorted(lat_ns)
        q = len(lat)
        res["latency_us"] = {"p50": lat[q // 2] / 1e3, "p99": lat[min(q - 1, int(q * 0.99))] / 1e3,
                             "max": lat[-1] / 1e3, "n": q}
        # settled regulation: within +-2 % after 50 ms
        late = trace["t"] >= 0.05
        dev = np.abs(trace["v"][late] - cfg.v_ref_V) / cfg.v_ref_V
        res["max_dev_after_50ms_pct"] = float(dev.max() * 100) if late.any() else None
    if rec is not None:
        rec.add_metadata("metrics", {"json": json.dumps(res)})
        rec.close()
        if rec.error:
            print(f"energyctl plant: the trace log is incomplete: {rec.error}", file=log)
    res["trace"] = trace
    return res


def _plant_clock(payload: bytes) -> tuple[int, float] | None:
    """(seq, t) of a plant sample; None for a payload that is not one."""
    try:
        v = MEAS.decode(payload)
    except DecodeError:
        return None
    return v[0], v[1]


def run_load(cfg: LoadPeerConfig, stop: threading.Event) -> dict:
    """Publish the load's outgoing interaction variable until stop or cfg.duration_s.

    lockstep: one message per plant sample, stamped with its seq and t (deterministic co-simulation);
    realtime: at rate_hz, for the newest plant sample's t (or time since start if no plant is named).
    Qdot_l is published as dP_l/dt, exact for a constant-power load at constant voltage.
    """
    load = Profile(cfg.load, cfg.base_dir)
    session = open_session(cfg.zenoh)
    forecasts: dict[int, tuple[float, float, float, float]] = {}
    W = cfg.window_s

    def forecast(k: int):
        if k not in forecasts:
            forecasts.pop(k - 2, None)
            forecasts[k] = load_box(*load.range_over(k * W, (k + 1) * W), cfg.forecast_margin)
        return forecasts[k]

    sent = 0
    rec = None
    z = [0.0, 0.0]
    last: tuple[float, float, float] | None = None
    try:
        pub = publisher(session, key(cfg.prefix, cfg.id, "z"))
        lockstep = cfg.pacing == "lockstep"
        # lockstep: every plant sample, queued by a callback (one message each); realtime: only the newest, in a
        # ring that Zenoh fills without Python, read once per message sent (a callback per sample took a quarter of a
        # CPU at 2-10 kHz for a 200 Hz publisher: README, "The CPU budget")
        sub, meas_q = None, None
        if cfg.plant_id:
            t_meas = key(cfg.prefix, cfg.plant_id, "meas")
            if lockstep:
                sub, meas_q = queued(session, t_meas)
            else:
                sub = latest(session, t_meas)
        rec, z_topic = None, f"{cfg.prefix}/{cfg.id}/z"
        if cfg.log_dir:
            from datetime import UTC, datetime

            from service.logio.ring import RingRecorder

            stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
            rec = RingRecorder(f"{cfg.log_dir}/{cfg.id}-{stamp}.mcap", {z_topic: ("energyctl.Interaction", Z)},
                               {"config": {"json": cfg.model_dump_json()}})
            rec.wait_ready()
        token = session.liveliness().declare_token(key(cfg.prefix, cfg.id, "alive"))  # ready: announce
        cpu = ProcessCpu().start()
        t_start = time.monotonic()
        period = 1.0 / cfg.rate_hz
        nxt = time.monotonic()
        t_plant, seq_plant = None, 0
        while not stop.is_set() and time.monotonic() - t_start < cfg.duration_s:
            if lockstep:  # wait for the next sample
                try:
                    m = meas_q.get(timeout=0.05)[1] if meas_q is not None else None
                except Empty:
                    m = None
                if m is None or (v := _plant_clock(m)) is None:
                    continue
                seq_plant, t_plant = v
                seq, t = seq_plant, t_plant
            else:
                now = time.monotonic()
                if now < nxt:
                    time.sleep(min(nxt - now, 0.001))
                    continue
                nxt += period
                if sub is not None and (s := sub.try_recv()) is not None and \
                        (v := _plant_clock(s.payload.to_bytes())) is not None:  # the newest sample, if any
                    seq_plant, t_plant = v
                if sub is not None and t_plant is None:
                    continue  # follow the plant's clock once it runs
                seq, t = sent, (t_plant if t_plant is not None else now - t_start)
            P, Pd = load.value(t), load.rate(t)
            if last is not None and t > last[0]:
                z[0] += 0.5 * (t - last[0]) * (P + last[1])
                z[1] += 0.5 * (t - last[0]) * (Pd + last[2])
            last = (t, P, Pd)
            k = announced_window(t, W)
            vals = (seq, t, P, Pd, Pd, z[0], z[1], k, *forecast(k))
            pub.put(Z.encode(*vals))
            if rec is not None:
                rec.offer(z_topic, t, vals)
            sent += 1
        cpu.stop()
        token.undeclare()
        if rec is not None:
            rec.close()
    finally:
        session.close()
    return {"sent": sent, "log": rec.paths if rec is not None else None, "cpu_pct": cpu.pct}
