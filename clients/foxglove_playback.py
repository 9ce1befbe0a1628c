"""Playback of recorded logs to Foxglove (energyctl foxglove --log): the messages of one or more MCAP logs, on
channels with each log's own topics and schemas, paced by their log times, with the Foxglove app's playback
controls (play, pause, seek, speed). The WebSocket server and the playback protocol are the foxglove-sdk package's
(``start_server(playback_time_range=...)``, ``Capability.PlaybackControl``, ``ServerListener.
on_playback_control_request``, ``broadcast_playback_state``, ``broadcast_time``); nothing of the protocol is
written here.

What is played: every message of every log, merged in log-time order (several logs: one timeline, so logs of
one run written by several processes play side by side; logs of unrelated runs are as far apart as their log
times). A complete log is read through its summary's chunk indexes (``mcap.reader``): a seek reads only the chunks
from the seek point on. A log without a summary (its writer was killed; ``energyctl log recover`` rebuilds one) is
read by energyctl's tolerant reader (``service.logio.reader.Stream``) up to its last complete record, in file
order, from its start at each seek.

How it is paced: while playing, the playback time runs at ``speed`` times the wall clock from where it was last
set (a play, a seek, a speed change); each message is logged, with its log time, once the playback time has
reached it. When the messages that are due outnumber ``BATCH`` (the server cannot keep up with the speed), the
playback time is held at the last one logged, so the clock never runs ahead of the data. A pause first logs what
is due, so every message up to the paused time has been sent and none after it. At the end of the data the status
becomes Ended; play from there starts again at the beginning.

One playback per server: every connected client sees (and controls) the same one.
"""

from __future__ import annotations

import heapq
import math
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from clients.foxglove_bridge import Served

BATCH = 5000  # messages logged at most per pass of the lock (then a control request can get in)
TIME_EVERY_NS = 50_000_000  # the server time goes out at most this often while playing
# The SDK sends a request's answer (the PlaybackState its callback returns) after the callback, from its own task
# once that has the GIL again; an Ended state broadcast by the player thread meanwhile (the rest of the data was
# short) would overtake it, and the app would believe the playback still runs. So Ended goes out no sooner than
# this after the last answer.
REPLY_GUARD_NS = 100_000_000
DEFAULT_BACKLOG = 65536  # messages buffered per client (the SDK's default, 1024, is 0.02 s of a 10 kHz log)


class PlaybackError(RuntimeError):
    """A log that cannot be played (unreadable, no messages)."""


@dataclass
class Source:
    """One log: its channels (log channel id -> key of the Foxglove channel), time range, whether its summary
    can be used for seeking."""

    path: Path
    indexed: bool
    start: int
    end: int
    channels: dict[int, tuple] = field(default_factory=dict)
    file: object = None  # the open file of an indexed log

    def messages(self, start: int, keys: dict[tuple, object]):
        """(log time, Foxglove channel, data) of the messages from log time ``start`` on, in log-time order (a log
        without summary: in file order)."""
        if self.indexed:
            from mcap.reader import make_reader

            self.file.seek(0)  # the reader starts at the magic
            for _schema, ch, msg in make_reader(self.file).iter_messages(starting_at=start, log_time_order=True):
                yield msg.log_time, keys[self.channels[ch.id]], msg.data
            return
        from mcap.records import Message

        from service.logio.reader import Stream

        for rec in Stream(self.path):
            if isinstance(rec, Message) and rec.log_time >= start and rec.channel_id in self.channels:
                yield rec.log_time, keys[self.channels[rec.channel_id]], rec.data


def _channel_key(ch, schema) -> tuple:
    """What makes two logs' channels one Foxglove channel: the same topic, encoding and schema."""
    if schema is None:
        return ch.topic, ch.message_encoding, None, None, None
    return ch.topic, ch.message_encoding, schema.name, schema.encoding, bytes(schema.data)


def open_source(path: str | Path) -> Source:
    """A log's channels and time range: from its summary, or (none: a killed writer) by reading it through."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.records import Channel, Message, Schema

    from service.logio.reader import Stream

    p = Path(path)
    try:
        f = open(p, "rb")  # noqa: SIM115 - kept open for seeking; Player.close closes it
    except OSError as e:
        raise PlaybackError(f"{p}: {e.strerror}") from None
    try:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise PlaybackError(f"{p}: not an MCAP file")
        f.seek(0)
        try:
            summary = make_reader(f).get_summary()
        except (McapError, EOFError, ValueError, OSError):
            summary = None
        stats = summary.statistics if summary is not None else None
        if summary is not None and summary.chunk_indexes and stats is not None and stats.message_count:
            src = Source(p, True, stats.message_start_time, stats.message_end_time, file=f)
            src.channels = {cid: _channel_key(ch, summary.schemas.get(ch.schema_id))
                            for cid, ch in summary.channels.items()}
            return src
        f.close()
        schemas: dict[int, Schema] = {}
        chans: dict[int, Channel] = {}
        t0 = t1 = None
        for rec in Stream(p):  # a cut-off tail ends it; what came before plays
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                chans[rec.id] = rec
            elif isinstance(rec, Message):
                t0 = rec.log_time if t0 is None else min(t0, rec.log_time)
                t1 = rec.log_time if t1 is None else max(t1, rec.log_time)
        if t0 is None:
            raise PlaybackError(f"{p}: no messages")
        src = Source(p, False, t0, t1)
        src.channels = {cid: _channel_key(ch, schemas.get(ch.schema_id)) for cid, ch in chans.items()}
        return src
    except BaseException:
        f.close()
        raise


class Player(Served):
    """Serves ``paths`` (MCAP logs) to Foxglove with playback controls on ``host:port`` (port 0: a free one, see
    ``port``). ``start()`` reads the logs' summaries, advertises their channels and starts the server, paused at
    the start of the data; ``close()`` stops it. ``control()`` is what a client's playback request does.
    ``backlog``: messages the SDK buffers per client before it drops the oldest."""

    def __init__(self, paths: list[str | Path], port: int = 8765, host: str = "127.0.0.1",
                 backlog: int = DEFAULT_BACKLOG):
        self.paths = [Path(p) for p in paths]
        self.host, self._port, self.backlog = host, port, backlog
        self.sources: list[Source] = []
        self.channels: dict[tuple, object] = {}  # channel key -> foxglove.Channel
        self.server = None
        self.start_ns = self.end_ns = 0
        self._cond = threading.Condition()
        self._closing = False
        self._thread: threading.Thread | None = None
        # playback state (under _cond)
        self._status = None  # PlaybackStatus
        self._speed = 1.0
        self._position = 0  # the playback time when not playing; where the clock was anchored when playing
        self._anchor_wall = 0
        self._messages = None  # the merged iterator of what is still to be logged
        self._inputs: list = []  # the logs' own iterators it merges
        self._answered_ns = 0  # when control() last returned a state
        self._end_pending = False  # Ended, not yet broadcast (REPLY_GUARD_NS)
        self._next = None  # its head: (log time, channel, data), or None at the end
        self.counts = {"logged": 0, "requests": 0, "seeks": 0, "ended": 0}

    # ------------------------------------------------------------------------------------------------ life cycle

    def start(self) -> Player:
        from foxglove.websocket import Capability, PlaybackStatus

        import foxglove

        try:
            self.sources = [open_source(p) for p in self.paths]
            self.start_ns = min(s.start for s in self.sources)
            self.end_ns = max(s.end for s in self.sources)
            self.context = foxglove.Context()
            for src in self.sources:
                for k in src.channels.values():
                    if k not in self.channels:
                        topic, enc, sname, senc, sdata = k
                        schema = foxglove.Schema(name=sname, encoding=senc, data=sdata) if sname is not None else None
                        self.channels[k] = foxglove.Channel(topic, schema=schema, message_encoding=enc,
                                                            context=self.context)
            with self._cond:
                self._status = PlaybackStatus.Paused
                self._seek(self.start_ns)
            name = self.paths[0].name if len(self.paths) == 1 else f"{len(self.paths)} logs"
            self.server = foxglove.start_server(
                name=f"energyctl: {name}", host=self.host, port=self._port, context=self.context,
                capabilities=[Capability.PlaybackControl, Capability.Time], server_listener=_listener(self),
                playback_time_range=(self.start_ns, self.end_ns), message_backlog_size=self.backlog)
            self._thread = threading.Thread(target=self._run, name="foxglove-playback", daemon=True)
            self._thread.start()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        if self.server is not None:
            self.server.stop()
            self.server = None
        for ch in self.channels.values():
            ch.close()
        with self._cond:
            self._close_messages()
        for s in self.sources:
            if s.file is not None:
                s.file.close()
                s.file = None

    def __enter__(self) -> Player:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def status(self) -> dict:
        with self._cond:
            return {"port": self.port, "logs": [str(p) for p in self.paths], "channels": len(self.channels),
                    "start_ns": self.start_ns, "end_ns": self.end_ns, "status": self._status.name,
                    "time_ns": self._clock(time.monotonic_ns()), "speed": self._speed, **self.counts}

    # ------------------------------------------------------------------------------------------------ playback

    def _clock(self, now_ns: int) -> int:
        """The playback time now (under _cond)."""
        from foxglove.websocket import PlaybackStatus

        if self._status != PlaybackStatus.Playing:
            return self._position
        return min(self.end_ns, self._position + int((now_ns - self._anchor_wall) * self._speed))

    def _seek(self, t: int) -> None:
        """The messages from log time t on are next (under _cond)."""
        self._close_messages()
        self._inputs = [s.messages(t, self.channels) for s in self.sources]
        its = self._inputs
        self._messages = heapq.merge(*its, key=lambda m: m[0]) if len(its) > 1 else its[0]
        self._next = next(self._messages, None)
        self._position = t

    def _close_messages(self) -> None:
        for it in (self._messages, *self._inputs):
            if it is not None:
                it.close()
        self._messages, self._inputs = None, []

    def _deliver(self, target: int) -> int:
        """Logs the messages up to log time ``target``, at most about BATCH of them (under _cond). Returns the time
        up to which everything has been logged: target, or the last log time logged when the batch filled up
        (the messages sharing it included)."""
        n = 0
        nxt, it = self._next, self._messages
        while nxt is not None and nxt[0] <= target:
            t, ch, data = nxt
            ch.log(data, log_time=t)
            n += 1
            nxt = next(it, None)
            if n >= BATCH and (nxt is None or nxt[0] != t):
                target = t
                break
        self._next = nxt
        self.counts["logged"] += n
        return target

    def _state(self, now_ns: int, did_seek: bool = False, request_id: str | None = None):
        """The PlaybackState at now_ns (under _cond)."""
        from foxglove.websocket import PlaybackState

        return PlaybackState(status=self._status, current_time=self._clock(now_ns),
                             playback_speed=self._speed, did_seek=did_seek, request_id=request_id)

    def control(self, command: str | None, speed: float | None = None, seek_ns: int | None = None,
                request_id: str | None = None):
        """A playback request: ``command`` "play", "pause" or None (keep), ``speed`` (a factor of real time; None,
        0 or less: keep), ``seek_ns`` (a log time: play from there; clamped to the data's range). Returns the
        PlaybackState to answer with."""
        from foxglove.websocket import PlaybackStatus

        with self._cond:
            self.counts["requests"] += 1
            now = time.monotonic_ns()
            if self._status == PlaybackStatus.Playing:
                # freeze the clock here; unless jumping elsewhere, first send what it has reached
                self._position = self._clock(now) if seek_ns is not None else self._deliver(self._clock(now))
            if seek_ns is not None:
                self.counts["seeks"] += 1
                self._seek(min(max(int(seek_ns), self.start_ns), self.end_ns))
                if self._status == PlaybackStatus.Ended:
                    self._status = PlaybackStatus.Paused
            if speed is not None and math.isfinite(speed) and speed > 0:
                self._speed = float(speed)
            if command == "play":
                if self._status == PlaybackStatus.Ended and seek_ns is None:
                    self._seek(self.start_ns)  # play at the end: from the beginning
                self._status = PlaybackStatus.Playing
            elif command == "pause" and self._status == PlaybackStatus.Playing:
                self._status = PlaybackStatus.Paused
            self._anchor_wall = now
            self._end_pending = False  # this answer says where the playback is
            self._answered_ns = time.monotonic_ns()
            self._cond.notify_all()
            return self._state(now, did_seek=seek_ns is not None, request_id=request_id)

    def _run(self) -> None:
        """The player thread: logs each message when the playback time reaches it; waits (on _cond, so a request
        or close wakes it) until the next one is due."""
        from foxglove.websocket import PlaybackStatus

        last_time = 0
        while True:
            ended = None
            with self._cond:
                if self._closing:
                    return
                now = time.monotonic_ns()
                if self._end_pending:
                    hold = self._answered_ns + REPLY_GUARD_NS - now
                    if hold > 0:  # an answer just given goes first (or a request supersedes this)
                        self._cond.wait(hold / 1e9)
                        continue
                    self._end_pending = False
                    ended = self._state(now)
                elif self._status != PlaybackStatus.Playing:
                    self._cond.wait()
                    continue
                elif self._next is None:  # all logged
                    self._status, self._position = PlaybackStatus.Ended, self.end_ns
                    self.counts["ended"] += 1
                    self._end_pending = True
                    continue
                else:
                    due = self._anchor_wall + math.ceil((self._next[0] - self._position) / self._speed)
                    if due > now:
                        self._cond.wait((due - now) / 1e9)  # pacing: the next message's time, or a request
                        continue
                    clock = self._clock(now)
                    reached = self._deliver(clock)
                    if reached < clock:  # behind: hold the clock at what was sent
                        self._position, self._anchor_wall = reached, now
                    t_now = reached
            server = self.server
            if server is None:
                continue
            try:
                if ended is not None:
                    server.broadcast_time(self.end_ns)
                    server.broadcast_playback_state(ended)
                elif now - last_time >= TIME_EVERY_NS:
                    server.broadcast_time(t_now)
                    last_time = now
            except Exception as e:  # noqa: BLE001 - the server stopping under us: close() follows
                print(f"energyctl foxglove: {e}", file=sys.stderr, flush=True)


def _listener(player: Player):
    """A foxglove.websocket.ServerListener for the playback requests (called on the asking client's connection
    task; a request waits at most for one batch of logging)."""
    from foxglove.websocket import PlaybackCommand, ServerListener

    class Listener(ServerListener):
        def on_playback_control_request(self, playback_control_request):
            r = playback_control_request
            command = "play" if r.playback_command == PlaybackCommand.Play else \
                "pause" if r.playback_command == PlaybackCommand.Pause else None  # (the enum is not hashable)
            try:
                return player.control(command, r.playback_speed, r.seek_time, r.request_id)
            except Exception as e:  # noqa: BLE001 - a raising callback leaves the request unanswered
                print(f"energyctl foxglove: playback request {r.request_id}: {type(e).__name__}: {e}",
                      file=sys.stderr, flush=True)
                return player.control(None, request_id=r.request_id)

    return Listener()
