"""The coordinator's log holds every LayerWindow it sends (``<prefix>/<id>/window/<source>``) and its replay
recomputes each one field for field: a log it wrote replays with its windows identical, a window value changed in
the log is caught and named, and an older log without window topics still replays (no windows, a note). Without
Zenoh: the coordinator's grid samples are handed over by hand, its recorder writes a real MCAP file."""

from __future__ import annotations

import pytest
from conftest import SCENARIOS

from schemas.codec import GRID
from schemas.netlive import CoordinatorConfig
from schemas.network import load_network
from service.daemon.coordinator import Coordinator
from service.logio.reader import messages
from service.network import layer_replay
from service.network.layer_replay import replay_coordinator

NET = SCENARIOS / "network" / "realtime.toml"


class Pub:
    def __init__(self, sent: list):
        self.sent = sent

    def put(self, b: bytes) -> None:
        self.sent.append(b)


@pytest.fixture(scope="module")
def coordinator_log(tmp_path_factory):
    """A coordinator's log of 2.5 windows of the 1 kHz network, S3's breaker closed at sample 70 and S2's opened at
    sample 110 (window messages at the first sample, at each window's end and at each breaker change)."""
    path = tmp_path_factory.mktemp("windowlog") / "coordinator.mcap"
    c = Coordinator(CoordinatorConfig(out=str(path)), load_network(NET))
    sent: list[bytes] = []
    c.pubs = [Pub(sent) for _ in c.names]
    c.recorder = c._open_recorder()
    try:
        ns, nb, nl = c.sizes
        for k in range(125):
            connected = [True, k < 110, k >= 70][:ns] + [True] * max(0, ns - 3)
            v = [c.v_nom + 0.01 * ((k * (j + 3)) % 7) for j in range(ns)]
            i_out = [1.0 + 0.1 * j + 0.001 * (k % 11) for j in range(ns)]
            c.grid(GRID.encode(k, k * c.layer.T, v, i_out, connected, [c.v_nom - 0.02 * (k % 5)] * nb,
                               [400.0 + (200.0 if k >= 40 else 0.0)] * nl))
    finally:
        c.recorder.close()
    assert c.counters["rejected"] == 0, c.last_reject
    return path, c.counters["windows_sent"], ns, len(sent)


def test_every_window_sent_is_logged_and_replays_identical(coordinator_log):
    path, windows_sent, ns, n_put = coordinator_log
    # the first sample, 2 window ends (49, 99) and 2 breaker changes (70, 110): 5 sends to each source
    assert windows_sent == 5 and n_put == 5 * ns
    rc = replay_coordinator(path)
    assert rc["windows"] == n_put and rc["n_windows_differing"] == 0 and rc["identical"] and not rc["notes"], rc
    logged = messages(path, "/window/S3")
    assert [(m["seq"], m["connected"], m["has_range"]) for m in logged] == [
        (0, False, False), (50, False, False), (70, True, True), (100, True, True), (110, True, True)]


@pytest.mark.parametrize("field, value", [("alpha", 0.5), ("Z_P_max", 1e6), ("v_ref_V", 1.0), ("window", 7),
                                          ("connected", True), ("seq", 51)])
def test_a_changed_window_value_in_the_log_is_caught_and_named(coordinator_log, monkeypatch, field, value):
    path = coordinator_log[0]
    read = layer_replay.messages

    def tampered(p, topic):
        out = read(p, topic)
        if topic.endswith("/window/S3"):
            out[1][field] = value  # the window sent at the end of window 0 (seq 50)
        return out

    monkeypatch.setattr(layer_replay, "messages", tampered)
    rc = replay_coordinator(path)
    assert not rc["identical"] and rc["n_windows_differing"] >= 1, rc
    if field == "seq":  # a seq moved leaves one replayed without a logged one and one logged without a replayed one
        assert [(d["source"], d["seq"], d["logged"] is None, d["replayed"] is None)
                for d in rc["windows_differing"]] == [("S3", 50, True, False), ("S3", 51, False, True)], rc
        return
    [d] = rc["windows_differing"]
    assert d["source"] == "S3" and d["seq"] == 50 and d["fields"] == [field] and d["logged"][field] == value, d


def test_a_log_without_window_topics_still_replays(coordinator_log, monkeypatch):
    """An older coordinator's log (before the windows were recorded): its samples replay, windows 0, a note."""
    path = coordinator_log[0]
    read = layer_replay.messages
    monkeypatch.setattr(layer_replay, "messages", lambda p, topic: [] if "/window/" in topic else read(p, topic))
    rc = replay_coordinator(path)
    assert rc["identical"] and rc["windows"] == 0 and rc["samples"] == 125, rc
    assert rc["notes"] and "no window messages" in rc["notes"][0]
