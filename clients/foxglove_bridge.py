"""A bridge from Zenoh to Foxglove (energyctl foxglove): the components' measurements, commands and interaction
messages as Foxglove channels, their controller settings as Foxglove parameters, their status and config as
Foxglove services. The WebSocket server is the foxglove-sdk package's (``foxglove.start_server``); nothing of
the Foxglove protocol is written here.

For each component ``ID`` under ``PREFIX``:

| Zenoh key | Foxglove | schema |
| --- | --- | --- |
| ``PREFIX/PLANT/meas`` (PLANT: its plant's id, by default ID) | channel ``PREFIX/ID/meas`` | energyctl.Measurement |
| ``PREFIX/ID/cmd`` | channel ``PREFIX/ID/cmd`` | energyctl.Command |
| ``PREFIX/ID/z`` | channel ``PREFIX/ID/z_out`` | energyctl.Interaction |
| ``PREFIX/ID/config`` (get), ``.../config/set`` | parameters ``ID.controller.<key>``, ``ID.lifecycle`` | - |
| ``PREFIX/ID/status`` | service ``ID/status`` | energyctl.StatusReply |
| ``PREFIX/ID/config`` | service ``ID/config`` | energyctl.ConfigReply |
| ``PREFIX/ID/config/set`` | service ``ID/config/set`` (request ``{"set": [...]}``) | energyctl.ConfigSetReply |

The channel topics and schemas are those of the daemon's MCAP log (JSON encoding, the message models' JSON
Schemas), so a Foxglove layout made for a recording works live and the other way round. Each channel keeps at
most ``rate_hz`` messages a second (the rest are counted as dropped); a channel no Foxglove client subscribes
to is not decoded at all. Zenoh's callback threads only decode and hand the JSON to the SDK.

The connection graph (Foxglove's Topic Graph panel) shows every component under PREFIX that holds its liveliness
token ``PREFIX/ID/alive`` (not only the bridged ones), with Zenoh keys as topics and component ids as nodes:

* every live one (a controller or a load) publishes ``PREFIX/ID/z``;
* one that answers its status query (a controller) also publishes ``PREFIX/ID/cmd``, subscribes to
  ``PREFIX/PLANT/meas`` and to ``PREFIX/N/z`` of each neighbour N, and provides the services ``PREFIX/ID/status``,
  ``PREFIX/ID/config`` and ``PREFIX/ID/config/set``.

So an interaction link is a topic ``PREFIX/N/z`` from N to the controllers that have N among their neighbours
(the ids in the status reply's ``neighbours``; the config reply has only the controller settings). PLANT is the
id given as ``ID:PLANT`` in the component list, else ID (no query tells a controller's plant id). A token that
appears is followed by a status query (at most GET_TIMEOUT_S, on the graph's own thread), then an update; a
token that goes away (the component closed, or its session was lost) removes the component at once.
"""

from __future__ import annotations

import json
import math
import secrets
import sys
import threading
import time
from dataclasses import dataclass, field

import zenoh

from schemas.codec import CMD, EST, MEAS, TICK_IN, Codec, DecodeError, Z
from schemas.component import ZenohConfig
from schemas.messages import Event, json_schema
from schemas.replies import REPLY_MODELS
from service.daemon.bus import close_session, key, open_session
from service.daemon.failure import Failure, guarded

# Zenoh leaf -> (the daemon's MCAP topic leaf, schema name, codec)
STREAMS = {"meas": ("meas", "energyctl.Measurement", MEAS), "cmd": ("cmd", "energyctl.Command", CMD),
           "z": ("z_out", "energyctl.Interaction", Z)}
# the same for what a daemon with log_live_hz > 0 publishes from its recorder, already as the log's JSON text:
# (topic leaf, schema name, model); passed through as they come (decimated by the daemon and here)
LIVE_STREAMS = {"est": ("est", "energyctl.Estimate", EST.model), "z_in": ("z_in", "energyctl.TickInput",
                                                                             TICK_IN.model),
                "events": ("events", "energyctl.Event", Event)}
SET_TIMEOUT_S = 3.0  # the daemon refuses a set its loop did not take within 2 s: allow for that answer
GET_TIMEOUT_S = 1.0


def parse_components(text: str) -> list[tuple[str, str]]:
    """"source,b:rig" -> [("source", "source"), ("b", "rig")]: component ids, each with the id its plant publishes
    measurements under (``ID:PLANT``; by default the id itself)."""
    out = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        cid, _, plant = part.partition(":")
        for name in (cid, plant or cid):
            if not name or not all(c.isalnum() or c in "_-" for c in name):
                raise ValueError(f"{part!r}: a component id is letters, digits, _ and - (ID or ID:PLANT_ID)")
        out.append((cid, plant or cid))
    if not out:
        raise ValueError("no component given")
    return out


class Decimator:
    """Keeps at most ``rate_hz`` messages a second (0: all), as a schedule of one slot per interval 1/rate_hz: a
    message is kept when the next slot is due, and then the slot after it is. A message up to half an interval late
    keeps the schedule (steady input at the rate with jitter is not thinned); later, the schedule restarts half an
    interval after it. So kept messages are at least half an interval apart, at most T * rate_hz + 1.5 in any T
    seconds, and a burst after a quiet spell passes one."""

    __slots__ = ("interval_ns", "due_ns")

    def __init__(self, rate_hz: float):
        self.interval_ns = int(1e9 / rate_hz) if rate_hz > 0 else 0
        self.due_ns = 0

    def keep(self, now_ns: int) -> bool:
        if now_ns < self.due_ns:
            return False
        self.due_ns = max(self.due_ns + self.interval_ns, now_ns + self.interval_ns // 2)
        return True


@dataclass
class Stream:
    """One Zenoh key bridged to one Foxglove channel, with its counters."""

    key: str
    topic: str
    codec: Codec | None  # None: the payload is the message's JSON text already (LIVE_STREAMS)
    channel: object
    decimator: Decimator
    bools: tuple[int, ...]
    lock: threading.Lock = field(default_factory=threading.Lock)
    received: int = 0
    logged: int = 0
    dropped: int = 0  # by the decimation
    unsubscribed: int = 0  # arrived while no Foxglove client subscribed: not decoded
    invalid: int = 0  # not a valid message (schemas.codec.DecodeError)
    last_error: str = ""

    def on_sample(self, sample) -> None:
        """Zenoh's callback: count, decimate, decode, log. Never waits on anything but this stream's counters."""
        with self.lock:
            self.received += 1
            if not self.decimator.keep(time.monotonic_ns()):
                self.dropped += 1
                return
            if not self.channel.has_sinks():
                self.unsubscribed += 1
                return
        if self.codec is None:
            self.channel.log(sample.payload.to_bytes())
            with self.lock:
                self.logged += 1
            return
        try:
            vals = self.codec.decode(sample.payload.to_bytes())
        except DecodeError as e:
            with self.lock:
                self.invalid += 1
                self.last_error = str(e)
            return
        msg = dict(zip(self.codec.fields, vals, strict=True))
        for k in self.bools:  # as the daemon's log writes them: true/false, not 1/0
            msg[self.codec.fields[k]] = bool(vals[k])
        self.channel.log(msg)
        with self.lock:
            self.logged += 1

    def status(self) -> dict:
        with self.lock:
            out = {"key": self.key, "received": self.received, "logged": self.logged, "dropped": self.dropped,
                   "unsubscribed": self.unsubscribed, "invalid": self.invalid}
            if self.last_error:
                out["last_error"] = self.last_error
        return out


def toml_text(value) -> str:
    """A Foxglove parameter value as the TOML value of a config/set entry."""
    if value is None:
        raise ValueError("a parameter cannot be unset (no value)")
    if isinstance(value, bytes):
        raise ValueError("a byte array is not a config value")
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # TOML reads inf, nan, 1e+20 and repr's other forms
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(toml_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_text(v)}" for k, v in value.items()) + "}"
    raise ValueError(f"unsupported parameter value {value!r}")


def flatten_config(cid: str, reply: dict) -> dict[str, object]:
    """A ConfigReply (or the controller of a ConfigSetApplied) -> {"ID.controller.K_per_s": 2000.0, ...,
    "ID.lifecycle": state}."""
    out: dict[str, object] = {}

    def walk(prefix: str, d: dict) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(f"{prefix}{k}.", v)
            else:
                out[f"{prefix}{k}"] = v

    walk(f"{cid}.controller.", reply.get("controller", {}))
    if "state" in reply:
        out[f"{cid}.lifecycle"] = reply["state"]
    return out


def finite_json(obj) -> bytes:
    """JSON bytes a browser can parse: the daemon's replies may hold NaN or Infinity (Python's json writes them as
    bare tokens, outside strict JSON); here they become null."""

    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    return json.dumps(clean(obj), allow_nan=False).encode()


@dataclass(frozen=True)
class Node:
    """A live component as the connection graph shows it: ``controller`` if it answered its status query (then
    ``neighbours``: the ids whose interaction messages it reads)."""

    controller: bool = False
    neighbours: tuple[str, ...] = ()


Graph = tuple[dict[str, tuple[str, ...]], dict[str, tuple[str, ...]], dict[str, tuple[str, ...]]]


def connection_graph(prefix: str, nodes: dict[str, Node], plants: dict[str, str]) -> Graph:
    """(published, subscribed, services): Zenoh key -> the ids publishing / subscribing / providing it, sorted.
    Every topic is in both maps (an empty tuple where nobody is): foxglove-sdk 0.30.3 sends a graph update as a
    difference, and a topic left out of one map while still in the other does not reach the client, so a
    publisher that goes away from a topic still subscribed would not be seen leaving."""
    pub: dict[str, set[str]] = {}
    sub: dict[str, set[str]] = {}
    srv: dict[str, set[str]] = {}
    for cid, n in nodes.items():
        pub.setdefault(key(prefix, cid, "z"), set()).add(cid)
        if not n.controller:
            continue
        pub.setdefault(key(prefix, cid, "cmd"), set()).add(cid)
        sub.setdefault(key(prefix, plants.get(cid, cid), "meas"), set()).add(cid)
        for nb in n.neighbours:
            sub.setdefault(key(prefix, nb, "z"), set()).add(cid)
        for what in ("status", "config", "config/set"):
            srv.setdefault(key(prefix, cid, what), set()).add(cid)
    topics = sorted(pub.keys() | sub.keys())
    return ({t: tuple(sorted(pub.get(t, ()))) for t in topics}, {t: tuple(sorted(sub.get(t, ()))) for t in topics},
            {k: tuple(sorted(v)) for k, v in sorted(srv.items())})


class Served:
    """What the bridge and the player share: the Foxglove server they started (``server``), on ``_port`` until then
    (0: a free one)."""

    server = None
    _port = 0

    @property
    def port(self) -> int:
        return self.server.port if self.server is not None else self._port

    def app_url(self) -> str | None:
        return self.server.app_url() if self.server is not None else None


class Bridge(Served):
    """Zenoh -> Foxglove WebSocket for ``components`` (ids, or (id, plant id) pairs).

    ``start()`` opens the Zenoh session, subscribes, reads each component's config and starts the Foxglove server on
    ``host:port`` (port 0: a free one, see ``port``); ``close()`` undoes it all. ``status()``: the counters.
    ``rate_hz``: the most messages a second each channel passes on (0: all)."""

    def __init__(self, zenoh: ZenohConfig, components: list[str] | list[tuple[str, str]], prefix: str = "energyctl",
                 port: int = 8765, rate_hz: float = 1000.0, host: str = "127.0.0.1", poll_s: float = 1.0):
        self.zenoh = zenoh
        self.components = [(c, c) if isinstance(c, str) else (c[0], c[1]) for c in components]
        self.ids = [c for c, _ in self.components]
        self.prefix, self.host, self.rate_hz, self.poll_s = prefix, host, rate_hz, poll_s
        self._port = port
        self.session = None
        self.server = None
        self.streams: list[Stream] = []
        self._subs: list = []
        self._params: dict[str, object] = {}  # parameter name -> value, as last read from the daemons
        self._plock = threading.Lock()
        self._subscribed_params: set[str] = set()
        # values changed elsewhere, waiting for the SDK to publish them (_poll), and the parameter name only the
        # bridge's own connection sends, which marks its setParameters as that publish
        self._outgoing: dict[str, object] = {}
        self._token = "energyctl-bridge-publish/" + secrets.token_hex(16)
        self._stop = threading.Event()
        # the graph's or the parameters' thread ended by an unexpected exception: the bridge has failed (its command
        # exits 1), rather than serve a graph or parameters nobody updates any more
        self.failure = Failure("energyctl foxglove")
        self._poller: threading.Thread | None = None
        self.counts = {"param_gets": 0, "param_sets": 0, "param_set_errors": 0, "config_reads_failed": 0,
                       "service_calls": 0, "service_errors": 0, "param_publishes": 0}
        self._clock = threading.Lock()
        self.last_error = ""
        # the connection graph: live components (by their liveliness tokens), kept by the graph thread
        self.plants = {c: p for c, p in self.components}
        self.nodes: dict[str, Node] = {}
        self._graph: Graph | None = None  # as last published
        self._glock = threading.Lock()  # nodes and _graph; never held by an SDK callback (see _listener)
        self._alive_sub = None
        self._watcher: threading.Thread | None = None
        self._hold: GraphHold | None = None  # the bridge's own graph subscription (see GraphHold)
        self.graph_counts = {"tokens_seen": 0, "tokens_gone": 0, "status_unanswered": 0, "graph_updates": 0,
                             "hold_reconnects": 0}

    # ------------------------------------------------------------------------------------------------ life cycle

    def start(self) -> Bridge:
        from foxglove.websocket import Capability

        import foxglove

        try:
            self.session = open_session(self.zenoh)
            self.context = foxglove.Context()  # this bridge's channels only, not the SDK's global context
            for cid, plant in self.components:
                for leaf, (topic_leaf, schema_name, codec) in STREAMS.items():
                    zkey = key(self.prefix, plant if leaf == "meas" else cid, leaf)
                    schema = foxglove.Schema(name=schema_name, encoding="jsonschema",
                                             data=json.dumps(json_schema(codec.model)).encode())
                    topic = key(self.prefix, cid, topic_leaf)
                    ch = foxglove.Channel(topic, schema=schema, message_encoding="json", context=self.context)
                    s = Stream(zkey, topic, codec, ch, Decimator(self.rate_hz), codec.bool_positions)
                    self.streams.append(s)
                    self._subs.append(self.session.declare_subscriber(zkey, s.on_sample))
                for leaf, (topic_leaf, schema_name, model) in LIVE_STREAMS.items():
                    zkey = topic = key(self.prefix, cid, topic_leaf)
                    schema = foxglove.Schema(name=schema_name, encoding="jsonschema",
                                             data=json.dumps(json_schema(model)).encode())
                    ch = foxglove.Channel(topic, schema=schema, message_encoding="json", context=self.context)
                    s = Stream(zkey, topic, None, ch, Decimator(0 if leaf == "events" else self.rate_hz), ())
                    self.streams.append(s)
                    self._subs.append(self.session.declare_subscriber(zkey, s.on_sample))
            for cid in self.ids:
                self._refresh(cid, GET_TIMEOUT_S)  # a component not up yet: its parameters come with the next get
            self.server = foxglove.start_server(
                name="energyctl", host=self.host, port=self._port, context=self.context,
                capabilities=[Capability.Parameters, Capability.Services, Capability.ConnectionGraph],
                server_listener=_listener(self), supported_encodings=["json"], services=self._services())
            self._hold = GraphHold.taken(self.host, self.server.port)  # before any publish (see GraphHold)
            self._publish_graph()  # empty until the tokens come: what a client subscribing now is sent
            # the tokens, those already declared first (history); a channel read by the graph thread, no Python
            # callback (dropping one at close can deadlock zenoh-python against the GIL)
            self._alive_sub = self.session.liveliness().declare_subscriber(
                key(self.prefix, "*", "alive"), zenoh.handlers.FifoChannel(256), history=True)
            self._watcher = guarded(self.failure, "foxglove-graph", self._watch, self._alive_sub.handler,
                                    on_failure=self._stop.set)
            self._watcher.start()
            self._poller = guarded(self.failure, "foxglove-params", self._poll, on_failure=self._stop.set)
            self._poller.start()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        self._stop.set()
        if self._poller is not None:
            self._poller.join(2 * GET_TIMEOUT_S + 1.0)
            self._poller = None
        if self._alive_sub is not None:
            try:
                self._alive_sub.undeclare()  # closes its channel: the graph thread's recv ends
            except Exception:  # noqa: BLE001 - closing anyway
                pass
            self._alive_sub = None
        if self._watcher is not None:
            self._watcher.join(GET_TIMEOUT_S + 1.0)  # it may be in a status query
            self._watcher = None
        for sub in self._subs:  # no callback logs after this
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        self._subs = []
        if self.server is not None:
            with self._glock:  # no publish from here on
                server, self.server = self.server, None
            server.stop()  # with the GIL released: the SDK calls the listener as the hold's connection ends
        if self._hold is not None:
            self._hold.close()
            self._hold = None
        for s in self.streams:
            s.channel.close()
        if self.session is not None:
            close_session(self.session)
            self.session = None

    def __enter__(self) -> Bridge:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def status(self) -> dict:
        channels = {s.topic: s.status() for s in self.streams}
        with self._clock:
            counts = dict(self.counts)
        with self._plock:
            n_params = len(self._params)
        with self._glock:
            graph = {"live": {c: {"controller": n.controller, "neighbours": list(n.neighbours)}
                              for c, n in sorted(self.nodes.items())},
                     "held": self._hold is not None and not self._hold.lost, **self.graph_counts}
        return {"state": "failed" if self.failure else "serving", "failure": self.failure.reason,
                "port": self.port, "components": self.ids, "rate_hz": self.rate_hz, "channels": channels,
                "received": sum(c["received"] for c in channels.values()),
                "logged": sum(c["logged"] for c in channels.values()),
                "dropped": sum(c["dropped"] for c in channels.values()),
                "invalid": sum(c["invalid"] for c in channels.values()),
                "parameters_known": n_params, "graph": graph, **counts,
                **({"last_error": self.last_error} if self.last_error else {})}

    def _count(self, name: str) -> None:
        with self._clock:
            self.counts[name] += 1

    # ------------------------------------------------------------------------------------------------ queries

    def _ask(self, cid: str, what: str, sets: list[str] | None = None, timeout_s: float = GET_TIMEOUT_S) -> dict:
        from clients.query import ask

        return ask(self.session, self.prefix, cid, what, sets, timeout_s)

    def _refresh(self, cid: str, timeout_s: float) -> dict[str, object] | None:
        """Reads ``cid``'s config into the parameter cache; the parameters whose value changed, or None if the
        daemon did not answer."""
        from clients.query import QueryError

        try:
            reply = self._ask(cid, "config", timeout_s=timeout_s)
        except QueryError as e:
            self._count("config_reads_failed")
            self.last_error = f"{cid}: {e}"
            return None
        return self._store(flatten_config(cid, reply))

    def _store(self, values: dict[str, object]) -> dict[str, object]:
        with self._plock:
            changed = {k: v for k, v in values.items() if k not in self._params or self._params[k] != v}
            self._params.update(values)
        return changed

    def _poll(self) -> None:
        """The parameters' thread: every poll_s rereads the configs of the components whose parameters some client
        subscribes to and publishes changes made elsewhere (energyctl query --set, another client).

        It never calls the SDK's publish_parameter_values: that takes the SDK's parameter-subscription lock without
        releasing the GIL, and the SDK calls the listener (Python: it needs the GIL) under that lock whenever a
        client's subscription to a name is the first or its leaving the last, which any client can make happen
        (a name the bridge does not know). Instead the bridge's own connection (GraphHold) sends the server a
        setParameters naming only the bridge's secret token; the listener answers it with the changed values, and
        the SDK publishes them to the subscribed clients from its own task, with no Python thread waiting on its
        locks."""
        while not self._stop.wait(self.poll_s):
            with self._plock:
                wanted = {n.split(".", 1)[0] for n in self._subscribed_params}
            changed: dict[str, object] = {}
            for cid in (c for c in self.ids if c in wanted):
                changed.update(self._refresh(cid, GET_TIMEOUT_S) or {})
            if changed and not self._stop.is_set():
                self._publish_parameters(changed)

    def _publish_parameters(self, values: dict[str, object]) -> bool:
        """Hands values to the SDK for every client subscribed to them, through the bridge's own connection (see
        _poll); False (and last_error) if that connection is gone or the server did not answer within its timeout
        (the values are sent with the next change then)."""
        hold = self._hold
        with self._plock:
            self._outgoing.update(values)
        if hold is None or hold.lost:
            self.last_error = "parameter values not published: the bridge's own connection is gone"
            return False
        if not hold.set_token(self._token):
            self.last_error = "parameter values not published: the server did not answer the bridge's own connection"
            return False
        self._count("param_publishes")
        return True

    def _take_outgoing(self) -> list:
        """The listener's answer to the bridge's own setParameters: the values waiting to be published."""
        with self._plock:
            values, self._outgoing = self._outgoing, {}
        return self._parameters(values)

    @staticmethod
    def _parameters(values: dict[str, object]) -> list:
        from foxglove.websocket import Parameter

        return [Parameter(name, value=v) for name, v in values.items()]

    def get_parameters(self, names: list[str]) -> list:
        """Foxglove getParameters: all (no names) or the named ones, as the daemons answer now (their cached values
        if one does not answer within GET_TIMEOUT_S)."""
        self._count("param_gets")
        ids = self.ids if not names else [c for c in self.ids if any(n.startswith(c + ".") for n in names)]
        for cid in ids:
            self._refresh(cid, GET_TIMEOUT_S)
        with self._plock:
            values = dict(self._params) if not names else {n: self._params[n] for n in names if n in self._params}
        return self._parameters(values)

    def set_parameters(self, params: list) -> list:
        """Foxglove setParameters: one config/set per component, with every entry for it (the daemon applies all
        or none). Returns the parameters' values after it: the new ones, or, where the daemon refused, the values
        still in force; a refusal is also published as an error status naming the field."""
        from foxglove.websocket import StatusLevel

        from clients.query import QueryError

        if any(p.name == self._token for p in params):  # the bridge's own connection: publish (see _poll)
            return self._take_outgoing()
        self._count("param_sets")
        by_id: dict[str, list[str]] = {}
        names = [p.name for p in params]
        errors = []
        for p in params:
            cid, _, dotted = p.name.partition(".")
            if cid not in self.ids or not dotted:
                errors.append(f"{p.name}: unknown parameter (expected ID.controller.<key> or ID.lifecycle, ID one "
                              f"of {', '.join(self.ids)})")
                continue
            try:
                by_id.setdefault(cid, []).append(f"{dotted}={toml_text(p.get_value())}")
            except ValueError as e:
                errors.append(f"{p.name}: {e}")
        for cid, sets in by_id.items():
            try:
                reply = self._ask(cid, "config", sets, timeout_s=SET_TIMEOUT_S)
            except QueryError as e:
                errors.append(f"{cid}: config/set {sets} refused: {e}")
                continue
            values = flatten_config(cid, reply)
            for s in sets:
                if s.startswith("lifecycle="):  # handed to the loop, made at its next pass (status shows it)
                    values[f"{cid}.lifecycle"] = s.split("=", 1)[1].strip().strip('"')
            self._store(values)
            if self.server is not None:
                self.server.remove_status([f"{cid}/config/set"])
        for text in errors:
            self._count("param_set_errors")
            self.last_error = text
            print(f"energyctl foxglove: {text}", file=sys.stderr, flush=True)
            if self.server is not None:
                cid = text.split(":", 1)[0].split(".", 1)[0]
                self.server.publish_status(text, StatusLevel.Error, f"{cid}/config/set")
        with self._plock:
            return self._parameters({n: self._params[n] for n in names if n in self._params})

    def subscribe_parameters(self, names: list[str], on: bool) -> None:
        with self._plock:
            (self._subscribed_params.update if on else self._subscribed_params.difference_update)(names)

    # ------------------------------------------------------------------------------------------------ graph

    def _watch(self, tokens) -> None:
        """The graph thread: each liveliness token that appears (then the component's status query) or goes away
        updates the graph, published at once."""
        head = self.prefix.rstrip("/") + "/"
        while True:
            try:
                sample = tokens.recv()
            except Exception:  # noqa: BLE001 - the subscriber was undeclared (close): its channel is closed
                return
            k = str(sample.key_expr)
            if not (k.startswith(head) and k.endswith("/alive")):
                continue
            cid = k[len(head):-len("/alive")]
            if sample.kind == zenoh.SampleKind.PUT:
                node = self._probe(cid)
                with self._glock:
                    self.graph_counts["tokens_seen"] += 1
                    self.nodes[cid] = node
            else:
                with self._glock:
                    self.graph_counts["tokens_gone"] += 1
                    self.nodes.pop(cid, None)
            if self._stop.is_set():
                return
            self._publish_graph()

    def _probe(self, cid: str) -> Node:
        """A component whose token appeared: a controller (with its neighbours) if it answers its status query."""
        from clients.query import QueryError

        try:
            reply = self._ask(cid, "status", timeout_s=GET_TIMEOUT_S)
        except QueryError:
            with self._glock:
                self.graph_counts["status_unanswered"] += 1
            return Node()
        return Node(True, tuple(sorted(reply.get("neighbours") or {})))

    def _publish_graph(self) -> None:
        """Publishes the graph of self.nodes if it changed (never from an SDK callback: the SDK deadlocks); first a
        new GraphHold if the old one's connection ended."""
        hold, server = self._hold, self.server
        if hold is not None and hold.lost and server is not None and not self._stop.is_set():
            hold.close()
            try:
                self._hold = GraphHold.taken(self.host, server.port)
            except (OSError, RuntimeError) as e:  # no publish without it (that is what deadlocks): next time again
                self.last_error = f"connection graph not published: {e}"
                return
            self.graph_counts["hold_reconnects"] += 1
        from foxglove import ConnectionGraph

        with self._glock:
            graph = connection_graph(self.prefix, self.nodes, self.plants)
            server = self.server
            if graph == self._graph or server is None:
                return
            published, subscribed, services = graph
            g = ConnectionGraph()
            for t, ids in published.items():
                g.set_published_topic(t, list(ids))
            for t, ids in subscribed.items():
                g.set_subscribed_topic(t, list(ids))
            for name, ids in services.items():
                g.set_advertised_service(name, list(ids))
            server.publish_connection_graph(g)
            self._graph = graph
            self.graph_counts["graph_updates"] += 1

    # ------------------------------------------------------------------------------------------------ services

    def _services(self) -> list:
        from foxglove import MessageSchema, Schema, Service, ServiceSchema

        def js(name: str, schema: dict) -> MessageSchema:
            return MessageSchema(encoding="json", schema=Schema(name=name, encoding="jsonschema",
                                                                data=json.dumps(schema).encode()))

        empty = js("energyctl.Empty", {"type": "object", "properties": {}})
        out = []
        for cid in self.ids:
            for what, req, resp in (("status", empty, "energyctl.StatusReply"),
                                    ("config", empty, "energyctl.ConfigReply"),
                                    ("config/set", js("energyctl.ConfigSetRequest",
                                                      REPLY_MODELS["energyctl.ConfigSetRequest"].model_json_schema()),
                                     "energyctl.ConfigSetReply")):
                schema = ServiceSchema(resp, request=req, response=js(resp, REPLY_MODELS[resp].model_json_schema()))
                out.append(Service(f"{cid}/{what}", schema=schema, handler=self._handler(cid, what)))
        return out

    def _handler(self, cid: str, what: str):
        """A service handler: the daemon's JSON answer; a refusal raises, which the SDK sends as the call's
        failure with the daemon's text."""
        from clients.query import QueryError

        def handle(request) -> bytes:
            self._count("service_calls")
            sets = None
            if what == "config/set":
                try:
                    sets = json.loads(request.payload or b"null")["set"]
                    if not isinstance(sets, list) or not sets or not all(isinstance(s, str) for s in sets):
                        raise TypeError
                except (ValueError, TypeError, KeyError):
                    self._count("service_errors")
                    raise ValueError('set: expected {"set": ["key=value", ...]}') from None
            try:
                reply = self._ask(cid, "config" if sets else what, sets,
                                  timeout_s=SET_TIMEOUT_S if sets else GET_TIMEOUT_S)
            except QueryError as e:
                self._count("service_errors")
                raise RuntimeError(f"{cid}: {e}") from None
            if sets:
                self._store(flatten_config(cid, reply))
            return finite_json(reply)

        return handle


class GraphHold:
    """The bridge's own WebSocket connection to its Foxglove server, subscribed to the connection graph from the
    server's start to its stop, so that no Foxglove client's subscription is ever the first, nor its leaving the
    last.

    Why: foxglove-sdk (0.30) calls the listener's on_connection_graph_subscribe (first subscriber) and
    on_connection_graph_unsubscribe (last one gone) while holding its graph lock, and those are Python: they wait
    for the GIL. ``publish_connection_graph`` takes the same lock without releasing the GIL. A client subscribing
    while the graph thread published deadlocked the whole bridge (the bridge's graph test hung CI for 90 minutes;
    reproduced here in 1 of 9 runs). With this subscription taken before the first publish and kept until the
    server has stopped, the SDK never calls Python under that lock while anything publishes.

    Parameters have the same hazard (the SDK calls the listener under its parameter-subscription lock, which
    ``publish_parameter_values`` takes holding the GIL), but a hold cannot cover it: any client can subscribe to a
    name nobody else does. So the bridge never calls publish_parameter_values; this connection asks the server to
    publish instead (``set_token``, Bridge._poll).

    The few lines of RFC 6455 a client needs: the upgrade request, masked text frames; whatever the server
    sends (its info, advertisements, graph updates) is read and dropped by a thread of its own, which sets
    ``ready`` at the first graph update (the SDK has taken the subscription) and ``lost`` if the connection ends
    while not closed (the bridge then opens a new one before its next publish)."""

    TIMEOUT_S = 5.0
    MARK = b"connectionGraphUpdate"  # in the server's JSON text frames, unmasked and uncompressed

    def __init__(self, host: str, port: int):
        import base64
        import os
        import socket

        self.ready, self.lost, self._closing = threading.Event(), False, False
        self._marks: dict[bytes, threading.Event] = {}  # request ids awaited in the server's answers
        self._n = 0
        host = "127.0.0.1" if host in ("", "0.0.0.0") else "::1" if host == "::" else host
        self.sock = socket.create_connection((host, port), timeout=self.TIMEOUT_S)
        try:
            ws_key = base64.b64encode(os.urandom(16)).decode()
            where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
            self.sock.sendall(f"GET / HTTP/1.1\r\nHost: {where}\r\nUpgrade: websocket\r\n"
                              f"Connection: Upgrade\r\nSec-WebSocket-Key: {ws_key}\r\nSec-WebSocket-Version: 13\r\n"
                              "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n".encode())
            head = b""
            while b"\r\n\r\n" not in head:
                chunk = self.sock.recv(4096)
                if not chunk:
                    raise ConnectionError("the Foxglove server closed the bridge's own connection in its handshake")
                head += chunk
            status, _, rest = head.partition(b"\r\n\r\n")
            status = status.split(b"\r\n", 1)[0]
            if status.split(b" ")[1:2] != [b"101"]:
                raise ConnectionError(f"the Foxglove server refused the bridge's own connection: {status.decode()!r}")
            self.sock.sendall(self.text_frame(json.dumps({"op": "subscribeConnectionGraph"}).encode()))
            self.sock.settimeout(None)
        except BaseException:
            self.sock.close()
            raise
        self._thread = threading.Thread(target=self._drain, args=(rest,), name="foxglove-graph-hold", daemon=True)
        self._thread.start()

    @classmethod
    def taken(cls, host: str, port: int) -> GraphHold:
        """A hold whose subscription the server has taken (its first graph update came), or an error saying why."""
        hold = cls(host, port)
        if not hold.ready.wait(cls.TIMEOUT_S):
            hold.close()
            raise RuntimeError(f"the Foxglove server on port {port} did not take the bridge's own connection-graph "
                               f"subscription within {cls.TIMEOUT_S:g} s")
        return hold

    def set_token(self, token: str) -> bool:
        """Sends the server a setParameters naming only ``token`` (Bridge._poll: the listener answers it with the
        values to publish, which the SDK then publishes from its own task) and waits for the server's answer to it
        (False: none within TIMEOUT_S, or the connection is gone). One caller at a time (the parameters thread)."""
        self._n += 1
        mark = f'"energyctl-hold-{self._n}"'.encode()  # with its quotes: -1 is not found inside -10
        ev = self._marks[mark] = threading.Event()
        try:
            self.sock.sendall(self.text_frame(json.dumps({"op": "setParameters", "parameters": [
                {"name": token, "value": self._n}], "id": mark.decode().strip('"')}).encode()))
            return ev.wait(self.TIMEOUT_S)
        except OSError:
            return False
        finally:
            self._marks.pop(mark, None)

    @staticmethod
    def text_frame(payload: bytes) -> bytes:
        """One final text frame, masked as a client's must be (RFC 6455, 5.2)."""
        import os
        import struct

        n = len(payload)
        length = (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n) if n < 65536
                  else bytes([0x80 | 127]) + struct.pack(">Q", n))
        mask = os.urandom(4)
        return bytes([0x81]) + length + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))

    def _drain(self, seen: bytes) -> None:
        try:
            while True:
                if not self.ready.is_set() and self.MARK in seen:
                    self.ready.set()
                for mark, ev in list(self._marks.items()):
                    if mark in seen:
                        ev.set()
                chunk = self.sock.recv(65536)
                if not chunk:
                    break
                seen = seen[-64:] + chunk
        except OSError:  # closed
            pass
        finally:  # (also after an exception nobody expected: printed, and the bridge opens a new hold)
            if not self._closing:
                self.lost = True
                print("energyctl foxglove: the bridge's own connection-graph subscription ended; opening a new one "
                      "before the next graph update", file=sys.stderr, flush=True)

    def close(self) -> None:
        import socket

        self._closing = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes the drain thread's recv
        except OSError:
            pass
        self.sock.close()
        self._thread.join(self.TIMEOUT_S)


def _listener(bridge: Bridge):
    """A foxglove.websocket.ServerListener for the bridge's parameters. The SDK calls these on the asking client's
    connection task: that client's stream waits until they return (a set: until the daemon answers, normally within
    a tick, at most SET_TIMEOUT_S); other clients' streams do not."""
    from foxglove.websocket import ServerListener

    class Listener(ServerListener):
        def on_get_parameters(self, client, param_names, request_id=None):  # noqa: ARG002
            return bridge.get_parameters(list(param_names))

        def on_set_parameters(self, client, parameters, request_id=None):  # noqa: ARG002
            return bridge.set_parameters(list(parameters))

        def on_parameters_subscribe(self, param_names):
            bridge.subscribe_parameters(list(param_names), True)

        def on_parameters_unsubscribe(self, param_names):
            bridge.subscribe_parameters(list(param_names), False)

        # on_connection_graph_(un)subscribe: left to the base class; the SDK calls them only for its first
        # subscriber and after its last, the bridge's own (GraphHold); publishing from there would deadlock it

    return Listener()
