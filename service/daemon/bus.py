"""Zenoh session and key expressions (the only module that knows Zenoh's configuration keys).

Key expressions, for component id ``ID`` under ``PREFIX`` (default ``energyctl``):

| key | who publishes | payload |
| --- | --- | --- |
| ``PREFIX/ID/meas`` | the plant of ID | Measurement, binary (schemas.codec.MEAS) |
| ``PREFIX/ID/cmd`` | the controller of ID | Command, binary (CMD) |
| ``PREFIX/ID/z`` | component ID | Interaction, binary (Z) |
| ``PREFIX/ID/status`` | queryable of the controller | JSON |
| ``PREFIX/ID/config`` | queryable of the controller: get | JSON |
| ``PREFIX/ID/config/set`` | queryable of the controller: set, JSON payload ``{"set": [...]}`` | JSON |
| ``PREFIX/ID/alive`` | liveliness token of the controller | - |
"""

from __future__ import annotations

import json
import os
import socket
import time
from queue import Empty, Full, Queue

import zenoh

from schemas.component import ZenohConfig
from schemas.scenario import ScenarioError

TX_QUEUE_BATCHES = 16  # zenoh.tx_queue_batches unset and no config file: Zenoh's default of 2 drops after 1 ms stalls


PEER_DEFAULT_LISTEN = "tcp/127.0.0.1:0"  # a peer given no listen endpoint (and no config file) listens here


def local_only(z: ZenohConfig) -> bool:
    """A peer with no listen endpoint and no config file whose every connect endpoint is on this host (loopback) and
    that does not scout: it gets PEER_DEFAULT_LISTEN. Any other peer keeps Zenoh's default (every interface), so
    that peers on other hosts, routed through a router, can still reach it."""
    if z.mode != "peer" or z.listen or z.config_file or z.multicast_scouting:
        return False
    return all(_loopback(e) for e in z.connect)


def _loopback(endpoint: str) -> bool:
    """tcp/127.0.0.1:7447, udp/localhost:7447, tcp/[::1]:7447 ... (protocol/host:port[#...])."""
    host = endpoint.partition("/")[2].split("#")[0].rpartition(":")[0].strip("[]")
    return host == "localhost" or host == "::1" or host.startswith("127.")


def key(prefix: str, component_id: str, leaf: str) -> str:
    return f"{prefix}/{component_id}/{leaf}"


def zenoh_config(z: ZenohConfig) -> zenoh.Config:
    cfg = zenoh.Config.from_file(z.config_file) if z.config_file else zenoh.Config()
    if z.config_file:  # relative files named in it (credentials, TLS) are taken from its directory
        for k in CONFIG_FILE_PATHS:
            d = json.loads(cfg.get_json(k) or "null")
            if isinstance(d, str) and not os.path.isabs(d):
                path = os.path.join(os.path.dirname(os.path.abspath(z.config_file)), d)
                cfg.insert_json5(k, json.dumps(path))
    if not z.config_file or z.mode != "peer":
        cfg.insert_json5("mode", json.dumps(z.mode))
    if z.listen:
        cfg.insert_json5("listen/endpoints", json.dumps(z.listen))
    elif local_only(z):
        # Zenoh's own default for a peer is every interface ([::]:0), and its gossip then links peers of this host
        # through a non-loopback address; a peer that only ever talks to this host listens on loopback instead
        cfg.insert_json5("listen/endpoints", json.dumps([PEER_DEFAULT_LISTEN]))
    if z.connect:
        cfg.insert_json5("connect/endpoints", json.dumps(z.connect))
    if not z.config_file or not z.multicast_scouting:
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(z.multicast_scouting))
    # fields with a default of ours: set, or unset and no config file (a user's own file keeps its value)
    for path, value, ours in (("transport/link/tx/queue/size/data", z.tx_queue_batches, TX_QUEUE_BATCHES),
                              ("transport/shared_memory/enabled", z.shared_memory, False)):
        if value is None and not z.config_file:
            value = ours
        if value is not None:
            cfg.insert_json5(path, json.dumps(value))
    if z.open_timeout_s is not None:
        cfg.insert_json5("transport/unicast/open_timeout", json.dumps(int(round(z.open_timeout_s * 1000))))
    if z.user is not None:
        auth = {"user": z.user, "password": read_password(z.password_file)}
        cfg.insert_json5("transport/auth/usrpwd", json.dumps(auth))
    tls = {}
    if z.tls_root_ca is not None:
        tls["root_ca_certificate"] = _readable(z.tls_root_ca, "zenoh.tls_root_ca")
    if z.tls_certificate is not None:
        read_private(z.tls_private_key, "zenoh.tls_private_key", first_line=False)
        tls.update(connect_certificate=_readable(z.tls_certificate, "zenoh.tls_certificate"),
                   connect_private_key=z.tls_private_key, enable_mtls=True)
    for k, v in tls.items():
        cfg.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    return cfg


CONFIG_FILE_PATHS = ["transport/auth/usrpwd/dictionary_file"] + [
    f"transport/link/tls/{k}" for k in ("root_ca_certificate", "listen_private_key", "listen_certificate",
                                        "connect_private_key", "connect_certificate")]


def _readable(path: str, field: str) -> str:
    if not os.access(path, os.R_OK):
        raise ScenarioError(f"{field}: cannot read {path}")
    return path


def read_private(path: str, field: str, first_line: bool = True) -> str:
    """A secret file's first line (or all of it); refuses a file others can read (as ssh refuses a key)."""
    try:
        st = os.stat(path)
        with open(path, encoding="utf-8") as f:
            text = f.readline().rstrip("\r\n") if first_line else f.read()
    except OSError as e:
        raise ScenarioError(f"{field}: cannot read {path}: {e.strerror}") from None
    if st.st_mode & 0o077:
        raise ScenarioError(f"{field}: {path} is readable by group or others (chmod 600 it)")
    if not text.strip():
        raise ScenarioError(f"{field}: {path} is empty")
    return text


def read_password(path: str) -> str:
    """The first line of a password file; refuses a file others can read."""
    return read_private(path, "zenoh.password_file")


def open_session(z: ZenohConfig) -> zenoh.Session:
    """Raises ConnectionError naming the endpoints (and the user) when Zenoh refuses: in client mode that
    includes a router that rejects the credentials."""
    cfg = zenoh_config(z)
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as e:
        who = f" as user {z.user!r}" if z.user else ""
        first = str(e).split(" at ")[0]
        raise ConnectionError(f"cannot open a Zenoh {z.mode} session{who} (connect {z.connect or 'none'}): {first}"
                              + (" - wrong credentials, or the router is down" if z.mode == "client" else "")) from None


def close_session(session: zenoh.Session) -> str | None:
    """Closes a session; Zenoh's own close timeout (10 s: a peer that stopped reading never takes its close
    messages) is not an error of the run that ends here: returned as text (None: closed), not raised."""
    try:
        session.close()
    except zenoh.ZError as e:
        return str(e).split(" at ")[0]
    return None


def free_tcp_port() -> int:
    """A currently free TCP port on 127.0.0.1 (for tests and the demo)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def publisher(session: zenoh.Session, key_expr: str) -> zenoh.Publisher:
    """Hot-path publisher: express (no batching), drop under congestion rather than block. Zenoh's default priority
    and waits: real-time priority and shorter waits cost missed commands here (decision 0034)."""
    return session.declare_publisher(key_expr, express=True, congestion_control=zenoh.CongestionControl.DROP)


class NewestQueue(Queue):
    """A queue.Queue of at most ``maxsize`` items (0: unbounded) that keeps the newest: ``put_newest`` on a full one
    drops the oldest item and counts it in ``dropped``. For a loop that answers only the newest samples: when it
    stalls (a starved thread, a stopped process), the samples that arrive meanwhile cannot pile up in memory."""

    def __init__(self, maxsize: int = 0):
        super().__init__(maxsize)
        self.dropped = 0

    def put_newest(self, item) -> None:
        while True:
            try:
                self.put_nowait(item)
                return
            except Full:
                try:
                    self.get_nowait()
                    self.dropped += 1
                except Empty:  # the consumer took one meanwhile: there is room now
                    pass


def queued(session: zenoh.Session, key_expr: str, maxsize: int = 0, admit=None):
    """(subscriber, queue): each message is put as (arrival monotonic ns, payload bytes) by a callback.

    For event-driven loops: ``queue.get(timeout=...)`` sleeps without the GIL and wakes on arrival
    (unlike a blocked ``recv()``, it can time out, so the loop can always be stopped). ``maxsize`` (0: unbounded)
    keeps the newest that many and counts the dropped ones in ``queue.dropped`` (``NewestQueue``). ``admit``
    (payload bytes -> bool), if given, runs on Zenoh's thread first: a payload it refuses is not queued (it counts
    and names what it refuses itself).

    queue.Queue, not SimpleQueue: CPython 3.11's SimpleQueue.get(timeout=...) can block forever when its
    deadline passes between a wake-up and the re-wait (the remaining time goes negative, which its lock
    call takes as "no timeout"). Seen here: a realtime plant waiting 44 us hung for minutes in
    futex(..., NULL). Queue.get checks the remaining time itself."""
    q = NewestQueue(maxsize)
    put, now = q.put_newest, time.monotonic_ns

    if admit is None:
        def on_sample(sample) -> None:
            put((now(), sample.payload.to_bytes()))
    else:
        def on_sample(sample) -> None:
            b = sample.payload.to_bytes()
            if admit(b):
                put((now(), b))

    return session.declare_subscriber(key_expr, on_sample), q


def latest(session: zenoh.Session, key_expr: str, newest: int = 1) -> zenoh.Subscriber:
    """Latest-value subscriber: a ring of the ``newest`` messages (default one; a full ring drops its oldest),
    polled with try_recv() (oldest first) from the loop thread."""
    return session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(newest))


def answer(query, ok: bool, body: dict, own_key: str) -> None:
    """Reply to a query with JSON (on own_key, or as an error) and drop it; an asker gone meanwhile is no error. A
    body JSON cannot encode is answered as an error naming why (the asker is not left to time out)."""
    try:
        text = json.dumps(body)
    except (TypeError, ValueError) as e:
        ok, text = False, json.dumps({"error": f"the reply could not be encoded: {type(e).__name__}: {e}"})
    try:
        if ok:
            query.reply(own_key, text)
        else:
            query.reply_err(text)
    except Exception:  # noqa: BLE001 - the asker went away
        pass
    finally:
        query.drop()


def serve_queries(q, own_key: str, handler, on_error=None) -> None:
    """A queryable's thread: each query's (ok, JSON body) from handler(query), answered on own_key (a `get` on
    ``energyctl/**`` learns which leaf answered) until the channel closes at shutdown. handler returns None for a
    query it has handed on (answered and dropped elsewhere). An exception in it (a bad query) is answered as
    {"error": on_error(e)} (default "Type: message") and never ends the thread."""
    while True:
        try:
            query = q.recv()
        except Exception:  # noqa: BLE001 - channel closed at shutdown
            return
        try:
            res = handler(query)
        except Exception as e:  # noqa: BLE001 - RecursionError from deep JSON too: answered
            res = False, {"error": on_error(e) if on_error is not None else f"{type(e).__name__}: {e}"}
        if res is not None:
            answer(query, res[0], res[1], own_key)


def request(session: zenoh.Session, selector: str, body: dict | None, timeout_s: float) -> tuple[bool, dict]:
    """One JSON query between services: (ok, the reply's JSON) of the first reply; (False, {"error": ...}) when
    none came within timeout_s or the reply was not JSON."""
    payload = json.dumps(body) if body is not None else None
    try:
        for r in session.get(selector, payload=payload, timeout=timeout_s):
            ok = r.ok is not None
            raw = (r.ok if ok else r.err).payload.to_bytes()
            try:
                return ok, json.loads(raw)
            except ValueError:
                return False, {"error": raw.decode(errors="replace")}
    except Exception as e:  # noqa: BLE001 - a closed session, a bad selector: the caller decides
        return False, {"error": f"{type(e).__name__}: {e}"}
    return False, {"error": f"no answer from {selector} within {timeout_s:g} s"}
