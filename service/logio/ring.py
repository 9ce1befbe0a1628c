"""Recorder in its own process, fed through a shared-memory ring (single producer, single consumer).

The loop thread packs each message into a fixed 128-byte slot with ``struct.pack_into`` (the binary
codecs of schemas/codec.py) and advances the write index; it never blocks, and a full ring is a
counted drop. A spawned writer process polls the ring, unpacks, encodes JSON and writes the MCAP,
so neither encoding nor I/O nor the writer's GIL share the loop's process. Events (rare, variable
length) go through a multiprocessing queue.

Synchronisation is one byte per slot (a single-byte store is never torn): the producer fills a free
slot (flag 0) and then sets its flag to 1; the writer reads a full slot and then clears the flag.
x86 does not reorder stores with stores or loads with loads, so a set flag means a complete
payload. (A first version shared 64-bit read/write indices; those reads tore across processes and
showed phantom backlogs and false drops.)
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import struct
import threading
import time
from array import array
from multiprocessing import shared_memory
from pathlib import Path

from schemas.codec import VERSION, Codec
from service.logio.tickindex import TickIndex

SLOT = 128
_HDR = struct.Struct("<QQQ")  # (unused), messages taken by the writer (statistics only), flags (bytes 16, 17)
_STOP, _FAILED = 16, 17  # header bytes: asked to finish; the writer failed (tickwriter.c RING_FAILED)
_SLOT_HDR = struct.Struct("<Bd")  # topic id, log time (s); after the one-byte slot flag
_PAYLOAD = 1 + _SLOT_HDR.size


_IDX = struct.Struct("<Q")
GROUP_BASE = 128  # slot topic ids from here on name a group of topics (RingRecorder groups)


def _group_fields(codecs: list[Codec]) -> str:
    """struct format of a group's payload: each member's fields one after the other, without "<", magic, version."""
    return "".join(c.struct.format[3:] for c in codecs)
# the writer's nap when the ring is empty: long enough that its wake-ups (200/s) do not disturb the loop's core,
# short against the ring (131 072 slots = 4 s of the daemon's 32 k messages/s)
IDLE_SLEEP_S = 0.005
WRITER_STALL_S = 10.0  # at close: a writer that takes no slot for this long is left (it hangs, or died unseen)


def _finite(msg: dict) -> bool:
    """Whether every float of an event is finite (JSON text has no NaN or infinity)."""
    return all(math.isfinite(v) for v in msg.values() if isinstance(v, float))


class RingRecorder:
    """Same interface as service.logio.mcapfile.Recorder: offer(topic, t, values) and close()."""

    def __init__(self, path: str | Path, topics: dict[str, tuple[str, Codec | None]],
                 metadata: dict[str, dict[str, str]], slots: int = 1 << 17, chunk_size: int = 1 << 20,
                 rotate_bytes: int | None = None, rotate_s: float | None = None,
                 writer_cpus: list[int] | None = None, groups: list[tuple[str, ...]] = (),
                 live: tuple[str, dict[str, str], float] | None = None):
        """groups: topics offered together every time (the daemon's meas, z_in and cmd each tick): offer_group
        packs one message of each into a single slot, with one call; the writer records them as separate
        messages of their channels, in the group's order. A full ring drops the slot: one drop per topic.

        live: (a Zenoh config as JSON5, {topic: Zenoh key}, min_interval_s): the writer process also puts those
        topics' messages, as the JSON text it writes, on their keys, at most one per min_interval_s of sample time
        per topic (events: every one) - a live view of what only the log had, at no cost to the recorded process
        (RingWriter.tap)."""
        self.path = str(path)
        self.slots = slots
        self._shm = shared_memory.SharedMemory(create=True, size=_HDR.size + slots * SLOT)
        self._shm.buf[:] = bytes(self._shm.size)  # touch every page now: no RSS growth while the ring fills
        _HDR.pack_into(self._shm.buf, 0, 0, 0, 0)
        # per topic: (topic id, one struct for the slot header and the payload: flag byte excluded, magic)
        self._codecs: dict[str, tuple[int, struct.Struct, int]] = {}
        spec = []
        for k, (topic, (schema, codec)) in enumerate(topics.items()):
            spec.append((topic, schema, codec.model.__module__ + ":" + codec.model.__name__ if codec else None,
                         codec.magic if codec else 0))
            if codec is not None:
                assert _PAYLOAD + codec.size <= SLOT, topic
                # "<Bd" then the codec's own "<BB..." without its byte-order mark: the same bytes as packing the
                # header and the payload one after the other, in one call
                self._codecs[topic] = (k, struct.Struct(_SLOT_HDR.format + codec.struct.format[1:]), codec.magic)
        assert len(topics) < GROUP_BASE, "topic ids are one byte below GROUP_BASE"
        # per group: (its id in the slot: GROUP_BASE + index, its struct: slot header and every member's fields
        # with no magic and version bytes, its topics)
        ids = {topic: k for k, topic in enumerate(topics)}
        self.groups: list[tuple[int, struct.Struct, tuple[str, ...]]] = []
        group_spec = []
        for g, members in enumerate(groups):
            st = struct.Struct(_SLOT_HDR.format + _group_fields([topics[m][1] for m in members]))
            assert 1 + st.size <= SLOT, members
            self.groups.append((GROUP_BASE + g, st, tuple(members)))
            group_spec.append(tuple(ids[m] for m in members))
        self._events_topic = next((t for t, (s, c) in topics.items() if c is None), None)
        ctx = mp.get_context("spawn")
        self._events = ctx.Queue()
        self._result = ctx.Queue()
        self._ready = ctx.Event()
        self._proc = ctx.Process(target=_writer, name="energyctl-recorder", daemon=True,
                                 args=(self._shm.name, slots, self.path, spec, metadata, chunk_size,
                                       self._events, self._result, rotate_bytes, rotate_s, os.getpid(),
                                       self._ready, writer_cpus, group_spec, live))
        self._proc.start()
        self._buf = self._shm.buf
        self._wi = array("q", [0])  # the write index: shared with a TickWriter's grouped slots (ring_args)
        self.drops: dict[str, int] = {}
        self._written_final: int | None = None
        self.backlog_at_close: int | None = None  # slots the writer had yet to take when close began
        self.close_s: float | None = None  # how long close waited for the writer
        self.paths = [self.path]  # all parts, known at close
        self.error: str | None = None
        self._error_lock = threading.Lock()

    def wait_ready(self, timeout_s: float = 15.0) -> bool:
        """Block until the writer process has started and opened its file (or failed, or timed out).

        A spawned writer imports Python and our modules first: about a second of CPU on this machine, taken
        from the control loop if it starts meanwhile. Callers wait before announcing themselves alive, so
        the plant does not start sampling into a stack that is still starting up."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._ready.wait(0.05):
                return True
            if not self._proc.is_alive() or self._buf[_FAILED]:
                return False
        return False

    @property
    def written(self) -> int:
        """Messages the writer process has taken (a statistic; exact once closed)."""
        if self._written_final is not None or self._buf is None:
            return self._written_final or 0
        return _IDX.unpack_from(self._buf, 8)[0]

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    @property
    def failed(self) -> bool:
        """The writer process could not write (unwritable directory, disk full, died): logging is degraded."""
        if self._buf is None:
            return self.error is not None
        if self._buf[_FAILED] or not self._proc.is_alive():
            with self._error_lock:  # the status thread and the main thread both ask
                if self.error is None:
                    try:  # the writer raises the flag, then sends its reason down a pipe: give it a moment
                        self.error = self._result.get(timeout=1.0)["error"]
                    except Exception:  # noqa: BLE001 - no message (killed)
                        self.error = f"recorder process ended with code {self._proc.exitcode}"
            return True
        return False

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record known only at the end (e.g. a run's metrics); written before the file closes."""
        self._events.put((None, (name, data)))

    def offer(self, topic: str, t: float, values: tuple) -> None:
        if self._buf[_FAILED]:  # the writer failed: stop filling a ring nobody empties (control goes on)
            return
        ent = self._codecs.get(topic)
        if ent is None:
            if topic == self._events_topic:
                self._events.put((t, values))
            return
        wi = self._wi
        w = wi[0]
        buf = self._buf
        off = _HDR.size + (w % self.slots) * SLOT
        if buf[off]:  # the writer has not emptied this slot: the ring is full
            self.drops[topic] = self.drops.get(topic, 0) + 1
            return
        ent[1].pack_into(buf, off + 1, ent[0], t, ent[2], VERSION, *values)
        buf[off] = 1  # publish: the payload is complete
        wi[0] = w + 1

    def offer_group(self, g: int, t: float, *values) -> None:
        """One message of each topic of group g (the index into ``groups``) at log time t: their values one after
        the other, in the group's order."""
        if self._buf[_FAILED]:
            return
        gid, st, members = self.groups[g]
        wi = self._wi
        w = wi[0]
        buf = self._buf
        off = _HDR.size + (w % self.slots) * SLOT
        if buf[off]:
            self.dropped_group(g)
            return
        st.pack_into(buf, off + 1, gid, t, *values)
        buf[off] = 1
        wi[0] = w + 1

    def dropped_group(self, g: int) -> None:
        """Count a group's slot the full ring did not take: one drop per topic."""
        for topic in self.groups[g][2]:
            self.drops[topic] = self.drops.get(topic, 0) + 1

    def ring_args(self, g: int) -> dict:
        """What a service._kernel.TickWriter needs to write group g's slots itself (same ring, same write index);
        close it before this recorder."""
        gid, st, _members = self.groups[g]
        return {"ring": self._buf, "ring_index": self._wi, "slots": self.slots, "group_id": gid,
                "group_format": st.format}

    def close(self) -> None:
        if self.drops and self._events_topic:
            self._events.put((0.0, (0.0, 0, "recorder_drops", json.dumps(self.drops))))
        self._buf[_STOP] = 1  # stop
        from service.priority import extend_stop_grace, hurry

        t0 = time.monotonic()
        self.backlog_at_close = bytes(self._buf[_HDR.size::SLOT]).count(1)  # slots the writer has yet to take
        if self._proc.pid is not None:
            hurry(self._proc.pid)  # the rest of the ring is all that is left to do: at the recorded process's priority
        # the writer takes the rest of the ring (up to its 4 s of messages at 10 kHz; seconds on a machine busy with
        # other work): as long as it makes progress the process's stop is not hung (its grace moves on), and the log
        # is whole; a writer that takes nothing for WRITER_STALL_S is left
        taken, since = _IDX.unpack_from(self._buf, 8)[0], t0
        while self._proc.is_alive() and time.monotonic() - since < WRITER_STALL_S:
            self._proc.join(timeout=0.2)
            now = _IDX.unpack_from(self._buf, 8)[0]
            if now != taken:
                taken, since = now, time.monotonic()
                extend_stop_grace()
        self.close_s = time.monotonic() - t0
        try:
            res = self._result.get(timeout=1)
            self._written_final, self.error = res["written"], res["error"] or self.error
            self.paths = res["paths"]
        except Exception:  # noqa: BLE001 - the writer died, or its message was already taken by `failed`
            self.error = self.error or f"recorder process ended with code {self._proc.exitcode}"
            if self._written_final is None:
                self._written_final = 0
        self._buf = None
        self._shm.close()
        self._shm.unlink()


class RingWriter:
    """The writer process's side of the ring: decodes each slot and writes the MCAP (JSON text per message, the
    tick index, events and metadata from the side queue), rotating to a new part by size or time.

    spec: (topic, schema name, "module:Model" or None for the event topic, magic) per topic id; groups: the
    member topic ids of each group slot (GROUP_BASE + g)."""

    def __init__(self, path: str, spec, metadata: dict, chunk_size: int, events, rotate_bytes=None, rotate_s=None,
                 groups: list[tuple[int, ...]] = (), live: tuple[str, dict[str, str], float] | None = None):
        import importlib

        from schemas.messages import Event

        self.path, self.spec, self.meta, self.chunk_size = path, spec, metadata, chunk_size
        self.events, self.rotate_bytes, self.rotate_s = events, rotate_bytes, rotate_s
        self.topics, self.codecs, self.fields, self.templates, self.bools = [], [], [], [], []
        self.ev_topic = None
        for topic, _schema, model_ref, magic in spec:
            self.topics.append(topic)
            if model_ref is None:
                self.codecs.append(None)
                self.fields.append(None)
                self.templates.append(None)
                self.bools.append(())
                self.ev_topic = topic
                continue
            mod, name = model_ref.split(":")
            codec = Codec(getattr(importlib.import_module(mod), name), magic)
            self.codecs.append(codec)
            self.fields.append(codec.fields)
            self.templates.append(codec.json_template())
            self.bools.append(codec.bool_positions)
        self.ev_fields = tuple(Event.model_fields)
        # per group: its payload struct (members' fields, no magic or version) and (topic id, first, end) per member
        self.group_structs, self.group_parts = [], []
        for members in groups:
            self.group_structs.append(struct.Struct("<" + _group_fields([self.codecs[m] for m in members])))
            parts, a = [], 0
            for m in members:
                n = len(self.codecs[m].fields)
                parts.append((m, a, a + n))
                a += n
            self.group_parts.append(parts)
        self.paths = [path]
        self.index = TickIndex.for_topics(self.topics, [m for *_, m in spec])
        self.index_kinds = self.index.kinds if self.index is not None else ()
        self.part_bytes, self.part_t0 = 0, None
        self.f = None
        self.written = 0  # messages written (poll keeps it)
        self.live = live
        self.taps: dict[int, list] = {}  # topic id -> [publisher, sample time of its last put (s)] (open_live)
        self._session = None

    def open_part(self, p: str, part: int):
        from service.logio.mcapfile import McapFile

        mf = McapFile(p, chunk_size=self.chunk_size)
        for md_name, data in self.meta.items():
            mf.metadata(md_name, data)
        mf.metadata("part", {"index": str(part), "first": str(self.path)})
        if self.index is not None:
            mf.metadata("tick_index", self.index.metadata())
        for topic, schema, _ref, _magic in self.spec:
            mf.channel(topic, schema)
        return mf

    def open(self) -> None:
        """The first part (raises what the file system says: unwritable directory, disk full)."""
        self.f = self.open_part(self.path, 0)

    def open_live(self) -> None:
        """The live tap's session and publishers (``live``): dropped under congestion, at background priority, so
        a reader that stops holds up nobody; a tap that cannot open leaves the log as it is."""
        if self.live is None:
            return
        import zenoh

        cfg, keys, self.live_every_s = self.live
        try:
            self._session = zenoh.open(zenoh.Config.from_json5(cfg))
            for k, topic in enumerate(self.topics):
                if topic in keys:
                    pub = self._session.declare_publisher(keys[topic], congestion_control=zenoh.CongestionControl.DROP,
                                                          priority=zenoh.Priority.BACKGROUND)
                    self.taps[k] = [pub, -1e300]
        except Exception:  # noqa: BLE001 - no live view; the log is what matters here
            self.taps = {}

    def tap(self, k: int, t: float, text) -> None:
        """A message of topic k (JSON text) on its live key, if its last was min_interval_s of sample time ago (or
        t went back: a restart); events (k the event topic) every one."""
        tp = self.taps[k]
        if self.topics[k] != self.ev_topic and 0 <= t - tp[1] < self.live_every_s:
            return
        tp[1] = t
        try:
            tp[0].put(text)
        except Exception:  # noqa: BLE001 - the session closed under it: no more live view
            self.taps.pop(k, None)

    def maybe_rotate(self, t: float) -> None:
        if self.part_t0 is None:
            self.part_t0 = t
        if (self.rotate_bytes and self.part_bytes >= self.rotate_bytes) or (
                self.rotate_s and t - self.part_t0 >= self.rotate_s):
            if self.index is not None:
                self.index.flush(self.f)
            self.f.close()
            stem = self.path[:-5] if self.path.endswith(".mcap") else self.path
            nxt = f"{stem}-{len(self.paths)}.mcap"
            self.paths.append(nxt)
            self.f = self.open_part(nxt, len(self.paths) - 1)
            self.part_bytes, self.part_t0 = 0, t

    def side(self, t, vals) -> int:
        """One item of the side queue: an event message, or (t None) a metadata record."""
        if t is None:
            self.f.metadata(*vals)
            return 0
        if self.ev_topic:
            msg = dict(zip(self.ev_fields, vals, strict=True))
            self.f.add(self.ev_topic, t, msg)
            if self.taps and (k := self.topics.index(self.ev_topic)) in self.taps and _finite(msg):
                self.tap(k, t, json.dumps(msg, default=str))
            return 1
        return 0

    def drain(self, timeout_s: float | None = None) -> int:
        """Every item the side queue holds now (timeout_s: and any that arrives within it of the last)."""
        from queue import Empty

        n, events = 0, self.events
        try:
            while True:
                n += self.side(*(events.get_nowait() if timeout_s is None else events.get(timeout=timeout_s)))
        except Empty:
            pass
        return n

    def record(self, k: int, t: float, vals: tuple) -> None:
        """One message of topic k: into the tick index, and as JSON text into the file."""
        if k in self.index_kinds and self.index.take(k, vals):
            self.index.flush(self.f)
        raw = vals
        bools = self.bools[k]
        if bools:
            vals = tuple(("true" if v else "false") if j in bools else v for j, v in enumerate(vals))
        text = self.templates[k] % vals
        if self.rotate_bytes or self.rotate_s:
            self.maybe_rotate(t)
            self.part_bytes += len(text)
        if "nan" in text or "inf" in text:  # non-finite floats are not JSON text (no field name has these)
            self.f.add(self.topics[k], t, dict(zip(self.fields[k], raw, strict=True)))
        else:
            self.f.add_raw(self.topics[k], t, text.encode())
            if k in self.taps:
                self.tap(k, t, text)

    def poll(self, buf, slots: int, parent: int) -> int:
        """Take the ring's slots in order until stopped (or the recorded process is gone); returns the messages
        written. Raises what writing raised."""
        codecs, group_structs, group_parts, record = self.codecs, self.group_structs, self.group_parts, self.record
        written, r = 0, 0
        try:
            while True:
                off = _HDR.size + (r % slots) * SLOT
                if buf[off]:  # a full slot
                    k, t = _SLOT_HDR.unpack_from(buf, off + 1)
                    if k >= GROUP_BASE:
                        g = k - GROUP_BASE
                        vals = group_structs[g].unpack_from(buf, off + _PAYLOAD)
                        buf[off] = 0  # free it
                        for m, a, b in group_parts[g]:
                            record(m, t, vals[a:b])
                            written += 1
                    else:
                        vals = codecs[k].struct.unpack_from(buf, off + _PAYLOAD)[2:]
                        buf[off] = 0
                        record(k, t, vals)
                        written += 1
                    r += 1
                    if r & 0xFF == 0:
                        _IDX.pack_into(buf, 8, written)
                        if r & 0xFFF == 0:  # a ring that never empties must not starve the event queue
                            written += self.drain()
                    continue
                written += self.drain()
                _IDX.pack_into(buf, 8, written)
                if buf[_STOP] or os.getppid() != parent:  # stopped, or the recorded process died: finish
                    if not buf[_HDR.size + (r % slots) * SLOT]:
                        if buf[_STOP]:  # items put just before the stop may still be in the queue's pipe
                            written += self.drain(0.1)
                        return written
                    continue
                time.sleep(IDLE_SLEEP_S)
        finally:
            self.written = written

    def close(self) -> None:
        if self.index is not None:
            self.index.flush(self.f)
        self.f.close()
        self.close_live()

    def close_live(self) -> None:
        s, self._session, self.taps = self._session, None, {}
        if s is not None:
            try:
                s.close()
            except Exception:  # noqa: BLE001 - a peer gone: nothing left to tell
                pass


def _writer(shm_name, slots, path, spec, metadata, chunk_size, events, result, rotate_bytes=None,
            rotate_s=None, parent: int | None = None, ready=None, cpus: list[int] | None = None,
            groups: list[tuple[int, ...]] = (), live=None) -> None:
    """The writer process's entry: below the recorded process in priority, off its CPU, its own output closed;
    a RingWriter drains the ring; ``result`` gets {"written", "error", "paths"} at the end."""
    from service.priority import RECORDER_NICE, background

    background(RECORDER_NICE)  # below the process it records: that one has a loop to keep
    if cpus:  # off the loop's CPU (RingRecorder's writer_cpus; the daemon's config checked they exist)
        try:
            os.sched_setaffinity(0, set(cpus))
        except (OSError, ValueError):  # gone since (CPU hot-unplug): record anyway, anywhere
            pass

    # do not hold the recorded process's stdout/stderr: whoever reads those pipes must see them close when
    # that process ends (errors go back through ``result``)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    os.close(devnull)

    shm = shared_memory.SharedMemory(name=shm_name)
    buf = shm.buf
    w = RingWriter(path, spec, metadata, chunk_size, events, rotate_bytes, rotate_s, groups, live)
    try:
        w.open()
    except Exception as e:  # noqa: BLE001 - unwritable directory, disk full: tell the parent, end
        buf[_FAILED] = 1
        result.put({"written": 0, "error": f"cannot write {path}: {type(e).__name__}: {e}", "paths": []})
        buf = None
        shm.close()
        return
    if ready is not None:
        ready.set()
    w.open_live()  # after ready: a slow Zenoh open does not count against the recorder's start
    # the recorded process, named by itself: reading getppid() here would be too late if it died while this
    # process was still importing (then the orphan never noticed, and idled forever)
    parent = parent or os.getppid()
    error = None
    try:
        w.poll(buf, slots, parent)
    except Exception as e:  # noqa: BLE001 - report, keep what was written
        error = f"{type(e).__name__}: {e}"
        buf[_FAILED] = 1
    finally:
        try:
            if error is None:
                w.close()
            else:
                w.f.close()
                w.close_live()
        except Exception as e:  # noqa: BLE001
            error = error or f"{type(e).__name__}: {e}"
        buf = None
        shm.close()
        result.put({"written": w.written, "error": error, "paths": w.paths})
