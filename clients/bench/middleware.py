"""``energyctl bench middleware``: the design notes' middleware facts (notes §8), re-measured on this machine.

Each part is one fact of the notes, measured the way the daemon uses Zenoh and MCAP (a declared publisher with
``express=True`` and ``CongestionControl.DROP``, 64-byte payloads, peers on loopback with multicast scouting off):

* ``put_us``: one ``put()``, with no subscriber and with one in another process, 0.5 ms apart (as the daemon puts
  one command per sample) and, with the subscriber, back to back;
* ``one_way_us`` / ``round_trip_us``: Python process to Python process; one way from the receiver's own stamp
  (CLOCK_MONOTONIC is one clock for all processes of a machine);
* ``receive``: a 1 kHz sleep-then-spin loop (200 us margin) while samples arrive at 1 kHz, once receiving them with
  a plain Python callback and once with a ``RingChannel(1)`` polled by ``try_recv()`` from the loop: the loop's
  lateness and its missed periods;
* ``get_us``: a queryable's ``get()`` round trip (channel handler, reply, drop);
* ``liveliness_sigkill_ms``: how long after kill -9 of a token's holder its loss is seen;
* ``cpu_per_message``: the CPU time (all threads of a process) one message costs through Zenoh, against a Unix socket
  pair, both ends in one process, back to back and 0.5 ms apart: the budget a realtime stack spends per sample;
* ``encode_us``: one Measurement as our struct codec, pydantic JSON and stdlib JSON;
* ``mcap``: ``add_message`` rate with zstd chunks, and the longest single call (the one that closes a chunk) for
  256 KiB and 4 MiB chunks.

The peer is a second Python process (``PEER`` below) that echoes, stamps, streams and answers queries.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from clients.live import COME_UP_S, wait_until
from clients.machine import StealMeter
from schemas.codec import MEAS
from schemas.component import ZenohConfig
from schemas.messages import Measurement
from service.daemon.bus import free_tcp_port, open_session, publisher

PEER = """
import struct, sys, threading, time, zenoh
ep, role = sys.argv[1], sys.argv[2]
c = zenoh.Config(); c.insert_json5("mode", '"peer"'); c.insert_json5("scouting/multicast/enabled", "false")
c.insert_json5("connect/endpoints", '["' + ep + '"]')
s = zenoh.open(c)
tok = s.liveliness().declare_token("mw/" + role + "/alive")
if role == "token":
    while True:
        time.sleep(1)
back = s.declare_publisher("mw/back", express=True, congestion_control=zenoh.CongestionControl.DROP)
stream = s.declare_publisher("mw/stream", express=True, congestion_control=zenoh.CongestionControl.DROP)
sub = s.declare_subscriber("mw/ping", zenoh.handlers.RingChannel(1))
qa = s.declare_queryable("mw/q", zenoh.handlers.FifoChannel(16))
ctl = s.declare_subscriber("mw/stream_for", zenoh.handlers.FifoChannel(4))
pad = bytes(56)

def answer():
    while True:
        q = qa.recv()
        q.reply("mw/q", b"ok")
        q.drop()

def streamer():
    while True:
        secs = float(ctl.recv().payload.to_bytes())
        nxt = time.monotonic_ns(); end = nxt + int(secs * 1e9); k = 0
        while nxt < end:
            nxt += 1_000_000
            d = nxt - time.monotonic_ns()
            if d > 0:
                time.sleep(d * 1e-9)
            stream.put(struct.pack("<q", k) + pad); k += 1

threading.Thread(target=answer, daemon=True).start()
threading.Thread(target=streamer, daemon=True).start()
while True:
    m = sub.recv()
    t_rx = time.monotonic_ns()
    back.put(m.payload.to_bytes()[:8] + struct.pack("<q", t_rx) + pad[:48])
"""


PUT_GAP_S = 5e-4  # puts as the daemon makes them, one per sample at 2 kHz (Zenoh's threads idle in between)


def _pcts(us) -> dict:
    v = np.asarray(us, dtype=float)
    if not v.size:
        return {"n": 0}
    p50, p99 = np.percentile(v, [50, 99])
    return {"p50": round(float(p50), 2), "p99": round(float(p99), 2), "max": round(float(v.max()), 2), "n": int(v.size)}


def _put_cost(pub, n: int, gap_s: float) -> dict:
    """n puts of 64 B, ``gap_s`` apart (0: back to back)."""
    payload = bytes(64)
    now = time.perf_counter_ns
    out = np.empty(n)
    for k in range(n):
        t0 = now()
        pub.put(payload)
        out[k] = (now() - t0) / 1e3
        if gap_s:
            time.sleep(gap_s)
    return _pcts(out)


def _ping(session, n: int) -> tuple[dict, dict]:
    pub = publisher(session, "mw/ping")
    sub = session.declare_subscriber("mw/back", zenoh.handlers.RingChannel(1))
    one, rtt = [], []
    try:
        for _ in range(n):
            t0 = time.monotonic_ns()
            pub.put(struct.pack("<q", t0) + bytes(56))
            deadline = t0 + 200_000_000
            while time.monotonic_ns() < deadline:  # the answer to this ping (an older one may come first)
                m = sub.try_recv()
                if m is None:
                    continue
                t1 = time.monotonic_ns()
                sent, t_rx = struct.unpack_from("<qq", m.payload.to_bytes())
                if sent == t0:
                    one.append((t_rx - t0) / 1e3)
                    rtt.append((t1 - t0) / 1e3)
                    break
            time.sleep(5e-4)
    finally:
        sub.undeclare()
        pub.undeclare()
    return _pcts(one), _pcts(rtt)


def _loop_while_receiving(session, how: str, seconds: float) -> dict:
    """A 1 kHz loop (sleep to 200 us before the instant, then spin) while the peer streams at 1 kHz."""
    latest = [None]
    last_rx = [0]
    if how == "callback":
        def on_sample(s) -> None:
            latest[0] = s.payload.to_bytes()
            last_rx[0] = time.monotonic_ns()

        sub = session.declare_subscriber("mw/stream", on_sample)
        poll = None
    else:
        sub = session.declare_subscriber("mw/stream", zenoh.handlers.RingChannel(1))
        poll = sub.try_recv
    ctl = session.declare_publisher("mw/stream_for")
    time.sleep(0.2)
    ctl.put(str(seconds).encode())
    period, margin = 1_000_000, 200_000
    now = time.monotonic_ns
    late = []
    missed = got = 0
    nxt = now() + period
    end = nxt + int(seconds * 1e9)
    while nxt < end:
        wait = nxt - now()
        if wait > margin:
            time.sleep((wait - margin) * 1e-9)
        while now() < nxt:
            pass
        t = now()
        late.append((t - nxt) / 1e3)
        if poll is not None:
            m = poll()
            got += m is not None
        else:
            got += latest[0] is not None
            latest[0] = None
        nxt += period
        if now() > nxt:
            skipped = (now() - nxt) // period + 1
            missed += skipped
            nxt += skipped * period
    if how == "callback":  # undeclared only once the stream has ended: no callback running
        wait_until(lambda: time.monotonic_ns() - last_rx[0] > 50_000_000, 2.0)
    sub.undeclare()
    ctl.undeclare()
    return {"lateness_us": _pcts(late), "missed_periods": int(missed), "periods": len(late),
            "periods_with_a_new_sample": int(got)}


def _get(session, n: int) -> dict:
    out = []
    for _ in range(n):
        t0 = time.monotonic_ns()
        ok = any(r.ok is not None for r in session.get("mw/q", timeout=1.0))
        if ok:
            out.append((time.monotonic_ns() - t0) / 1e3)
    return _pcts(out)


def _liveliness_sigkill(ep: str, script: Path, env: dict, runs: int) -> dict:
    """kill -9 a process holding a token; the time until its DELETE is seen here (a channel polled every 50 us,
    no Python callback: dropping one can deadlock zenoh-python against the GIL)."""
    session = open_session(ZenohConfig(mode="peer", connect=[ep]))
    seen_ms = []
    try:
        sub = session.liveliness().declare_subscriber("mw/token/alive", zenoh.handlers.FifoChannel(64))
        for _ in range(runs):
            p = subprocess.Popen([sys.executable, str(script), ep, "token"], env=env, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
            try:
                if not wait_until(lambda: any(r.ok is not None for r in
                                              session.liveliness().get("mw/token/alive", timeout=0.5)), COME_UP_S):
                    continue
                while sub.try_recv() is not None:  # its PUT
                    pass
                t_kill = time.monotonic_ns()
                p.send_signal(signal.SIGKILL)
                deadline = t_kill + 15_000_000_000
                while time.monotonic_ns() < deadline:
                    s = sub.try_recv()
                    if s is not None and s.kind == zenoh.SampleKind.DELETE:
                        seen_ms.append((time.monotonic_ns() - t_kill) / 1e6)
                        break
                    time.sleep(5e-5)
            finally:
                p.kill()
                p.wait()
        sub.undeclare()
    finally:
        session.close()
    return {"ms": [round(x, 2) for x in seen_ms], "runs": runs}


def _encode(n: int = 20_000) -> dict:
    vals = (123456, 0.0123, 15.2, 80.1, 80.3, 14.9)
    m = Measurement(seq=vals[0], t=vals[1], i=vals[2], v=vals[3], u=vals[4], i_load=vals[5])
    d = m.model_dump()

    def timed(fn) -> float:
        t0 = time.perf_counter_ns()
        for _ in range(n):
            fn()
        return round((time.perf_counter_ns() - t0) / n / 1e3, 3)

    return {"struct_codec": timed(lambda: MEAS.encode(*vals)), "pydantic_json": timed(m.model_dump_json),
            "stdlib_json": timed(lambda: json.dumps(d))}


def _echo_cpu(send, recv, echo_once, seconds: float) -> dict:
    """Round trips through an echo on a second thread of this process, back to back and PUT_GAP_S apart: the
    process's CPU time (every thread: both ends, and Zenoh's own) per message carried, and the wall time per round
    trip. ``echo_once`` receives one message and sends it back (it raises once the transport is closed)."""

    def echo() -> None:
        try:
            while True:
                echo_once()
        except Exception:  # noqa: BLE001 - closed: the measurement is over
            return

    threading.Thread(target=echo, daemon=True).start()
    payload = bytes(64)
    for _ in range(50):  # warm up: the first round trips set up routes and buffers
        send(payload)
        recv()
    out = {}
    for gap_s in (0.0, PUT_GAP_S):
        n = 0
        c0, w0 = time.process_time(), time.monotonic()
        while time.monotonic() - w0 < seconds:
            send(payload)
            recv()
            n += 1
            if gap_s:
                time.sleep(gap_s)
        cpu, wall = time.process_time() - c0, time.monotonic() - w0
        out[f"gap_{gap_s * 1e6:.0f}us"] = {"cpu_us_per_message": round(cpu / (2 * n) * 1e6, 1),
                                          "round_trip_us": round(wall / n * 1e6, 1), "round_trips": n}
    return out


def _cpu_per_message(ep: str, seconds: float) -> dict:
    """What carrying one message costs in CPU time, Zenoh against the kernel's own socket: two Zenoh sessions in this
    process connected over TCP loopback (publishers as the daemon's, ``RingChannel(1)`` subscribers read with a
    blocking ``recv()``: no Python callback), and a Unix socket pair, each echoed by a second thread; back to back
    and PUT_GAP_S apart (each wake-up then finds its threads asleep, as in a paced loop)."""
    import socket

    a = open_session(ZenohConfig(mode="peer", listen=[ep]))
    b = open_session(ZenohConfig(mode="peer", connect=[ep]))
    try:
        ping, pong = publisher(a, "mw/cpu/ping"), publisher(b, "mw/cpu/pong")
        sub_b = b.declare_subscriber("mw/cpu/ping", zenoh.handlers.RingChannel(1))
        sub_a = a.declare_subscriber("mw/cpu/pong", zenoh.handlers.RingChannel(1))
        time.sleep(0.3)
        out = {"zenoh": _echo_cpu(ping.put, sub_a.recv, lambda: pong.put(sub_b.recv().payload.to_bytes()), seconds)}
    finally:
        b.close()  # ends the echo thread's recv()
        a.close()
    x, y = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        out["unix_socket"] = _echo_cpu(x.send, lambda: x.recv(256), lambda: y.send(y.recv(256)), seconds)
    finally:
        y.shutdown(socket.SHUT_RDWR)  # ends the echo thread's recv() (a close alone would not wake it)
        y.close()
        x.close()
    return out


def _mcap(tmp: Path, n: int = 100_000) -> dict:
    from mcap.writer import CompressionType, Writer

    payload = Measurement(seq=1, t=0.1, i=15.0, v=80.0, u=80.1, i_load=15.0).model_dump_json().encode()
    out = {}
    for chunk in (256 * 1024, 4 * 1024 * 1024):
        with open(tmp / f"mw-{chunk}.mcap", "wb") as f:
            w = Writer(f, chunk_size=chunk, compression=CompressionType.ZSTD)
            w.start()
            sid = w.register_schema("m", "jsonschema", b"{}")
            cid = w.register_channel("m", "json", sid)
            worst = 0
            now = time.perf_counter_ns
            t_all = now()
            for k in range(n):
                t0 = now()
                w.add_message(cid, log_time=k, data=payload, publish_time=k)
                worst = max(worst, now() - t0)
            wall = (now() - t_all) / 1e9
            w.finish()
        out[f"chunk_{chunk // 1024}KiB"] = {"msgs_per_s": round(n / wall), "add_message_us": round(wall / n * 1e6, 2),
                                            "longest_add_message_ms": round(worst / 1e6, 2)}
    return out


def bench_middleware(n: int = 3000, receive_s: float = 3.0, progress=lambda m: None) -> dict:
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="energyctl-mw-"))
    script = tmp / "peer.py"
    script.write_text(PEER)
    env = dict(os.environ)
    res: dict = {"bench": "middleware", "zenoh": "eclipse-zenoh", "payload_bytes": 64}
    listener = open_session(ZenohConfig(mode="peer", listen=[ep]))
    peer = None
    steal = StealMeter().start()
    try:
        progress("put with no subscriber")
        pub = publisher(listener, "mw/nobody")
        res["put_us_no_subscriber"] = _put_cost(pub, n, PUT_GAP_S)
        pub.undeclare()
        peer = subprocess.Popen([sys.executable, str(script), ep, "echo"], env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)
        if not wait_until(lambda: any(r.ok is not None for r in
                                      listener.liveliness().get("mw/echo/alive", timeout=0.5)), COME_UP_S):
            raise RuntimeError("the peer process did not come up: " + (peer.stderr.read().decode()
                                                                       if peer.poll() is not None else ""))
        progress("put with a subscriber in another process")
        pub = publisher(listener, "mw/ping")
        time.sleep(0.3)
        res["put_us_subscriber_in_another_process"] = _put_cost(pub, n, PUT_GAP_S)
        res["put_us_subscriber_in_another_process_back_to_back"] = _put_cost(pub, n, 0.0)
        pub.undeclare()
        progress("one way and round trip")
        res["one_way_us"], res["round_trip_us"] = _ping(listener, n)
        for how in ("callback", "ring_channel_polled"):
            progress(f"1 kHz loop receiving by {how}")
            res[f"receive_{how}"] = _loop_while_receiving(listener, how, receive_s)
        progress("queryable get")
        res["get_us"] = _get(listener, max(50, n // 10))
        progress("liveliness after kill -9")
        res["liveliness_sigkill_ms"] = _liveliness_sigkill(ep, script, env, runs=3)
    finally:
        if peer is not None:
            peer.kill()
            peer.wait()
        listener.close()
    progress("CPU per message: Zenoh and a Unix socket")
    res["cpu_per_message"] = _cpu_per_message(f"tcp/127.0.0.1:{free_tcp_port()}", receive_s)
    progress("encoding and MCAP writer")
    res["encode_us"] = _encode()
    res["mcap"] = _mcap(tmp)
    steal.stop()
    res["host_steal_pct"] = steal.pct
    for p in tmp.glob("*"):
        p.unlink()
    tmp.rmdir()
    return res
