"""energyctl bench latency: measurement -> daemon -> command round trip vs a bare Zenoh echo, same run.

Three processes on loopback: the daemon (sample trigger, no neighbours), a bare echo (returns each
measurement payload unchanged) and this client, which alternates between the two targets so both see
the same machine load. Reports both round-trip distributions, their p50/p99 ratios, and the daemon's
own per-tick execution time: whole, its command put (Zenoh), the rest (compute), and of that the control
computation alone (control: from the accepted sample to the command ready to put).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from queue import Empty

from clients.live import COME_UP_S, Processes, _toml, wait_until
from clients.machine import StealMeter
from schemas.codec import MEAS
from schemas.component import ZenohConfig
from service.daemon.bus import free_tcp_port, key, open_session, publisher, queued
from service.priority import set_cpus

ECHO = """
import sys, json, time, zenoh
ep = sys.argv[1]
c = zenoh.Config(); c.insert_json5("mode", '"peer"'); c.insert_json5("scouting/multicast/enabled", "false")
c.insert_json5("connect/endpoints", json.dumps([ep]))
s = zenoh.open(c)
pub = s.declare_publisher("bench/echo/cmd", express=True)
sub = s.declare_subscriber("bench/echo/meas", zenoh.handlers.RingChannel(1))
tok = s.liveliness().declare_token("bench/echo/alive")
while True:
    m = sub.recv()
    pub.put(m.payload.to_bytes())
"""


def percentiles(xs: list[int]) -> dict:
    xs = sorted(xs)
    n = len(xs)
    return {"p50_us": xs[n // 2] / 1e3, "p99_us": xs[min(n - 1, int(n * 0.99))] / 1e3, "max_us": xs[-1] / 1e3, "n": n}


def bench_latency(n: int = 3000, wait: str = "block", gap_s: float = 5e-4, cpus: list[int] | None = None) -> dict:
    """Round trips plant-side -> daemon -> back, alternated with the same payload through a bare Zenoh echo. cpus:
    the CPUs the daemon and the echo each keep to (the daemon's `cpus` config; default any)."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="energyctl-bench-"))
    comp = {"id": "bench", "zenoh": {"mode": "peer", "listen": [ep]}, "neighbours": [],
            "loop": {"rate_hz": 1000.0, "trigger": "sample", "wait": wait}, "delay_samples": 1,
            "interaction_rate_hz": 10.0}
    if cpus:
        comp["cpus"] = cpus
    (tmp / "c.toml").write_text(_toml(comp))
    (tmp / "echo.py").write_text(ECHO)
    stats = tmp / "status.json"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2]) + os.pathsep + env.get("PYTHONPATH", "")
    with Processes() as procs:
        procs.start("daemon", ["run", "--config", str(tmp / "c.toml"), "--stats-out", str(stats)], env=env)
        echo = subprocess.Popen([sys.executable, str(tmp / "echo.py"), ep], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                preexec_fn=(lambda: set_cpus(cpus)) if cpus else None)
        procs.procs.append(("echo", echo))
        session = open_session(ZenohConfig(mode="peer", connect=[ep]))
        try:
            targets = {}
            for name, base in (("daemon", "energyctl/bench"), ("echo", "bench/echo")):
                sub, q = queued(session, f"{base}/cmd")
                targets[name] = (publisher(session, f"{base}/meas"), q, sub)

            def alive(k: str) -> bool:
                return any(r.ok is not None for r in session.liveliness().get(k, timeout=0.5))

            if not (wait_until(lambda: alive(key("energyctl", "bench", "alive")), COME_UP_S)
                    and wait_until(lambda: alive("bench/echo/alive"), COME_UP_S)):
                raise RuntimeError("daemon or echo did not come up")
            time.sleep(0.3)
            rtt: dict[str, list[int]] = {"daemon": [], "echo": []}
            steal = StealMeter().start()
            lost = {"daemon": 0, "echo": 0}
            for k in range(2 * n):
                name = "daemon" if k % 2 == 0 else "echo"
                pub, q, _ = targets[name]
                payload = MEAS.encode(k, k * 1e-3, 15.0, 80.0, 80.15, 15.0)
                t0 = time.monotonic_ns()
                pub.put(payload)
                try:
                    t_rx, _ = q.get(timeout=0.2)
                    rtt[name].append(t_rx - t0)
                except Empty:
                    lost[name] += 1
                while not q.empty():
                    q.get_nowait()
                time.sleep(gap_s)
            steal.stop()
        finally:
            session.close()
        procs.stop_all()
    d = json.loads(stats.read_text())["loop"] if stats.exists() else {}
    res = {"bench": "latency", "wait": wait, "cpus": cpus, "round_trips_each": n, "daemon": percentiles(rtt["daemon"]),
           "echo": percentiles(rtt["echo"]), "lost": lost, "daemon_tick_exec_us": d.get("exec_us"),
           "daemon_tick_compute_us": d.get("compute_us"), "daemon_tick_put_us": d.get("publish_us"),
           "daemon_tick_control_us": d.get("control_us")}
    res["ratio_p50"] = res["daemon"]["p50_us"] / res["echo"]["p50_us"]
    res["ratio_p99"] = res["daemon"]["p99_us"] / res["echo"]["p99_us"]
    res["host_steal_pct"] = steal.pct
    return res
