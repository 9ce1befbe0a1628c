"""The neighbour load as a Zenoh peer (energyctl load): publishes its outgoing interaction variable and the
forecast ranges of the windows it announces."""

from __future__ import annotations

import sys
import threading
import time
from queue import Empty

from clients.machine import ProcessCpu
from schemas.codec import MEAS, DecodeError, Z
from schemas.component import LoadPeerConfig
from service.core.feasibility import announced_window, load_box
from service.daemon.bus import close_session, key, latest, open_session, publisher, queued
from service.plant.profiles import Profile

NO_MEAS_WARN_S = 5.0  # lockstep: no measurement this long after the start is said on stderr (once)


def no_measurement(cfg) -> str:
    """What a lockstep load that has had no measurement says (once), and the likeliest reason."""
    return (f"energyctl load[{cfg.id}]: no measurement on {key(cfg.prefix, cfg.plant_id, 'meas')} in "
            f"{NO_MEAS_WARN_S:g} s: the plant is not running, or it cannot reach this process (peers link to each "
            "other directly, a daemon does not route between them: a peer that listens nowhere is reached only by "
            "the peers it connects to; give every peer a listen endpoint, or connect them all to a router)")


def _plant_clock(payload: bytes, last: tuple[int, float] | None) -> tuple[int, float] | None:
    """(seq, t) of the plant's next sample after ``last`` (the previous one followed, or None): later in seq and in
    t, or seq 0 (the plant restarted); None for a payload that is not a measurement, or one that is not the plant's
    next (a duplicate, a stray or corrupted frame on its key: the controller rejects those, and a lockstep load that
    answered them sent it z messages of a stale seq and time, which it then waited for)."""
    try:
        v = MEAS.decode(payload)
    except DecodeError:
        return None
    if last is not None and v[0] != 0 and (v[0] <= last[0] or v[1] <= last[1]):
        return None
    return v[0], v[1]


class LoadPeer:
    """One run of the neighbour load: ``run()`` publishes until stop or cfg.duration_s (see run_load)."""

    def __init__(self, cfg: LoadPeerConfig, stop: threading.Event):
        self.cfg, self.stop = cfg, stop
        self.load = Profile(cfg.load, cfg.base_dir)
        self.lockstep = cfg.pacing == "lockstep"
        self.forecasts: dict[int, tuple[float, float, float, float]] = {}
        self.sent = 0
        self.z = [0.0, 0.0]  # the integrals of P and dP/dt since the first message
        self.last: tuple[float, float, float] | None = None
        self.pub = self.rec = None
        self.z_topic = f"{cfg.prefix}/{cfg.id}/z"

    def forecast(self, k: int):
        """The announced load range of window k (kept for the current and the previous window)."""
        if k not in self.forecasts:
            W = self.cfg.window_s
            self.forecasts.pop(k - 2, None)
            self.forecasts[k] = load_box(*self.load.range_over(k * W, (k + 1) * W), self.cfg.forecast_margin)
        return self.forecasts[k]

    def subscribe(self, session):
        """(subscriber, queue) for the plant's samples: lockstep, every sample, queued by a callback (one message
        each); realtime, only the newest, in a ring that Zenoh fills without Python, read once per message sent (a
        callback per sample took a quarter of a CPU at 2-10 kHz for a 200 Hz publisher: docs/limits.md, "The CPU
        budget"). (None, None) when no plant is named."""
        cfg = self.cfg
        if not cfg.plant_id:
            return None, None
        t_meas = key(cfg.prefix, cfg.plant_id, "meas")
        if self.lockstep:
            return queued(session, t_meas)
        return latest(session, t_meas), None

    def open_recorder(self):
        """The recorder of the published messages, when cfg.log_dir is set (else None)."""
        cfg = self.cfg
        if not cfg.log_dir:
            return None
        from datetime import UTC, datetime

        from service.logio.ring import RingRecorder

        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        rec = RingRecorder(f"{cfg.log_dir}/{cfg.id}-{stamp}.mcap", {self.z_topic: ("energyctl.Interaction", Z)},
                           {"config": {"json": cfg.model_dump_json()}})
        rec.wait_ready()
        return rec

    def publish(self, seq: int, t: float) -> None:
        """One interaction message for time t: P_l, its rate, their integrals, the window's announced range."""
        load, z, last = self.load, self.z, self.last
        P, Pd = load.value(t), load.rate(t)
        if last is not None and t > last[0]:
            z[0] += 0.5 * (t - last[0]) * (P + last[1])
            z[1] += 0.5 * (t - last[0]) * (Pd + last[2])
        self.last = (t, P, Pd)
        k = announced_window(t, self.cfg.window_s)
        vals = (seq, t, P, Pd, Pd, z[0], z[1], k, *self.forecast(k))
        self.pub.put(Z.encode(*vals))
        if self.rec is not None:
            self.rec.offer(self.z_topic, t, vals)
        self.sent += 1

    def run(self) -> dict:
        cfg, stop, lockstep = self.cfg, self.stop, self.lockstep
        session = open_session(cfg.zenoh)
        try:
            self.pub = publisher(session, key(cfg.prefix, cfg.id, "z"))
            sub, meas_q = self.subscribe(session)
            self.rec = self.open_recorder()
            token = session.liveliness().declare_token(key(cfg.prefix, cfg.id, "alive"))  # ready: announce
            cpu = ProcessCpu().start()
            t_start = time.monotonic()
            period = 1.0 / cfg.rate_hz
            nxt = time.monotonic()
            plant = None  # (seq, t) of the plant's sample followed last
            told = False
            while not stop.is_set() and time.monotonic() - t_start < cfg.duration_s:
                if lockstep:  # wait for the next sample
                    try:
                        m = meas_q.get(timeout=0.05)[1] if meas_q is not None else None
                    except Empty:
                        m = None
                        if plant is None and not told and time.monotonic() - t_start > NO_MEAS_WARN_S:
                            told = True
                            print(no_measurement(cfg), file=sys.stderr, flush=True)
                    if m is None or (v := _plant_clock(m, plant)) is None:
                        continue
                    plant = v
                    seq, t = plant
                else:
                    now = time.monotonic()
                    if now < nxt:
                        time.sleep(min(nxt - now, 0.001))
                        continue
                    nxt += period
                    if sub is not None and (s := sub.try_recv()) is not None and \
                            (v := _plant_clock(s.payload.to_bytes(), plant)) is not None:  # the newest sample, if any
                        plant = v
                    if sub is not None and plant is None:
                        continue  # follow the plant's clock once it runs
                    seq, t = self.sent, (plant[1] if plant is not None else now - t_start)
                self.publish(seq, t)
            cpu.stop()
            token.undeclare()
            if self.rec is not None:
                self.rec.close()
        finally:
            close_session(session)
        return {"sent": self.sent, "log": self.rec.paths if self.rec is not None else None, "cpu_pct": cpu.pct}


def run_load(cfg: LoadPeerConfig, stop: threading.Event) -> dict:
    """Publish the load's outgoing interaction variable until stop or cfg.duration_s.

    lockstep: one message per plant sample, stamped with its seq and t (deterministic co-simulation);
    realtime: at rate_hz, for the newest plant sample's t (or time since start if no plant is named).
    Qdot_l is published as dP_l/dt, exact for a constant-power load at constant voltage.
    """
    return LoadPeer(cfg, stop).run()
