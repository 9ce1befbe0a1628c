"""``energyctl bench network-rate``: the realtime two-source network at one control rate, several runs, each beside a
bare Zenoh echo with the same number of processes in the same run.

Each run is a pair, echo then network, so both see the same machine load:

* **echo**: this process stands in for the rig and samples on the wall clock at the rate (sleep, then spin to the
  instant); each sample goes to as many echo processes as the network has besides its rig (the coordinator and a
  daemon per source), and each answers with the payload unchanged. A reply's age is counted as the rig counts a
  command's (service's ``age_summary``): periods from the sample answered to the one about to be taken when the
  reply was there; "after their period" is older than the network's loop delay d;
* **network**: ``energyctl bench network-live --realtime``'s rate run (the rig, the coordinator and the daemons as
  processes, the load step's acceptance checks).

Reported: how many of the runs pass every check, and per run the network's commands after their period and its p99
age against the echo's (the ratio): what the machine allows a stack of that many processes at that rate.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from clients.bench.network_live import rate_run, realtime_sets
from clients.live import COME_UP_S, wait_until
from clients.machine import StealMeter
from clients.peers.netrig import age_summary
from schemas.component import ZenohConfig
from service.daemon.bus import close_session, free_tcp_port, open_session, publisher

ECHO = """
import json, sys, zenoh
ep, i = sys.argv[1], sys.argv[2]
c = zenoh.Config(); c.insert_json5("mode", '"peer"'); c.insert_json5("scouting/multicast/enabled", "false")
c.insert_json5("connect/endpoints", json.dumps([ep]))
s = zenoh.open(c)
pub = s.declare_publisher("bench/net/cmd/" + i, express=True, congestion_control=zenoh.CongestionControl.DROP)
sub = s.declare_subscriber("bench/net/meas/" + i, zenoh.handlers.RingChannel(1))
tok = s.liveliness().declare_token("bench/net/alive/" + i)
while True:
    pub.put(sub.recv().payload.to_bytes())
"""
AGE_BINS = 64  # ages beyond this many periods share the last bin (as the rig's histogram)


def echo_run(n_echo: int, rate_hz: float, seconds: float, d: int) -> dict:
    """n_echo echo processes answering every sample of a rate_hz wall-clock loop for seconds: the replies' ages
    (age_summary with loop delay d) and the replies lost."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    T_ns = int(round(1e9 / rate_hz))
    tmp = Path(tempfile.mkdtemp(prefix="energyctl-echo-"))
    (tmp / "echo.py").write_text(ECHO)
    procs = []
    session = open_session(ZenohConfig(mode="peer", listen=[ep]))
    hist = [0] * AGE_BINS
    got = [0]
    lock = threading.Lock()
    t_start = [0]

    def on_reply(sample) -> None:  # the age in periods at the reply's arrival
        t = time.monotonic_ns()
        k = struct.unpack_from("<q", sample.payload.to_bytes())[0]
        age = (t - (t_start[0] + k * T_ns)) // T_ns + 1
        with lock:
            hist[min(max(age, 0), AGE_BINS - 1)] += 1
            got[0] += 1

    try:
        subs = [session.declare_subscriber(f"bench/net/cmd/{i}", on_reply) for i in range(n_echo)]
        pubs = [publisher(session, f"bench/net/meas/{i}") for i in range(n_echo)]
        env = dict(os.environ)
        for i in range(n_echo):
            procs.append(subprocess.Popen([sys.executable, str(tmp / "echo.py"), ep, str(i)], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

        def all_alive() -> bool:
            return len([r for r in session.liveliness().get("bench/net/alive/*", timeout=0.5) if r.ok]) >= n_echo

        if not wait_until(all_alive, COME_UP_S):
            raise RuntimeError(f"bench network-rate: the {n_echo} echo processes did not come up")
        n = int(round(seconds * rate_hz))
        pad = bytes(56)
        t_start[0] = time.monotonic_ns() + 50_000_000
        for k in range(n):
            due = t_start[0] + k * T_ns
            left = due - time.monotonic_ns()
            if left > 200_000:
                time.sleep((left - 200_000) * 1e-9)
            while time.monotonic_ns() < due:
                pass
            payload = struct.pack("<q", k) + pad
            for p in pubs:
                p.put(payload)
        wait_until(lambda: got[0] >= n * n_echo, 1.0)
        for s in subs:
            s.undeclare()
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=10)
        close_session(session)
    with lock:
        h = list(hist)
    return {**age_summary(h, d), "lost": n * n_echo - sum(h), "processes": n_echo + 1}


def bench_network_rate(rate_hz: float, runs: int, seconds: float, progress) -> dict:
    """runs pairs (echo, network) of seconds each at rate_hz (module docstring)."""
    sets = realtime_sets(rate_hz, ["S1", "S2"])
    d = int(sets[1].split("=")[1])
    out: dict = {"rate_hz": rate_hz, "delay_samples": d, "seconds": seconds, "runs": [],
                 "machine_cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="energyctl-netrate-") as tmp:
        work = Path(tmp)
        for r in range(runs):
            steal = StealMeter().start()
            progress(f"run {r + 1}/{runs}: echo with 3 processes ...")
            echo = echo_run(3, rate_hz, seconds, d)
            progress(f"run {r + 1}/{runs}: echo {json.dumps(echo)}; the network ...")
            (work / f"run{r}").mkdir()
            net = rate_run(work / f"run{r}", rate_hz, seconds)
            steal.stop()
            ages = list((net.get("command_age") or {}).values())
            late = max((a["after_their_period_pct"] for a in ages), default=None)
            p99 = max((a["p99_samples"] for a in ages), default=None)
            row = {"regulates": net["regulates"], "failed": net["failed"], "bus_ss_dev_pct": net["bus_ss_dev_pct"],
                   "step_bus_back_s": net["step_bus_back_s"], "sharing_pp": net["sharing_pp"],
                   "network_after_period_pct": late, "network_p99_samples": p99,
                   "echo_after_period_pct": echo["after_their_period_pct"], "echo_p99_samples": echo["p99_samples"],
                   "echo_lost": echo["lost"], "cpu_pct": net["cpu_pct"], "host_steal_pct": steal.pct}
            row["p99_ratio"] = (p99 / echo["p99_samples"]) if p99 is not None and echo["p99_samples"] else None
            out["runs"].append(row)
            progress(f"run {r + 1}/{runs}: {json.dumps(row)}")
    out["passed"] = sum(1 for x in out["runs"] if x["regulates"])
    return out
