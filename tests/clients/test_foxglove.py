"""energyctl foxglove: the Zenoh -> Foxglove WebSocket bridge (clients/foxglove_bridge.py), against a daemon in this
process and a stand-in plant publishing measurements, seen by a WebSocket client speaking the Foxglove protocol."""

from __future__ import annotations

import json
import struct
import threading
import time
from contextlib import ExitStack, contextmanager

import pytest

pytest.importorskip("foxglove.websocket")  # not the foxglove/ layout directory of this tree
ws_client = pytest.importorskip("websockets.sync.client")

from conftest import SCENARIOS, PumpingClient  # noqa: E402

from clients.foxglove_bridge import Bridge, Decimator, Node, connection_graph, parse_components, toml_text  # noqa: E402
from clients.live import configs_from_scenario, wait_until  # noqa: E402
from schemas.codec import MEAS  # noqa: E402
from schemas.component import ComponentConfig, ZenohConfig, config_from_dict  # noqa: E402
from schemas.messages import Interaction, Measurement, json_schema  # noqa: E402
from schemas.scenario import load_scenario  # noqa: E402
from service.daemon.bus import free_tcp_port, open_session, publisher  # noqa: E402
from service.daemon.daemon import Daemon  # noqa: E402

# foxglove-sdk 0.30 accepts only these subprotocols; it answers "foxglove.websocket.v1" alone with HTTP 400
SUBPROTOCOLS = ["foxglove.sdk.v1"]
RATE_HZ = 100.0  # the bridge's decimation in the live test; the plant publishes bursts of BURST back to back
BURST = 5


def expected_meas(seq: int) -> dict:
    return {"seq": seq, "t": seq * 1e-3, "i": 1.0 + seq * 1e-3, "v": 80.0 + (seq % 100) * 0.01, "u": 85.0,
            "i_load": 0.5}


class FoxgloveClient(PumpingClient):
    """The few parts of the Foxglove WebSocket protocol a test needs, on a blocking websockets connection."""

    def __init__(self, port: int):
        self._stack = ExitStack()
        self.ws = self._stack.enter_context(ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS,
                                                              open_timeout=5.0))
        self.channels: dict[str, dict] = {}  # topic -> advertised channel
        self.services: dict[str, dict] = {}  # name -> advertised service
        self.data: dict[int, list[dict]] = {}  # subscription id -> decoded messages
        self.responses: dict[int, bytes] = {}  # call id -> service response payload
        self.ops: list[dict] = []  # every other JSON message (parameterValues, status, serviceCallFailure, ...)
        # the connection graph as the updates so far make it: name -> ids
        self.graph = {"published": {}, "subscribed": {}, "services": {}}
        self.graph_updates = 0

    def _take(self, m) -> None:
        if isinstance(m, str):
            msg = json.loads(m)
            if msg["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in msg["channels"]})
            elif msg["op"] == "advertiseServices":
                self.services.update({s["name"]: s for s in msg["services"]})
            elif msg["op"] == "connectionGraphUpdate":
                self._graph_update(msg)
            else:
                self.ops.append(msg)
        elif m[0] == 1:  # messageData: subscription id u32, log time u64, payload
            (sub,) = struct.unpack_from("<I", m, 1)
            self.data.setdefault(sub, []).append(json.loads(m[13:]))
        elif m[0] == 3:  # serviceCallResponse: service id u32, call id u32, encoding (u32 length), payload
            _sid, call, n = struct.unpack_from("<III", m, 1)
            self.responses[call] = bytes(m[13 + n:])

    def _graph_update(self, msg: dict) -> None:
        g = self.graph
        g["published"].update({t["name"]: sorted(t["publisherIds"]) for t in msg["publishedTopics"]})
        g["subscribed"].update({t["name"]: sorted(t["subscriberIds"]) for t in msg["subscribedTopics"]})
        g["services"].update({t["name"]: sorted(t["providerIds"]) for t in msg["advertisedServices"]})
        for name in msg["removedTopics"]:
            g["published"].pop(name, None)
            g["subscribed"].pop(name, None)
        for name in msg["removedServices"]:
            g["services"].pop(name, None)
        self.graph_updates += 1

    def send(self, msg: dict) -> None:
        self.ws.send(json.dumps(msg))

    def op(self, name: str, **match) -> dict | None:
        for m in self.ops:
            if m["op"] == name and all(m.get(k) == v for k, v in match.items()):
                return m
        return None

    def call(self, service: str, request: dict, call_id: int, timeout_s: float = 5.0) -> dict:
        """A service call: the response as JSON, or {"failure": message}."""
        sid = self.services[service]["id"]
        self.ws.send(struct.pack("<BIII", 2, sid, call_id, 4) + b"json" + json.dumps(request).encode())
        assert self.pump(lambda: call_id in self.responses or self.op("serviceCallFailure", callId=call_id),
                         timeout_s), service
        if call_id in self.responses:
            return json.loads(self.responses[call_id])
        return {"failure": self.op("serviceCallFailure", callId=call_id)["message"]}

    def set_parameter(self, name: str, value: float, request_id: str, timeout_s: float = 5.0) -> dict:
        """setParameters; the answer's parameter values by name."""
        self.send({"op": "setParameters", "parameters": [{"name": name, "value": value, "type": "float64"}],
                   "id": request_id})
        assert self.pump(lambda: self.op("parameterValues", id=request_id), timeout_s), request_id
        return {p["name"]: p.get("value") for p in self.op("parameterValues", id=request_id)["parameters"]}

    def close(self) -> None:
        self._stack.close()


def test_decimation_keeps_at_most_the_rate():
    d = Decimator(1000.0)  # 1 ms
    kept = sum(d.keep(k * 100_000) for k in range(100_000))  # 10 kHz for 10 s
    assert 10_000 <= kept <= 10_002
    d = Decimator(1000.0)
    assert sum(d.keep(5_000_000_000) for _ in range(50)) == 1  # a burst at one instant passes one message
    assert d.keep(5_001_000_000) and not d.keep(5_001_400_000) and d.keep(5_001_500_000)
    assert all(Decimator(0).keep(0) for _ in range(10))  # 0: no decimation


def test_components_and_parameter_values():
    assert parse_components("source, b:rig") == [("source", "source"), ("b", "rig")]
    with pytest.raises(ValueError, match="component id"):
        parse_components("a/b")
    assert [toml_text(v) for v in (800, 800.0, 1e-4, True, "energy", [1.0, 2])] == \
        ["800", "800.0", "0.0001", "true", '"energy"', "[1.0, 2]"]
    with pytest.raises(ValueError, match="unset"):
        toml_text(None)


@contextmanager
def daemon_stack(neighbours: list[str], **extra):
    """A daemon for component "source" in this process (clock trigger, 1 kHz, these neighbours, no log unless
    ``extra`` sets log_dir) on a free loopback port, and a stand-in plant publishing measurements on
    energyctl/source/meas in bursts of BURST: (daemon, endpoint, its loop thread). Stopping and closing the daemon
    earlier is allowed."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _plant, _load = configs_from_scenario(scn, ep, lockstep=False, rate_hz=1000.0)
    comp["neighbours"] = neighbours
    comp.update(extra)
    comp["loop"]["trigger"] = "clock"
    comp["forecast"] = {"enabled": False}
    for k in ("local_reference_W", "nice"):
        comp.pop(k, None)
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    loop = threading.Thread(target=d.run_loop, daemon=True)
    loop.start()
    stop = threading.Event()
    plant = open_session(ZenohConfig(mode="peer", connect=[ep]))
    pub = publisher(plant, "energyctl/source/meas")

    def run_plant():
        seq = 0
        while not stop.wait(0.01):
            for _ in range(BURST):
                m = expected_meas(seq)
                pub.put(MEAS.encode(m["seq"], m["t"], m["i"], m["v"], m["u"], m["i_load"]))
                seq += 1

    pt = threading.Thread(target=run_plant, daemon=True)
    pt.start()
    try:
        yield d, ep, loop
    finally:
        stop.set()
        pt.join(2.0)
        pub.undeclare()
        plant.close()
        d.stop()
        loop.join(2.0)
        d.close()


@pytest.fixture
def stack():
    """daemon_stack without neighbours: (daemon, endpoint)."""
    with daemon_stack([]) as (d, ep, _loop):
        yield d, ep


def test_the_bridge_streams_sets_and_serves(stack):
    d, ep = stack
    bridge = Bridge(ZenohConfig(mode="peer", connect=[ep]), ["source"], port=0, rate_hz=RATE_HZ)
    client = None
    try:
        t_start = time.monotonic()  # before its subscribers exist
        bridge.start()
        assert bridge.port > 0
        client = FoxgloveClient(bridge.port)
        topics = {"energyctl/source/meas", "energyctl/source/cmd", "energyctl/source/z_out"}
        services = {"source/status", "source/config", "source/config/set"}
        assert client.pump(lambda: topics <= set(client.channels) and services <= set(client.services))
        meas = client.channels["energyctl/source/meas"]
        assert (meas["encoding"], meas["schemaName"], meas["schemaEncoding"]) == \
            ("json", "energyctl.Measurement", "jsonschema")
        assert json.loads(meas["schema"]) == json_schema(Measurement)  # the daemon's MCAP log carries this one
        assert client.channels["energyctl/source/cmd"]["schemaName"] == "energyctl.Command"
        assert client.channels["energyctl/source/z_out"]["schemaName"] == "energyctl.Interaction"

        # the measurements arrive decoded, field for field; the daemon's commands too
        client.send({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": client.channels[f"energyctl/source/{leaf}"]["id"]}
            for k, leaf in ((1, "meas"), (2, "cmd"), (3, "z_out"))]})
        assert client.pump(lambda: len(client.data.get(1, [])) >= 20 and client.data.get(2) and client.data.get(3),
                           10.0), {k: len(v) for k, v in client.data.items()}
        got = client.data[1]
        assert all(m == expected_meas(m["seq"]) for m in got), got[:3]
        assert [m["seq"] for m in got] == sorted({m["seq"] for m in got})  # in order, no repeats
        cmd = client.data[2][-1]
        assert set(cmd) == {"seq", "t", "du_dt", "du_dt_next", "limited"} and isinstance(cmd["limited"], bool)
        assert set(client.data[3][-1]) == set(json_schema(Interaction)["properties"])

        # parameters: the controller config, one parameter per setting
        client.send({"op": "getParameters", "parameterNames": [], "id": "g1"})
        assert client.pump(lambda: client.op("parameterValues", id="g1"))
        params = {p["name"]: p.get("value") for p in client.op("parameterValues", id="g1")["parameters"]}
        assert params["source.controller.K_per_s"] == 2000.0
        assert params["source.controller.limits.du_dt_max_V_per_s"] > 0
        assert params["source.lifecycle"] in ("active", "degraded")

        # a set goes to config/set: applied in the daemon, the new value is what Foxglove sees
        assert client.set_parameter("source.controller.K_per_s", 800.0, "s1")["source.controller.K_per_s"] == 800.0
        assert d.core.cfg.K_per_s == 800.0
        cfg = client.call("source/config", {}, 1)
        assert cfg["controller"]["K_per_s"] == 800.0 and cfg["config_version"] == 1
        st = client.call("source/status", {}, 2)
        assert st["id"] == "source" and st["config_version"] == 1

        # a refused set: an error status naming the field, and the value still in force
        assert client.set_parameter("source.controller.K_per_s", -1.0, "s2")["source.controller.K_per_s"] == 800.0
        assert client.pump(lambda: client.op("status", level=2))
        err = client.op("status", level=2)["message"]
        assert "K_per_s" in err and "greater than 0" in err, err
        assert d.core.cfg.K_per_s == 800.0
        # the same through the config/set service: the call fails with the daemon's text
        fail = client.call("source/config/set", {"set": ["controller.K_per_s=-5"]}, 3)
        assert "K_per_s" in fail["failure"], fail

        # the counters: decimated to RATE_HZ a channel (the plant sends bursts of 5 within microseconds)
        elapsed = time.monotonic() - t_start
        s = bridge.status()["channels"]["energyctl/source/meas"]
        assert s["received"] > 0 and s["logged"] >= 20 and s["dropped"] > 0 and s["invalid"] == 0
        assert s["logged"] + s["dropped"] + s["unsubscribed"] <= s["received"]
        assert s["logged"] + s["unsubscribed"] <= RATE_HZ * elapsed + 2
        st = bridge.status()
        assert st["param_sets"] == 2 and st["param_set_errors"] == 1 and st["service_errors"] == 1
    finally:
        if client is not None:
            client.close()
        bridge.close()


def test_a_component_that_does_not_answer_still_streams_and_its_services_fail(stack):
    """A component id no daemon serves: the bridge starts (no parameters for it), its services fail naming it."""
    _d, ep = stack
    bridge = Bridge(ZenohConfig(mode="peer", connect=[ep]), ["ghost"], port=0)
    client = None
    try:
        bridge.start()
        assert bridge.status()["config_reads_failed"] == 1
        client = FoxgloveClient(bridge.port)
        assert client.pump(lambda: "ghost/status" in client.services)
        fail = client.call("ghost/status", {}, 1, timeout_s=5.0)
        assert "ghost" in fail["failure"] and "no answer" in fail["failure"]
        assert wait_until(lambda: bridge.status()["service_errors"] == 1, 2.0)
    finally:
        if client is not None:
            client.close()
        bridge.close()


def test_the_graph_of_components():
    """connection_graph: each live component's keys; a controller's plant, neighbours and services."""
    nodes = {"a": Node(True, ("load",)), "b": Node(True, ("a",)), "load": Node()}
    pub, sub, srv = connection_graph("p", nodes, {"b": "rig"})
    assert pub == {"p/a/z": ("a",), "p/a/cmd": ("a",), "p/b/z": ("b",), "p/b/cmd": ("b",), "p/load/z": ("load",),
                   "p/a/meas": (), "p/rig/meas": ()}
    assert sub == {"p/a/meas": ("a",), "p/rig/meas": ("b",), "p/load/z": ("a",), "p/a/z": ("b",), "p/a/cmd": (),
                   "p/b/z": (), "p/b/cmd": ()}
    assert srv["p/b/config/set"] == ("b",) and len(srv) == 6
    assert connection_graph("p", {"load": Node()}, {}) == ({"p/load/z": ("load",)}, {"p/load/z": ()}, {})


def test_the_connection_graph_follows_liveliness():
    """A client subscribed to the connection graph gets the controller with its keys and the interaction link
    from its neighbour, and an update each time a liveliness token goes away."""
    src = {"energyctl/source/status": ["source"], "energyctl/source/config": ["source"],
           "energyctl/source/config/set": ["source"]}
    with ExitStack() as stack:
        d, ep, loop = stack.enter_context(daemon_stack(["load"]))
        load = open_session(ZenohConfig(mode="peer", connect=[ep]))  # the neighbour: only its token here
        stack.callback(load.close)
        token = load.liveliness().declare_token("energyctl/load/alive")
        bridge = Bridge(ZenohConfig(mode="peer", connect=[ep]), ["source"], port=0)
        stack.callback(bridge.close)
        bridge.start()
        client = FoxgloveClient(bridge.port)
        stack.callback(client.close)
        client.send({"op": "subscribeConnectionGraph"})
        g = client.graph
        assert client.pump(lambda: g["published"].get("energyctl/load/z") == ["load"]
                           and g["published"].get("energyctl/source/cmd") == ["source"], 10.0), g
        assert g["published"] == {"energyctl/source/z": ["source"], "energyctl/source/cmd": ["source"],
                                  "energyctl/load/z": ["load"], "energyctl/source/meas": []}
        assert g["subscribed"] == {"energyctl/source/meas": ["source"], "energyctl/load/z": ["source"],
                                   "energyctl/source/z": [], "energyctl/source/cmd": []}
        assert g["services"] == src

        # the neighbour goes: its link stays as the controller's subscription, with no publisher
        n = client.graph_updates
        token.undeclare()
        assert client.pump(lambda: client.graph_updates > n and g["published"]["energyctl/load/z"] == [], 10.0), g
        assert g["subscribed"]["energyctl/load/z"] == ["source"] and g["services"] == src

        # the controller goes (closed: its token with it): nothing is left
        n = client.graph_updates
        d.stop()
        loop.join(5.0)
        d.close()
        assert client.pump(lambda: client.graph_updates > n and not any(g.values()), 10.0), g
        st = bridge.status()["graph"]
        assert st["live"] == {} and st["held"] and st["tokens_seen"] == 2 and st["tokens_gone"] == 2


STRESS = r"""
import sys, threading
from websockets.sync import client as ws_client
from clients import foxglove_bridge as fb
from schemas.component import ZenohConfig
from service.daemon.bus import free_tcp_port

if sys.argv[1] == "without-hold":  # the bridge as it was: no subscription of its own
    class NoHold:
        lost = False
        @classmethod
        def taken(cls, host, port):
            return cls()
        def close(self):
            pass
    fb.GraphHold = NoHold
bridge = fb.Bridge(ZenohConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_tcp_port()}"]), [], port=0)
bridge.start()
done = threading.Event()

def publish():  # the graph thread's part: a component comes and goes, the graph is published each time
    k = 0
    while not done.is_set():
        with bridge._glock:
            if k % 2:
                bridge.nodes.pop("x", None)
            else:
                bridge.nodes["x"] = fb.Node(True, ("y",))
        bridge._publish_graph()
        k += 1
        done.wait(0.001)

t = threading.Thread(target=publish, daemon=True)
t.start()
first = None
for i in range(150):  # Foxglove clients opening and closing the Topic Graph panel meanwhile
    with ws_client.connect(f"ws://127.0.0.1:{bridge.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as ws:
        ws.send('{"op": "subscribeConnectionGraph"}')
        ws.recv(timeout=5)
        if first is None:  # the publishes counted from the first client's subscription on
            first = bridge.graph_counts["graph_updates"]
        ws.send('{"op": "unsubscribeConnectionGraph"}')
during = bridge.graph_counts["graph_updates"] - first
done.set()
t.join(5)
bridge.close()
print("clients", i + 1, "updates", during)
"""


def test_clients_subscribing_to_the_graph_while_it_is_published_do_not_deadlock_the_bridge(tmp_path):
    """foxglove-sdk calls the listener (Python, needing the GIL) under the graph lock that publish_connection_graph
    takes while holding the GIL: a client's first subscription during a publish deadlocked the bridge (1 run in 9
    of the liveliness test). With the bridge's own subscription held (GraphHold), 150 clients come and go while the
    graph is published a thousand times a second; the same run without the hold deadlocks (5 of 5 within 20 s;
    ENERGYCTL_TEST_SDK_DEADLOCK=1 runs that too)."""
    import os
    import subprocess
    import sys

    from conftest import ROOT

    script = tmp_path / "stress.py"
    script.write_text(STRESS)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def run(how: str, timeout_s: float):
        return subprocess.run([sys.executable, str(script), how], capture_output=True, text=True,
                              timeout=timeout_s, env=env, cwd=ROOT)

    try:
        r = run("with-hold", 90.0)
    except subprocess.TimeoutExpired:
        pytest.fail("the bridge deadlocked: 150 graph subscriptions did not finish within 90 s")
    assert r.returncode == 0, r.stderr[-3000:]
    clients, updates = int(r.stdout.split()[1]), int(r.stdout.split()[3])
    # every client came and went, and the graph was published while they did (how often depends on the machine)
    assert clients == 150 and updates > 0, r.stdout
    # the same run without the hold deadlocks (5 of 5 here within 20 s): a race, so only on request; if a release
    # of the SDK stops deadlocking here, GraphHold can go
    if os.environ.get("ENERGYCTL_TEST_SDK_DEADLOCK"):
        with pytest.raises(subprocess.TimeoutExpired):
            run("without-hold", 20.0)


def test_a_lost_graph_hold_is_taken_again_before_the_next_publish():
    """The bridge's own graph subscription ends (the server dropped it): status says so, and the next graph
    update first opens a new one the server has taken, then publishes."""
    bridge = Bridge(ZenohConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_tcp_port()}"]), [], port=0)
    bridge.start()
    try:
        assert bridge.status()["graph"]["held"]
        old = bridge._hold
        old.sock.shutdown(2)  # as if the server had closed it
        assert wait_until(lambda: old.lost, 5.0)
        assert not bridge.status()["graph"]["held"]
        with bridge._glock:
            bridge.nodes["x"] = Node(True, ())
        bridge._publish_graph()
        st = bridge.status()["graph"]
        assert bridge._hold is not old and st["held"] and st["hold_reconnects"] == 1 and st["graph_updates"] == 2
    finally:
        bridge.close()


def test_a_bridge_thread_that_fails_fails_the_bridge_visibly(monkeypatch):
    """The graph thread ended by an exception nobody expected (a status reply it could not read, say): before, the
    bridge served on with a graph nobody updated; now it fails, says why in status (and its command exits 1)."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    bridge = Bridge(ZenohConfig(mode="peer", listen=[ep]), [], port=0)

    def probe(cid):
        raise TypeError(f"a status of {cid} it cannot read")

    monkeypatch.setattr(bridge, "_probe", probe)
    bridge.start()
    try:
        with open_session(ZenohConfig(mode="peer", connect=[ep])) as s:
            token = s.liveliness().declare_token("energyctl/x/alive")
            assert wait_until(lambda: bool(bridge.failure), 10.0)
            token.undeclare()
        st = bridge.status()
        assert st["state"] == "failed" and st["failure"].startswith("foxglove-graph: TypeError: a status of x")
        assert bridge._stop.is_set()  # the parameters' thread stops too
    finally:
        bridge.close()


def test_a_change_made_elsewhere_reaches_the_subscribed_clients_through_the_server(stack):
    """A config set outside Foxglove (energyctl query --set) is published to the clients subscribed to it: the
    bridge's own connection asks the server with its token, the listener answers with the change (decision 0035).
    A client's set with a name like the token but not it is an unknown parameter, not a publish."""
    from clients.query import ask

    d, ep = stack
    bridge = Bridge(ZenohConfig(mode="peer", connect=[ep]), ["source"], port=0, poll_s=0.1)
    client = None
    try:
        bridge.start()
        client = FoxgloveClient(bridge.port)
        client.send({"op": "subscribeParameterUpdates", "parameterNames": ["source.controller.K_per_s"]})
        assert wait_until(lambda: "source.controller.K_per_s" in bridge._subscribed_params, 5.0)
        with open_session(ZenohConfig(mode="peer", connect=[ep])) as s:
            ask(s, "energyctl", "source", "config", ["controller.K_per_s=700"], 3.0)

        def published() -> list:
            return [p.get("value") for m in client.ops if m["op"] == "parameterValues" and "id" not in m
                    for p in m["parameters"] if p["name"] == "source.controller.K_per_s"]

        assert client.pump(lambda: 700.0 in published(), 5.0), client.ops
        # (counted when the server's answer reaches the bridge's connection, after the client may have the value)
        assert wait_until(lambda: bridge.status()["param_publishes"] >= 1, 5.0) and d.core.cfg.K_per_s == 700.0
        forged = "energyctl-bridge-publish/" + "0" * 32
        assert forged != bridge._token
        assert client.set_parameter(forged, 1.0, "f1") == {}
        assert client.pump(lambda: client.op("status", level=2)) and "unknown parameter" in \
            client.op("status", level=2)["message"]
    finally:
        if client is not None:
            client.close()
        bridge.close()


def test_a_client_churning_parameter_subscriptions_cannot_wedge_the_bridge():
    """Issue 28, item 2: one client subscribes and unsubscribes, as fast as it can, to a parameter name the bridge
    does not know (so each of its subscriptions is the first: the SDK calls the listener, needing the GIL, under its
    parameter lock) while the config changes every 20 ms (the bridge rereads it every 20 ms and publishes). Before,
    the parameters' thread called publish_parameter_values holding the GIL, which waits on that lock: the bridge
    wedged (serving nobody; SIGTERM did not end it). Now another client still gets its updates and its answers, and
    SIGTERM ends the bridge."""
    import os
    import signal
    import subprocess
    import sys

    from conftest import ROOT

    from clients.live import SHUTDOWN_GRACE_S, port_open
    from clients.query import QueryError, ask

    with daemon_stack([]) as (_d, ep, _loop):
        port = free_tcp_port()
        bridge = subprocess.Popen(
            [sys.executable, "-m", "clients.cli", "foxglove", "--components", "source", "--port", str(port),
             "--poll-s", "0.02", "--mode", "peer", "--connect", ep], cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        done = threading.Event()
        churns, sets = [0], [0]
        threads = []
        watcher = None
        try:
            assert wait_until(lambda: port_open(f"tcp/127.0.0.1:{port}") or bridge.poll() is not None, 20.0)
            assert bridge.poll() is None, bridge.communicate()[1][-2000:]
            watcher = FoxgloveClient(port)
            watcher.send({"op": "subscribeParameterUpdates", "parameterNames": ["source.controller.K_per_s"]})

            def adversary():
                with ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=5.0) as ws:
                    while not done.is_set():
                        for op in ("subscribeParameterUpdates", "unsubscribeParameterUpdates"):
                            ws.send(json.dumps({"op": op, "parameterNames": ["nobody.knows.this"]}))
                        churns[0] += 1

            def setter():
                with open_session(ZenohConfig(mode="peer", connect=[ep])) as s:
                    k = 0
                    while not done.wait(0.02):
                        k += 1
                        try:
                            ask(s, "energyctl", "source", "config", [f"controller.K_per_s={800 + k % 2 * 100}"], 3.0)
                            sets[0] += 1
                        except QueryError:
                            pass

            threads = [threading.Thread(target=f, daemon=True) for f in (adversary, setter)]
            for t in threads:
                t.start()

            def updates() -> int:
                return sum(1 for m in watcher.ops if m["op"] == "parameterValues" and "id" not in m)

            # the adversary churns for 8 s, the config changes meanwhile; the watcher keeps getting the changes
            deadline = time.monotonic() + 8.0
            while time.monotonic() < deadline:
                watcher.pump(lambda: False, 0.5)
            assert churns[0] > 100 and sets[0] > 10, (churns, sets)
            seen = updates()
            assert seen > 0, f"no parameter update published (bridge exit code: {bridge.poll()})"
            assert watcher.pump(lambda: updates() > seen, 5.0), "no parameter update published after 8 s of churn"
            # a new client is still served: its getParameters answered
            fresh = FoxgloveClient(port)
            try:
                fresh.send({"op": "getParameters", "parameterNames": ["source.controller.K_per_s"], "id": "g"})
                assert fresh.pump(lambda: fresh.op("parameterValues", id="g"), 5.0), "the bridge serves nobody"
            finally:
                fresh.close()
            done.set()
            for t in threads:
                t.join(5.0)
            # a stop signal ends it (cleanly: it is not wedged)
            bridge.send_signal(signal.SIGTERM)
            try:
                _out, err = bridge.communicate(timeout=SHUTDOWN_GRACE_S + 10)
            except subprocess.TimeoutExpired:
                pytest.fail("SIGTERM did not end the bridge")
            assert bridge.returncode == 0, err[-2000:]
        finally:
            done.set()
            if watcher is not None:
                watcher.close()
            if bridge.poll() is None:
                bridge.kill()
                bridge.communicate()


def test_the_ws_protocol_client_connects_only_offering_the_sdk_subprotocol(stack):
    """Issue 28, item 9, with @foxglove/ws-protocol's own FoxgloveClient (tests/js/foxglove_client.mjs): offering its
    default subprotocol "foxglove.websocket.v1" (what apps built on it send) the SDK refuses the handshake with HTTP
    400; the same client offering "foxglove.sdk.v1" is served: the bridge's server info, and measurements decoded."""
    import shutil
    import subprocess

    from conftest import ROOT

    js = ROOT / "tests" / "js"
    if shutil.which("node") is None or not (js / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.skip("needs node and npm install --prefix tests/js (@foxglove/ws-protocol)")
    _d, ep = stack
    bridge = Bridge(ZenohConfig(mode="peer", connect=[ep]), ["source"], port=0, rate_hz=RATE_HZ)
    bridge.start()
    try:
        def run(subprotocol: str) -> dict:
            r = subprocess.run(["node", str(js / "foxglove_client.mjs"), f"ws://127.0.0.1:{bridge.port}", subprotocol,
                                "energyctl/source/meas", "5"], capture_output=True, text=True, timeout=30, cwd=js)
            assert r.returncode == 0, r.stderr[-2000:]
            return json.loads(r.stdout.strip().splitlines()[-1])

        old = run("foxglove.websocket.v1")
        assert old.get("error") == "HTTP 400", old
        new = run("foxglove.sdk.v1")
        assert "error" not in new, new
        assert new["name"] == "energyctl" and "parameters" in new["capabilities"], new
        assert new["schemaName"] == "energyctl.Measurement" and len(new["messages"]) == 5
        assert all(m == expected_meas(m["seq"]) for m in new["messages"]), new["messages"]
    finally:
        bridge.close()


def test_the_layouts_live_topics_est_z_in_and_events_are_served_from_a_logging_daemon(tmp_path):
    """The layout's estimate, tick-input and event panels were empty live: the daemon recorded them but published
    none. With log_live_hz its recorder's process puts them on PREFIX/ID/est, z_in and events (est and z_in at most
    log_live_hz a second of sample time, events all), and the bridge serves them on the log's topics, as the log's
    JSON."""
    from schemas.messages import Estimate, Event, TickInput

    with daemon_stack([], log_dir=str(tmp_path), log_live_hz=20.0) as (d, ep, _loop):
        bridge = Bridge(ZenohConfig(mode="peer", connect=[ep]), ["source"], port=0, rate_hz=0.0)
        client = None
        try:
            bridge.start()
            client = FoxgloveClient(bridge.port)
            leaves = ("est", "z_in", "events")
            assert client.pump(lambda: {f"energyctl/source/{x}" for x in leaves} <= set(client.channels))
            for leaf, model in zip(leaves, (Estimate, TickInput, Event), strict=True):
                assert json.loads(client.channels[f"energyctl/source/{leaf}"]["schema"]) == json_schema(model)
            client.send({"op": "subscribe", "subscriptions": [
                {"id": k, "channelId": client.channels[f"energyctl/source/{leaf}"]["id"]}
                for k, leaf in enumerate(leaves, 1)]})
            assert client.pump(lambda: len(client.data.get(1, [])) >= 3 and len(client.data.get(2, [])) >= 3,
                               20.0), {k: len(v) for k, v in client.data.items()}
            assert set(client.data[1][-1]) == set(json_schema(Estimate)["properties"])
            assert set(client.data[2][-1]) == set(json_schema(TickInput)["properties"])
            ts = [m["t"] for m in client.data[2]]
            assert all(b - a >= 1 / 20.0 - 1e-9 for a, b in zip(ts, ts[1:], strict=False))  # decimated, sample time
            # an event: a config change made elsewhere is recorded, and so seen live
            client.call("source/config/set", {"set": ["controller.K_per_s=900"]}, 1)
            assert client.pump(lambda: any(e.get("kind") == "config" for e in client.data.get(3, [])), 20.0), \
                client.data.get(3)
        finally:
            if client is not None:
                client.close()
            bridge.close()
