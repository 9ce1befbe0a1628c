"""energyctl foxglove --log: playback of recorded logs with Foxglove's playback controls
(clients/foxglove_playback.py), seen by a WebSocket client speaking the Foxglove protocol (foxglove.sdk.v1)."""

from __future__ import annotations

import json
import re
import signal
import struct
import subprocess
import sys
import time
from contextlib import ExitStack

import pytest

pytest.importorskip("foxglove.websocket")  # not the foxglove/ layout directory of this tree
ws_client = pytest.importorskip("websockets.sync.client")

from conftest import SCENARIOS, PumpingClient  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

from clients.cli import main  # noqa: E402
from clients.foxglove_playback import Player, open_source  # noqa: E402
from clients.live import child_env, wait_until  # noqa: E402

SUBPROTOCOLS = ["foxglove.sdk.v1"]
PLAY, PAUSE = 0, 1  # PlaybackControlRequest's command byte
PLAYING, PAUSED, BUFFERING, ENDED = 0, 1, 2, 3  # PlaybackState's status byte


@pytest.fixture(scope="module")
def log10k(tmp_path_factory):
    """0.2 s of paper-constant-load at its 10 kHz control rate: 2000 ticks, 5 channels, 10 000 messages; and its
    messages as (topic, log time, data) in log-time order, read by the mcap package."""
    out = tmp_path_factory.mktemp("playback") / "const.mcap"
    assert main(["sim", str(SCENARIOS / "paper-constant-load.toml"), "--out", str(out),
                 "--set", "timing.duration_s=0.2"]) == 0
    with open(out, "rb") as f:
        msgs = [(ch.topic, m.log_time, bytes(m.data)) for _s, ch, m in make_reader(f).iter_messages()]
    assert len(msgs) == 10_000 and msgs[1000][1] - msgs[995][1] == 100_000  # 10 kHz
    return out, msgs


class PlaybackClient(PumpingClient):
    """The parts of the Foxglove protocol a playback test needs: channels, subscriptions, message data with log
    times, playback requests and states, server time."""

    PUMP_TIMEOUT_S = 10.0

    def __init__(self, port: int):
        self._stack = ExitStack()
        # max_queue=None: the connection's reader thread never waits for this one, so a close is answered even
        # with messages still unread
        self.ws = self._stack.enter_context(ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS,
                                                              open_timeout=5.0, close_timeout=2.0, max_queue=None))
        self.info: dict | None = None
        self.channels: dict[int, dict] = {}  # channel id -> advertised channel
        self.topic_of: dict[int, str] = {}  # subscription id -> topic
        self.data: list[tuple[str, int, bytes, float]] = []  # (topic, log time, payload, arrival monotonic s)
        self.states: list[dict] = []
        self.times: list[int] = []

    def _take(self, m) -> None:
        if isinstance(m, str):
            msg = json.loads(m)
            if msg["op"] == "serverInfo":
                self.info = msg
            elif msg["op"] == "advertise":
                self.channels.update({c["id"]: c for c in msg["channels"]})
            return
        now = time.monotonic()
        if m[0] == 1:  # messageData: subscription id u32, log time u64, payload
            sub, t = struct.unpack_from("<IQ", m, 1)
            self.data.append((self.topic_of[sub], t, bytes(m[13:]), now))
        elif m[0] == 2:  # time u64
            self.times.append(struct.unpack_from("<Q", m, 1)[0])
        elif m[0] == 5:  # playbackState: status u8, current time u64, speed f32, did_seek u8, request id (u32 len)
            status, t, speed, did_seek, n = struct.unpack_from("<BQfBI", m, 1)
            rid = bytes(m[19:19 + n]).decode() or None
            self.states.append({"status": status, "time": t, "speed": speed, "did_seek": bool(did_seek),
                                "request_id": rid, "at": now})

    def subscribe_all(self) -> None:
        subs = [{"id": k + 1, "channelId": cid} for k, cid in enumerate(sorted(self.channels))]
        self.topic_of = {s["id"]: self.channels[s["channelId"]]["topic"] for s in subs}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def request(self, command: int, speed: float, seek_ns: int | None, request_id: str) -> dict:
        """A playbackControlRequest; returns the server's answer to it (the state with its request id)."""
        rid = request_id.encode()
        self.ws.send(struct.pack("<BBfBQI", 3, command, speed, seek_ns is not None, seek_ns or 0, len(rid)) + rid)
        assert self.pump(lambda: self.state(request_id) is not None, 5.0), request_id
        return self.state(request_id)

    def state(self, request_id: str | None) -> dict | None:
        return next((s for s in self.states if s["request_id"] == request_id), None)

    def close(self) -> None:
        self._stack.close()


@pytest.fixture
def served(log10k):
    """The log served by a Player on a free loopback port, a client connected and subscribed to every channel."""
    path, msgs = log10k
    player = Player([path], port=0).start()
    client = None
    try:
        client = PlaybackClient(player.port)
        assert client.pump(lambda: client.info is not None and len(client.channels) == 5, 5.0)
        client.subscribe_all()
        yield player, client, msgs
    finally:
        if client is not None:
            client.close()
        player.close()


def test_seek_to_the_middle_and_play_at_1x(served):
    """The must-show: messages arrive in log-time order, starting at the seek point, each no earlier than its
    log time after the play (1x), and all of them."""
    player, client, msgs = served
    t0, t1 = msgs[0][1], msgs[-1][1]
    info = client.info
    assert {"playbackControl", "time"} <= set(info["capabilities"])
    assert info["dataStartTime"] == {"sec": 0, "nsec": t0} and info["dataEndTime"] == {"sec": 0, "nsec": t1}
    topics = {c["topic"]: c for c in client.channels.values()}
    assert set(topics) == {m[0] for m in msgs}
    meas = topics["energyctl/paper-constant-load/meas"]
    assert (meas["encoding"], meas["schemaName"], meas["schemaEncoding"]) == \
        ("json", "energyctl.Measurement", "jsonschema")

    mid = (t0 + t1) // 2  # 99.95 ms: between two ticks
    expected = [m for m in msgs if m[1] >= mid]
    assert expected[0][1] == 100_000_000 and len(expected) == 5000
    sent = time.monotonic()
    reply = client.request(PLAY, 1.0, mid, "seek-play")
    assert reply["status"] == PLAYING and reply["did_seek"] and reply["speed"] == 1.0
    assert reply["time"] == mid
    assert client.pump(lambda: len(client.data) >= len(expected) and client.state(None) is not None, 20.0), \
        (len(client.data), client.states)

    got = client.data
    assert [(topic, t, data) for topic, t, data, _ in got] == expected  # every message from the seek point, in order
    ts = [t for _, t, _, _ in got]
    assert ts == sorted(ts) and ts[0] == 100_000_000
    # paced at 1x: none arrived before its log time after the request (less 2 ms for clock granularity)
    early = [(t, at - sent) for _, t, _, at in got if at - sent < (t - mid) / 1e9 - 2e-3]
    assert not early, early[:5]
    assert got[-1][3] - sent >= (t1 - mid) / 1e9 - 2e-3
    ended = client.state(None)
    assert ended["status"] == ENDED and ended["time"] == t1
    assert client.times and all(mid <= t <= t1 for t in client.times)
    st = player.status()
    assert st["status"] == "Ended" and st["logged"] == len(expected) and st["seeks"] == 1


def test_pause_resume_at_4x_and_play_again_from_the_start(served):
    player, client, msgs = served
    t0, t1 = msgs[0][1], msgs[-1][1]
    # play from the start at 1x; pause once a few hundred messages are in
    assert client.request(PLAY, 1.0, None, "play")["status"] == PLAYING
    assert client.pump(lambda: len(client.data) >= 300, 10.0)
    p = client.request(PAUSE, 1.0, None, "pause")
    assert p["status"] == PAUSED and not p["did_seek"]
    paused_at = p["time"]
    before = [m for m in msgs if m[1] <= paused_at]
    assert 300 <= len(before) < len(msgs)
    # the pause sent everything up to its time, and nothing after it
    assert client.pump(lambda: len(client.data) >= len(before), 10.0)
    n_paused = len(client.data)
    assert [(a, b, c) for a, b, c, _ in client.data] == before

    # resume at 4x: from the paused time on, nothing repeated or skipped, paced at 4x
    sent = time.monotonic()
    r = client.request(PLAY, 4.0, None, "resume")
    assert r["status"] == PLAYING and r["speed"] == 4.0 and r["time"] == paused_at and not r["did_seek"]
    assert client.pump(lambda: len(client.data) >= len(msgs) and client.state(None) is not None, 20.0)
    assert [(a, b, c) for a, b, c, _ in client.data] == msgs
    assert all(t > paused_at for _, t, _, _ in client.data[n_paused:])
    assert client.data[-1][3] - sent >= (t1 - r["time"]) / 4e9 - 2e-3
    assert client.state(None)["status"] == ENDED

    # play after the end starts again at the beginning; a seek while playing jumps there
    n = len(client.data)  # (the data can come before the answer)
    again = client.request(PLAY, 1.0, None, "again")
    assert again["status"] == PLAYING and again["time"] == t0
    jump = t1 - 10_000_000  # the last 10 ms
    j = client.request(PLAY, 4.0, jump, "jump")
    assert j["did_seek"] and j["time"] == jump
    after = [m for m in msgs if m[1] >= jump]
    assert client.pump(lambda: len(client.data) - n >= len(after)
                       and [(a, b, c) for a, b, c, _ in client.data[-len(after):]] == after, 20.0)
    # what came before the jump (from the start, in order), then everything from the jump point on
    tail = [(a, b, c) for a, b, c, _ in client.data[n:]]
    k = len(tail) - len(after)
    assert tail[:k] == msgs[:k]
    assert client.pump(lambda: client.states[-1]["status"] == ENDED and client.states[-1]["at"] >= j["at"], 5.0), \
        [(s["status"], s["request_id"], s["time"], round(s["at"] - j["at"], 4)) for s in client.states]
    assert player.status()["seeks"] == 1


def test_a_log_cut_off_by_a_killed_writer_plays_up_to_its_last_complete_record(log10k, tmp_path):
    path, msgs = log10k
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[:len(data) * 3 // 5])  # no summary, a partial chunk at the end
    src = open_source(cut)
    assert not src.indexed and src.start == msgs[0][1] and src.end < msgs[-1][1]
    keys = {k: k[0] for k in src.channels.values()}  # the channel key -> its topic, standing in for a channel
    got = [(topic, t, bytes(d)) for t, topic, d in src.messages(100_000_000, keys)]
    assert got and got == [m for m in msgs if 100_000_000 <= m[1] <= src.end][:len(got)]


def test_two_logs_play_as_one_timeline(log10k, tmp_path):
    path, msgs = log10k
    other = tmp_path / "b.mcap"
    other.write_bytes(path.read_bytes())
    with Player([path, other], port=0) as player:
        assert len(player.channels) == 5  # the same topics and schemas: one channel each
        st = player.control("play", 100.0, msgs[0][1])
        assert st.current_time == msgs[0][1]
        assert wait_until(lambda: player.status()["status"] == "Ended", 10.0)
        assert player.status()["logged"] == 2 * len(msgs)


def test_the_command_plays_a_log_until_sigint(log10k):
    """energyctl foxglove --log LOG --port 0: says where it serves, serves the log's channels, prints its
    counters as JSON at SIGINT."""
    path, msgs = log10k
    p = subprocess.Popen([sys.executable, "-m", "clients.cli", "foxglove", "--log", str(path), "--port", "0"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env())
    try:
        line = p.stderr.readline()  # written once the server listens
        m = re.search(r"ws://127\.0\.0\.1:(\d+)", line)
        assert m and "5 channels" in line, line + p.stderr.read()
        client = PlaybackClient(int(m.group(1)))
        try:
            assert client.pump(lambda: len(client.channels) == 5, 5.0)
            assert client.info["dataEndTime"] == {"sec": 0, "nsec": msgs[-1][1]}
        finally:
            client.close()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=10.0)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 0, err
    st = json.loads(out)
    assert st["status"] == "Paused" and st["logged"] == 0 and st["channels"] == 5 and st["end_ns"] == msgs[-1][1]
