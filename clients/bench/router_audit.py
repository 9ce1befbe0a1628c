"""energyctl bench router-audit: what logging refusals costs the secure router (docs/decisions/0041).

An ``energyctl router`` process enforcing a freshly written secure profile on loopback; the ``source`` identity
publishes on its command key at ``rate_hz`` for ``seconds`` (paced by the clock), the ``plant`` identity receives,
both allowed by the ACL. The router's CPU time over the run (utime + stime from /proc), and per message delivered to
the subscriber (the publisher drops under congestion, so fewer may arrive than were offered), is measured with refusal
logging on (the default: Zenoh's access-control target at TRACE writes a line per routed message, read and dropped
by the router's own thread) and off (``--no-audit``), alternated ``pairs`` times. Then, with logging on, a
``monitor`` asks to set config (which it may not) 20 times and a wrong password is tried: the router's status must
count exactly those.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from clients.live import COME_UP_S, stop_process


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _start_router(paths: dict, audit: bool, err: Path) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    cmd = [sys.executable, "-m", "clients.cli", "router", "--config", str(paths["router"])]
    with err.open("w") as f:  # the child keeps its own copy of the descriptor
        p = subprocess.Popen(cmd + ([] if audit else ["--no-audit"]), stdout=subprocess.DEVNULL, stderr=f, env=env,
                             start_new_session=True)
    deadline = time.monotonic() + COME_UP_S
    while "listening" not in err.read_text():
        if p.poll() is not None or time.monotonic() > deadline:
            stop_process(p, 0.0)
            raise RuntimeError(f"router did not start: {err.read_text()[-500:]}")
        time.sleep(0.02)
    return p


def _run(paths: dict, ep: str, audit: bool, rate_hz: float, seconds: float, work: Path) -> dict:
    from clients.secure import client_zenoh
    from schemas.component import ZenohConfig
    from service.daemon.bus import open_session, publisher

    p = _start_router(paths, audit, work / f"router-{audit}.err")
    try:
        src = open_session(ZenohConfig(**client_zenoh(ep, "source", paths["source"])))
        plant = open_session(ZenohConfig(**client_zenoh(ep, "plant", paths["plant"])))
        got = [0]
        sub = plant.declare_subscriber("energyctl/source/cmd", lambda _s: got.__setitem__(0, got[0] + 1))
        pub = publisher(src, "energyctl/source/cmd")
        pub.put(b"warm-up")
        deadline = time.monotonic() + 5.0
        while got[0] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        got[0] = 0
        n = int(rate_hz * seconds)
        payload = bytes(40)
        c0, t0 = _cpu_s(p.pid), time.perf_counter()
        for k in range(n):
            while time.perf_counter() < t0 + k / rate_hz:
                pass
            pub.put(payload)
        wall = time.perf_counter() - t0
        time.sleep(0.2)  # the last messages through
        cpu = _cpu_s(p.pid) - c0
        sub.undeclare()
        src.close()
        plant.close()
        return {"audit": audit, "sent": n, "received": got[0], "wall_s": round(wall, 3),
                "router_cpu_s": round(cpu, 3), "router_cpu_pct": round(100 * cpu / wall, 1),
                "router_us_per_delivered": round(1e6 * cpu / max(got[0], 1), 1)}
    finally:
        stop_process(p)


def _refusals(paths: dict, ep: str, work: Path) -> dict:
    """With logging on: 20 config sets the monitor may not make and one wrong password, then the router's counts
    (asked until they are in, at most 10 s: the router reads its log on a thread of its own)."""
    from clients.query import query
    from clients.secure import client_zenoh
    from schemas.component import ZenohConfig
    from service.daemon.bus import open_session

    p = _start_router(paths, True, work / "router-refusals.err")
    try:
        bad = work / "wrong.password"
        bad.write_text("not-the-password\n")
        bad.chmod(0o600)
        try:
            open_session(ZenohConfig(**client_zenoh(ep, "operator", bad))).close()
        except ConnectionError:
            pass
        mon = ZenohConfig(**client_zenoh(ep, "monitor", paths["monitor"]))
        s = open_session(mon)
        for _ in range(20):
            list(s.get("energyctl/source/config/set", payload=b'{"set": ["controller.K_per_s=1"]}', timeout=0.1))
        s.close()
        deadline = time.monotonic() + 10.0
        while True:
            got = query(mon, "energyctl", "router", "status", timeout_s=5.0)["refusals"]
            if (got["acl_denied"] >= 20 and got["logins_refused"] >= 1) or time.monotonic() > deadline:
                return got
            time.sleep(0.05)
    finally:
        stop_process(p)


def bench_router_audit(rate_hz: float = 10_000.0, seconds: float = 3.0, pairs: int = 2, progress=None) -> dict:
    from clients.secure import write_profile
    from service.daemon.bus import free_tcp_port

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        paths = write_profile(work / "secure", listen=[ep])
        runs = []
        for _ in range(pairs):
            for audit in (False, True):
                r = _run(paths, ep, audit, rate_hz, seconds, work)
                runs.append(r)
                if progress:
                    progress(r)
        refused = _refusals(paths, ep, work)
    on = [r for r in runs if r["audit"]]
    off = [r for r in runs if not r["audit"]]

    def med(rs, k):
        v = sorted(r[k] for r in rs)
        return v[len(v) // 2]

    return {"rate_hz": rate_hz, "seconds": seconds, "pairs": pairs,
            "router_cpu_pct_off": med(off, "router_cpu_pct"), "router_cpu_pct_on": med(on, "router_cpu_pct"),
            "router_us_per_delivered_off": med(off, "router_us_per_delivered"),
            "router_us_per_delivered_on": med(on, "router_us_per_delivered"),
            "received_off": med(off, "received"), "received_on": med(on, "received"),
            "refusals_counted": refused, "runs": runs}
