"""The coordinator's and the rig's worker threads cannot die silently (service.daemon.failure): an exception nobody
expected fails the component, which stops publishing (allocations, samples), says why in its status, and its command
exits 1. Without Zenoh: the loops are driven by hand."""

from __future__ import annotations

import threading
from queue import Queue

from conftest import SCENARIOS, QueryStub

from clients.live import wait_until
from clients.peers.netrig import NetworkRig
from schemas.codec import GRID
from schemas.netlive import CoordinatorConfig, NetworkRigConfig
from schemas.network import load_network
from service.daemon import coordinator as coordinator_module
from service.daemon.coordinator import Coordinator

NET = SCENARIOS / "network" / "realtime.toml"


class NoTokens:
    def try_recv(self):
        return None


def coordinator() -> Coordinator:
    c = Coordinator(CoordinatorConfig(), load_network(NET))
    c.grid_q, c.alive_sub = Queue(), NoTokens()
    return c


def grid_sample(c: Coordinator, seq: int) -> bytes:
    ns, nb, nl = c.sizes
    return GRID.encode(seq, seq * c.layer.T, [c.v_nom] * ns, [1.0] * ns, [True] * ns, [c.v_nom] * nb, [100.0] * nl)


def test_an_exception_in_the_coordinators_loop_fails_it_and_no_allocation_follows(monkeypatch):
    """Before, one was counted as 'internal' and the loop went on with a layer in an unknown state."""
    c = coordinator()
    sent = []
    c.pubs = [type("Pub", (), {"put": lambda self, b: sent.append(b)})() for _ in c.names]

    def allocate(seq, P, connected):
        raise IndexError("a bug in the layer")

    monkeypatch.setattr(c.layer, "allocate", allocate)
    for k in range(3):
        c.grid_q.put((0, grid_sample(c, k)))
    c.run()  # ends by itself
    st = c.status()
    assert st["state"] == "failed" and st["failure"].startswith("loop: IndexError: a bug in the layer (at ")
    assert sent == [] and c._stop.is_set() and c.grid_q.qsize() == 2  # nothing published, nothing more taken


def test_a_trip_thread_that_fails_stops_the_coordinator(monkeypatch):
    c = coordinator()
    c.session = None

    def request(*a, **k):
        raise RuntimeError("the session broke")

    monkeypatch.setattr(coordinator_module, "request", request)
    c._trip("S1")
    assert wait_until(lambda: c._stop.is_set(), 5.0)
    assert c.status()["failure"].startswith("trip-S1: RuntimeError: the session broke")


def test_a_bad_connect_request_is_still_answered_not_a_failure():
    c = coordinator()
    q = QueryStub()
    c._connect(q, {"source": "S1", "controller": {"K_per_s": "fast"}})
    assert q.got[0] == "err" and "K_per_s" in q.got[1]["error"] and not c.failure


def test_a_breaker_thread_that_fails_ends_the_rigs_sampling_and_its_result_says_failed():
    rig = NetworkRig(NetworkRigConfig(), load_network(NET), threading.Event())

    class Query:
        payload = None

        def reply(self, *a):
            pass

        def drop(self):
            raise RuntimeError("zenoh went away mid-query")

    rig.breaker_q = type("Q", (), {"recv": lambda self: Query()})()
    from service.daemon.failure import guarded

    t = guarded(rig.failure, "breaker", rig._serve_breaker)
    t.start()
    t.join(5.0)
    assert not t.is_alive() and rig.failure
    res = rig.result()
    assert res["state"] == "failed" and res["failure"].startswith("breaker: RuntimeError: zenoh went away")


class Tokens:
    """Liveliness events, as the rig's token subscriber hands them over."""

    def __init__(self):
        self.items = []

    def put(self, name: str, up: bool) -> None:
        import zenoh

        kind = zenoh.SampleKind.PUT if up else zenoh.SampleKind.DELETE
        self.items.append(type("Tok", (), {"key_expr": f"energyctl/{name}/alive", "kind": kind})())

    def try_recv(self):
        return self.items.pop(0) if self.items else None


class Linked:
    """A session whose info says it still has a router (links) or has none."""

    def __init__(self, routers: list):
        self.info = type("Info", (), {"routers_zid": lambda _: routers, "peers_zid": lambda _: []})()


def test_the_rig_takes_every_token_gone_at_once_for_its_own_outage_not_every_source_leaving():
    """Its router restarted, the lockstep rig saw every source's token go at once and stopped waiting for them: it
    stepped thousands of samples with no commands. Now every peer's token gone (or its session without a link) is
    its own outage: those sources are unknown (None), waited for, not gone; one source going alone is that source."""
    rig = NetworkRig(NetworkRigConfig(), load_network(NET), threading.Event())
    rig.alive_sub, rig.session = Tokens(), Linked(["router"])
    rig.peers_up = {"S1", "S2", "coordinator"}
    rig.alive.update(S1=True, S2=True)
    rig.alive_sub.put("S2", False)  # S2 alone: gone
    rig._poll_alive()
    assert rig.cut_off_since is None and rig.alive["S2"] is False and rig.counters["cut_off"] == 0
    rig.alive_sub.put("S2", True)
    rig._poll_alive()
    for name in ("S1", "S2", "coordinator"):  # every token at once: its own outage
        rig.alive_sub.put(name, False)
    rig._poll_alive()
    assert rig.cut_off_since is not None and rig.counters["cut_off"] == 1
    assert rig.alive["S1"] is None and rig.alive["S2"] is None and rig._awaited == {"S1", "S2", "coordinator"}
    # a session with no router left is cut off too, whoever's token went first
    rig = NetworkRig(NetworkRigConfig(), load_network(NET), threading.Event())
    rig.alive_sub, rig.session = Tokens(), Linked([])
    rig.peers_up = {"S1", "S2", "coordinator"}
    rig.alive.update(S1=True, S2=True)
    rig.alive_sub.put("S1", False)
    rig._poll_alive()
    assert rig.cut_off_since is not None and rig.alive["S1"] is None and rig.alive["S2"] is True
