"""``energyctl bench foxglove``: what the Foxglove bridge costs the stack it watches.

The same stack (controller daemon, stand-in plant and load as processes on loopback Zenoh) runs alternately
without and with ``energyctl foxglove`` beside it, and with a WebSocket client subscribed to every channel the
bridge offers (so that it decodes and sends everything). Compared within one run of the bench: the daemon loop's
overruns, the plant's wall time (lockstep: how fast the stack goes) and its missed commands (realtime); reported
for the bridge: its CPU share (its process's CPU time over its wall time) and what it received, sent and dropped.
"""

from __future__ import annotations

import json
import os
import threading
import time

CLK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float | None:
    """User + system CPU time of a process (s), from /proc; None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK
    except (OSError, IndexError, ValueError):
        return None


class _Watcher(threading.Thread):
    """A Foxglove WebSocket client that subscribes to every advertised channel and counts what arrives."""

    def __init__(self, port: int, stop: threading.Event, keep_topic: str | None = None):
        """keep_topic: the decoded JSON messages of this channel are kept in ``kept``."""
        super().__init__(daemon=True)
        self.port, self.stop, self.messages, self.error = port, stop, 0, ""
        self.subscribed = threading.Event()
        self.keep_topic, self.kept, self._keep_sub = keep_topic, [], None

    def run(self) -> None:
        from websockets.sync.client import connect

        deadline = time.monotonic() + 20.0
        while not self.stop.is_set():
            try:
                ws = connect(f"ws://127.0.0.1:{self.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=1.0)
                break
            except OSError:
                if time.monotonic() > deadline:
                    self.error = "the bridge did not listen within 20 s"
                    return
                self.stop.wait(0.1)
        else:
            return
        with ws:
            sub_id = 0
            while not self.stop.is_set():
                try:
                    msg = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except Exception as e:  # noqa: BLE001 - the bridge stopped: done
                    self.error = self.error or f"{type(e).__name__}"
                    return
                if isinstance(msg, bytes):
                    self.messages += 1
                    # message data: opcode 1, subscription id (u32), receive time (u64), then the payload
                    if msg[0] == 1 and int.from_bytes(msg[1:5], "little") == self._keep_sub:
                        self.kept.append(json.loads(msg[13:]))
                    continue
                d = json.loads(msg)
                if d.get("op") == "advertise":
                    subs = []
                    for ch in d["channels"]:
                        sub_id += 1
                        subs.append({"id": sub_id, "channelId": ch["id"]})
                        if ch["topic"] == self.keep_topic:
                            self._keep_sub = sub_id
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                    self.subscribed.set()


def _stack(port: int | None, rate_hz: float, watch: dict, keep_topic: str | None = None):
    """run_live's ``extra``: with a port, the bridge on it (and the watching client, and its CPU time sampled);
    in every case the time the plant starts."""
    from clients.live import wait_until

    def extra(ep, procs, env):
        if port is None:
            watch["t_plant"] = time.monotonic()
            return None
        p = procs.start("foxglove", ["foxglove", "--connect", ep, "--components", "source", "--port", str(port),
                                     "--rate-hz", str(rate_hz)], env=env)
        stop = threading.Event()
        w = _Watcher(port, stop, keep_topic)
        w.start()
        ok = wait_until(w.subscribed.is_set, 30.0)
        watch.update(watcher=w, stop=stop, subscribed=ok)

        def sample_cpu() -> None:  # the bridge's CPU time while the plant runs, read every 0.2 s until stopped
            t0, c0 = time.monotonic(), _cpu_s(p.pid)
            while not stop.wait(0.2):
                c = _cpu_s(p.pid)
                if c is None or c0 is None:
                    return
                watch["bridge_cpu_pct"] = 100.0 * (c - c0) / (time.monotonic() - t0)

        threading.Thread(target=sample_cpu, daemon=True).start()
        watch["t_plant"] = time.monotonic()
        return None

    return extra


def bench_foxglove(scn, seconds: float = 2.0, pairs: int = 2, lockstep: bool = True, rate_hz: float | None = None,
                   delay: int | None = None, bridge_rate_hz: float = 1000.0, progress=None) -> dict:
    """``pairs`` runs without and with the bridge, alternated (the machine's noise moves both alike)."""
    from clients.live import run_live
    from service.daemon.bus import free_tcp_port

    runs = []
    for j in range(pairs):
        for with_bridge in (False, True):
            watch: dict = {}
            extra = _stack(free_tcp_port() if with_bridge else None, bridge_rate_hz, watch)
            res = run_live(scn, lockstep=lockstep, rate_hz=rate_hz, out=None, duration_s=seconds,
                           controller_delay=delay, extra=extra)
            wall = time.monotonic() - watch["t_plant"]  # the plant's run (and the stack's stop)
            loop = res.get("daemon", {}).get("loop", {})
            c = res.get("counters", {})
            n = max(1, c.get("samples", 0))
            row = {"bridge": with_bridge, "pair": j, "wall_s": wall, "overrun_pct": loop.get("overrun_pct"),
                   "missed_or_late_pct": 100.0 * (c.get("missed", 0) + c.get("late", 0)) / n,
                   "v_dev_after_50ms_pct": res.get("metrics", {}).get("hold_max_dev_pct"),
                   "latency_p50_us": res.get("latency_us", {}).get("p50"),
                   "latency_p99_us": res.get("latency_us", {}).get("p99")}
            if with_bridge:
                w = watch.get("watcher")
                if w is not None:
                    watch["stop"].set()
                    w.join(5.0)
                out = (res.get("extra_outputs") or {}).get("foxglove", (None, "", ""))
                status = {}
                for line in reversed(out[1].strip().splitlines()):
                    try:
                        status = json.loads(line)
                        break
                    except ValueError:
                        continue
                row.update(bridge_subscribed=watch.get("subscribed"), client_messages=w.messages if w else 0,
                           client_error=w.error if w else "", bridge_status=status,
                           bridge_cpu_pct=watch.get("bridge_cpu_pct"))
            runs.append(row)
            if progress:
                progress(row)
    def mean(key, bridge):
        xs = [r[key] for r in runs if r["bridge"] == bridge and r.get(key) is not None]
        return sum(xs) / len(xs) if xs else None

    return {"bench": "foxglove", "lockstep": lockstep, "rate_hz": rate_hz, "seconds": seconds, "runs": runs,
            **{f"{k}_{w}": mean(k, b) for k in ("overrun_pct", "wall_s", "latency_p50_us", "latency_p99_us",
                                                 "missed_or_late_pct")
               for w, b in (("without", False), ("with", True))},
            "bridge_cpu_pct": mean("bridge_cpu_pct", True)}
