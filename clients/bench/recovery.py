"""Fault injection: the live stack as processes that can be killed, stopped, resumed and restarted.

``Rig`` starts controller, load and plant (and optionally a router between them) on a free loopback
port, lets a test or a bench signal any of them, and reads the controller's status and log.
``recovery`` is ``energyctl bench recovery``: after the plant or the neighbour comes back, how long
(in plant time; lockstep, or realtime with ``--realtime``) until v is within +-2 % of v_ref again for good.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from clients.live import Processes, _toml, child_env, configs_from_scenario, port_open, wait_until
from clients.query import QueryError, ask
from schemas.component import ZenohConfig, merge_tables
from schemas.scenario import Scenario
from service.daemon.bus import free_tcp_port
from service.logio.reader import messages as read_messages
from service.metrics import BAND_SETTLE, back_in_band, max_dev_pct


class Rig:
    """Controller ``source``, neighbour ``load`` and ``plant`` (and ``router`` if asked) as child processes."""

    def __init__(self, scn: Scenario, workdir: str | Path | None = None, *, lockstep: bool = True,
                 router: bool = False, rate_hz: float | None = None, duration_s: float | None = None,
                 comp: dict | None = None, plant: dict | None = None, load: dict | None = None,
                 controller_delay: int | None = None):
        self.dir = Path(workdir or tempfile.mkdtemp(prefix="energyctl-faults-"))
        self.dir.mkdir(parents=True, exist_ok=True)
        self.ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.plant_out = self.dir / "plant.mcap"
        c, p, ld = configs_from_scenario(scn, self.ep, lockstep, rate_hz, controller_delay, out=str(self.plant_out),
                                         duration_s=duration_s)
        self.router = router
        if router:  # everyone is a client of the router, which is the one that listens
            for d in (c, p, ld):
                d["zenoh"] = {"mode": "client", "connect": [self.ep]}
        # a neighbour that comes back may miss the sample it is waited for: stall one tick briefly, not 2 s
        c["loop"]["lockstep_timeout_s"] = 0.3
        self.cfg = {"daemon": merge_tables(c, comp or {}), "plant": merge_tables(p, plant or {}),
                    "load": merge_tables(ld, load or {})}
        self.paths = {}
        for name, d in self.cfg.items():
            self.paths[name] = self.dir / f"{name}.toml"
            self.paths[name].write_text(_toml(d))
        self.stats_path = self.dir / "daemon-status.json"
        self.env = child_env()
        self.procs = Processes()
        self._zq = ZenohConfig(mode="client" if router else "peer", connect=[self.ep])
        self._session = None

    # ---------------------------------------------------------------- processes
    def start(self, name: str, popen: dict | None = None, **overrides) -> subprocess.Popen:
        """Start (or start again) one role; keyword overrides change its config for this start; ``popen``
        passes keyword arguments to subprocess.Popen (e.g. a preexec_fn that sets a resource limit)."""
        if name == "router":
            p = self.procs.start("router", ["router", "--listen", self.ep], env=self.env)
            if not wait_until(lambda: port_open(self.ep), 15.0):
                raise RuntimeError(f"the router did not listen on {self.ep} within 15 s")
            return p
        path = self.paths[name]
        if overrides:
            path = self.dir / f"{name}-{len(self.procs.procs)}.toml"
            path.write_text(_toml(merge_tables(self.cfg[name], overrides)))
        args = {"daemon": ["run", "--config", str(path), "--stats-out", str(self.stats_path)],
                "load": ["load", "--config", str(path)],
                "plant": ["plant", "--config", str(path), "--json"]}[name]
        return self.procs.start(name, args, env=self.env, **(popen or {}))

    def proc(self, name: str) -> subprocess.Popen:
        return [p for n, p in self.procs.procs if n == name][-1]

    def signal(self, name: str, sig: int) -> None:
        self.proc(name).send_signal(sig)
        if sig == signal.SIGKILL:
            self.proc(name).wait(5.0)

    def plant_result(self, timeout_s: float = 120.0) -> dict:
        """Wait for the newest plant to finish; its JSON result (metrics, counters)."""
        p = self.proc("plant")
        so, se = p.communicate(timeout=timeout_s)
        if p.returncode != 0:
            raise RuntimeError(f"plant failed ({p.returncode}): {se.strip()[-800:]}")
        return json.loads(so.strip().splitlines()[-1])

    def close(self) -> dict:
        if self._session is not None:
            self._session.close()
            self._session = None
        return self.procs.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---------------------------------------------------------------- observing
    def session(self):
        """The rig's own Zenoh session on the stack's endpoint (one for the rig's life): queries, and whatever a test
        or a bench publishes or subscribes to beside the stack."""
        if self._session is None:
            from service.daemon.bus import open_session

            self._session = open_session(self._zq)
        return self._session

    def status(self, timeout_s: float = 1.0) -> dict | None:
        """The controller's status, or None if it does not answer."""
        try:
            return ask(self.session(), "energyctl", "source", "status", timeout_s=timeout_s)
        except (QueryError, ConnectionError):
            return None

    def wait_status(self, pred, timeout_s: float) -> dict | None:
        """The first status for which pred(status) holds, or None after timeout_s."""
        found: list[dict] = []

        def check() -> bool:
            st = self.status()
            if st is not None and pred(st):
                found.append(st)
                return True
            return False

        wait_until(check, timeout_s, every_s=0.01)
        return found[0] if found else None

    def sample_t(self, st: dict) -> float:
        return (st.get("last_sample") or {}).get("t", -1.0)

    def daemon_log(self) -> Path | None:
        logs = sorted(Path(self.cfg["daemon"].get("log_dir") or self.dir).glob("source-*.mcap"))
        return logs[-1] if logs else None


def recovery_after(t: np.ndarray, v: np.ndarray, t_back: float, v_ref: float) -> float | None:
    """Seconds from t_back until v is within +-2 % of v_ref to the end of the trace (None: not by the end)."""
    return back_in_band(t, v, t_back, math.inf, v_ref, BAND_SETTLE)


def recovery(scn: Scenario, workdir: str | None = None, progress=print, realtime: bool = False,
             rate_hz: float | None = None, controller_delay: int | None = None) -> dict:
    """``energyctl bench recovery``: kill -9 the plant and the neighbour, bring them back, time the recovery.
    realtime: wall-clock pacing at rate_hz with a controller_delay-sample schedule, instead of lockstep."""
    res: dict = {"scenario": scn.name,
                 "mode": f"realtime at {rate_hz:g} Hz, {controller_delay}-sample schedule (times are plant time)"
                 if realtime else "lockstep (times are plant time)"}
    v_ref = scn.controller.v_ref_V
    base = Path(workdir or tempfile.mkdtemp(prefix="energyctl-recovery-"))
    pace = {"lockstep": not realtime, "rate_hz": rate_hz if realtime else None,
            "controller_delay": controller_delay if realtime else None}

    # 1. the plant dies and a new one starts (its seq restarts at 0: the controller re-initialises)
    progress("plant: kill -9 at t = 0.15 s, then a new plant process ...")
    with Rig(scn, base / "plant", duration_s=1.0, **pace) as rig:
        rig.start("daemon")
        rig.start("load")
        rig.start("plant")
        st = rig.wait_status(lambda s: rig.sample_t(s) >= 0.15, 120.0)
        if st is None:
            raise RuntimeError("the first plant never reached t = 0.15 s")
        rig.signal("plant", signal.SIGKILL)
        t_kill = time.monotonic()
        st = rig.wait_status(lambda s: s["state"] == "degraded", 10.0)
        res["plant_killed_to_degraded_ms"] = (time.monotonic() - t_kill) * 1e3 if st else None
        t0 = time.monotonic()
        rig.start("plant", duration_s=0.3, out=str(rig.dir / "plant-2.mcap"))
        st = rig.wait_status(lambda s: s["state"] == "active" and s["plant_restarts"] >= 1, 60.0)
        res["plant_start_to_active_ms"] = (time.monotonic() - t0) * 1e3 if st else None
        r2 = rig.plant_result()
        settle = r2["metrics"]["settle_s"]
        res["plant_restart_recovery_ms"] = None if settle is None else settle * 1e3
        res["plant_restart_counters"] = r2["counters"]

    # 2. the neighbour dies and comes back; with and without a local reference meanwhile
    # (realtime falls back to the measured load power by default: there "hold" is not run)
    labels = (("hold", None), ("measured", "measured"), ("constant_1200W", 1200.0))
    for label, local in labels[1:] if realtime else labels:
        progress(f"neighbour ({label}): kill -9 the load at t = 0.15 s, back at t = 0.30 s ...")
        comp = {"local_reference_W": local} if local is not None else {}
        # the new load process takes 1-2 s of wall time to start; the plant must still be running when it is back
        # (in lockstep without a neighbour to wait for, plant time runs faster than wall time)
        with Rig(scn, base / f"load-{label}", duration_s=4.0, comp=comp, **pace) as rig:
            rig.start("daemon")
            rig.start("load")
            rig.start("plant")
            if rig.wait_status(lambda s: rig.sample_t(s) >= 0.15, 120.0) is None:
                raise RuntimeError("the plant never reached t = 0.15 s")
            rig.signal("load", signal.SIGKILL)
            st = rig.wait_status(lambda s: rig.sample_t(s) >= 0.30, 120.0)
            away = st["reference"] if st else None
            rig.start("load")
            r = rig.plant_result()
            rig.close()
            log = rig.daemon_log()
            events = read_messages(log, "/events") if log else []
            gone = [e["t"] for e in events if e["kind"] == "neighbour_gone"]
            t_gone = gone[0] if gone else None
            # its return: an alive event after it went (the first one, at start, is not a return)
            back = [e["t"] for e in events if e["kind"] == "neighbour_alive" and t_gone is not None
                    and e["t"] >= t_gone]
            tr = read_messages(rig.plant_out, "/plant")
            t = np.array([m["t"] for m in tr])
            v = np.array([m["v"] for m in tr])
            t_back = back[0] if back else None
            rec = recovery_after(t, v, t_back, v_ref) if t_back is not None else None
            res[f"neighbour_{label}"] = {
                "gone_at_s": t_gone, "back_at_s": t_back, "reference_while_away": away,
                "max_dev_while_away_pct": max_dev_pct(t, v, t_gone, t_back, v_ref) if t_gone and t_back else None,
                "recovery_ms": None if rec is None else rec * 1e3, "counters": r["counters"]}
    return res
