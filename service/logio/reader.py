"""The one reader of energyctl's MCAP logs: replay, ``log info`` / ``log recover``, the report and the fault
benches all read through here.

Two ways in, for two needs:

* ``Stream`` / ``scan`` / ``messages``: every record in file order, chunks expanded, without the summary, so a
  file cut short by SIGKILL yields everything up to its last complete record (``complete`` says whether the
  footer was reached, ``error`` what ended it early).
* ``read_log``: a log's replay inputs as arrays. From the daemon's tick index (``ring.TickIndex``: one row of
  doubles per tick in zstd attachments, used only when it accounts for every tick) without touching the JSON
  chunks; else by the compiled scanner (``_mcapscan.c`` parses the recorder's flat JSON without a Python
  object per message); else by the general reader over ``Stream``. Every path gives the same doubles.
"""

from __future__ import annotations

import json
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from schemas.codec import CMD, MEAS
from schemas.messages import TickInput

try:
    from service.logio import _mcapscan
except ImportError:  # not built (no C compiler): the general reader is used
    _mcapscan = None
if sys.byteorder != "little" or (_mcapscan is not None and _mcapscan.ROW != 9):
    _mcapscan = None


class LogError(RuntimeError):
    """A file that is not a readable energyctl log."""


LEAVES = ("meas", "z_in", "cmd")  # channel codes 0, 1, 2
KEYS = (MEAS.fields, tuple(TickInput.model_fields), CMD.fields)
NEEDED = (set(MEAS.fields), {"seq", "P_r_in", "P_r_in_dot", "stepped"}, {"seq", "du_dt", "du_dt_next"})  # read
ROW = 9  # a row: channel code, then up to 8 fields
SEQ_BITS = 40  # key = epoch << SEQ_BITS | seq


@dataclass
class LogData:
    """A log's replay inputs in file order: one row per message of meas / z_in / cmd (code, then its fields in
    schema order, zero-padded), the config events, the core metadata, and where the epochs ended."""

    core: dict | None = None
    rows: list[np.ndarray] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    source: str = "json"  # "index": read from the tick index
    ticks: np.ndarray | None = None  # from the index: n x 11 (TickIndex.COLUMNS), instead of rows

    def as_rows(self) -> list[np.ndarray]:
        """rows, also for a log read from its index (meas, z_in, cmd of each tick, as the scanner lays them)."""
        if self.ticks is None:
            return self.rows
        t, n = self.ticks, len(self.ticks)
        rows = np.zeros((3 * n, ROW))
        rows[0::3, 0], rows[0::3, 1:7] = 0, t[:, 0:6]
        rows[1::3, 0], rows[1::3, 1], rows[1::3, 3:6] = 1, t[:, 0], t[:, 6:9]
        rows[2::3, 0], rows[2::3, 1], rows[2::3, 3], rows[2::3, 4] = 2, t[:, 0], t[:, 9], t[:, 10]
        return [rows]


def _walk(buf, off: int = 0):
    """(opcode, content offset, content length) of each complete record of a record sequence from off; a
    cut-off one (killed writer) ends at its last complete record."""
    n = len(buf)
    while off + 9 <= n:
        op, ln = buf[off], struct.unpack_from("<Q", buf, off + 1)[0]
        if off + 9 + ln > n:
            return
        yield op, off + 9, ln
        off += 9 + ln


def _top_level(data: bytes):
    """The records of a whole file, after its magic."""
    return _walk(data, 8)


def _config_events(raw) -> list[dict]:
    """The config-change events among raw event messages (JSON)."""
    return [d for d in map(json.loads, raw) if d.get("kind") in ("config", "v_ref")]


def _string(data: bytes, off: int) -> tuple[str, int]:
    k = struct.unpack_from("<I", data, off)[0]
    return bytes(data[off + 4:off + 4 + k]).decode(), off + 4 + k


def _core_meta(data: bytes, component: str | None = None) -> dict | None:
    """The 'core' metadata record (name, then a string map {"json": ...}); a network log's component has its own,
    'core:NAME'."""
    want = "core" if component is None else f"core:{component}"
    for op, c, _ln in _top_level(data):
        if op == 0x0C:
            name, c = _string(data, c)
            if name != want:
                continue
            end = c + 4 + struct.unpack_from("<I", data, c)[0]
            c += 4
            while c < end:
                k, c = _string(data, c)
                v, c = _string(data, c)
                if k == "json":
                    return json.loads(v)
    return None


def _read_bytes(path: str | Path):
    """The file, memory-mapped (read-only): a reader that follows the summary touches only the pages it needs."""
    import mmap

    with open(path, "rb") as f:
        try:
            data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # an empty file cannot be mapped
            data = b""
    if data[:8] != b"\x89MCAP0\r\n":
        raise LogError(f"{path}: not an MCAP file")
    return data


def _chunk(data: bytes, c: int, dctx) -> bytes:
    """The records of the chunk whose content starts at c, decompressed."""
    size = struct.unpack_from("<Q", data, c + 16)[0]  # start, end, uncompressed size, crc, compression, records
    comp, c = _string(data, c + 28)
    rl = struct.unpack_from("<Q", data, c)[0]
    raw = data[c + 8:c + 8 + rl]
    if comp == "zstd":
        return dctx.decompress(raw, max_output_size=size)
    if comp == "lz4":
        import lz4.frame

        return lz4.frame.decompress(raw)
    if comp:
        raise LogError(f"chunk compression {comp!r} not supported")
    return raw


def _records(path: str | Path, data: bytes):
    """Each record sequence of an MCAP file: the top level itself, then every chunk decompressed."""
    import zstandard

    yield memoryview(data)[8:]  # the top level (channels, metadata, unchunked messages)
    dctx = zstandard.ZstdDecompressor()
    for op, c, _ln in _top_level(data):
        if op == 0x06:
            yield _chunk(data, c, dctx)


def _channel_messages(data: bytes, cids: set[int]) -> list[bytes]:
    """The data of the messages on these channels, from only the chunks that the summary's chunk indexes say
    hold any (a complete file)."""
    import zstandard

    dctx = zstandard.ZstdDecompressor()
    out: list[bytes] = []
    for op, c, _ln in _top_level(data):
        if op != 0x08:  # chunk index: start, end, chunk offset, chunk length, {channel: message index offset}, ...
            continue
        n = struct.unpack_from("<I", data, c + 32)[0]
        if not cids & {cid for cid, _off in struct.iter_unpack("<HQ", data[c + 36:c + 36 + n])}:
            continue
        recs = _chunk(data, struct.unpack_from("<Q", data, c + 16)[0] + 9, dctx)
        if _mcapscan is not None:
            out += [m for cid in sorted(cids) for m in _mcapscan.raw(recs, cid)]
            continue
        out += [bytes(recs[c2 + 22:c2 + ln]) for op2, c2, ln in _walk(recs)  # few chunks, rare messages
                if op2 == 0x05 and struct.unpack_from("<H", recs, c2)[0] in cids]
    return out


def _mine(topic: str, component: str | None) -> bool:
    """A channel of the component (a network log: .../COMPONENT/leaf), or any channel when none is named."""
    return component is None or topic.rsplit("/", 2)[-2:-1] == [component]


def component_names(path: str | Path) -> list[str]:
    """The components of a network log (its 'core:NAME' records), in file order; [] for a one-component log."""
    data = _read_bytes(path)
    out = []
    for op, c, _ln in _top_level(data):
        if op == 0x0C:
            name = _string(data, c)[0]
            if name.startswith("core:"):
                out.append(name[5:])
    return out


def _read_fast(path: str | Path, data=None, component: str | None = None) -> LogData:
    out = LogData()
    table = bytearray(b"\xff" * 65536)
    events_ids: set[int] = set()
    keys = tuple(tuple(("" if k in NEEDED[c] else "~").encode() + k.encode() for k in ks) for c, ks in enumerate(KEYS))
    data = _read_bytes(path) if data is None else data
    out.core = _core_meta(data, component)
    for recs in _records(path, data):  # the top level first, then each chunk
        for cid, topic in _mcapscan.channels(recs):
            name = topic.decode()
            if not _mine(name, component):
                continue
            leaf = name.rsplit("/", 1)[-1]
            if leaf in LEAVES:
                table[cid] = LEAVES.index(leaf)
            elif leaf == "events":
                events_ids.add(cid)
        rows = np.frombuffer(_mcapscan.scan(recs, bytes(table), keys), dtype=np.float64)
        out.rows.append(rows.reshape(-1, ROW))
        for cid in events_ids:
            out.events += _config_events(_mcapscan.raw(recs, cid))
    return out


def _read_general(path: str | Path, data=None, component: str | None = None) -> LogData:
    out = LogData(core=_core_meta(_read_bytes(path) if data is None else data, component))
    rows: list[list[float]] = []
    events: list[bytes] = []
    # records in file order, chunks expanded: works on a file without summary too; a cut-off record ends it, a
    # corrupt one is raised
    s = Stream(path, tolerate=(McapError, EOFError, struct.error))
    for rec in s:
        if not isinstance(rec, Message):
            continue
        topic = s.topic(rec)
        if not _mine(topic, component):
            continue
        leaf = topic.rsplit("/", 1)[-1]
        if leaf in LEAVES:
            code = LEAVES.index(leaf)
            d = json.loads(rec.data)
            r = [float(code), *(float(d[k]) for k in KEYS[code])]
            rows.append(r + [0.0] * (ROW - len(r)))
        elif leaf == "events":
            events.append(rec.data)
    out.events = _config_events(events)
    out.rows.append(np.array(rows, dtype=np.float64).reshape(-1, ROW))
    return out


def _read_index(path: str | Path, data: bytes) -> LogData | None:
    """A log's replay inputs from its tick index (service.logio.ring.TickIndex attachments), or None when it has
    none or the index does not account for every tick of the file (no summary: a killed writer; a dropped
    ring slot; a tick split by rotation): then the JSON channels are read instead."""
    from service.logio.tickindex import TickIndex

    topics: dict[int, str] = {}
    counts: dict[int, int] | None = None
    blobs: list[bytes] = []
    has_index = False
    for op, c, _ln in _top_level(data):
        if op == 0x04:  # channel: id, schema id, topic
            topics[struct.unpack_from("<H", data, c)[0]] = _string(data, c + 4)[0]
        elif op == 0x09:  # attachment: log time, create time, name, media type, data
            name, c2 = _string(data, c + 16)
            media, c2 = _string(data, c2)
            if name == TickIndex.NAME and media == TickIndex.MEDIA_TYPE:
                n = struct.unpack_from("<Q", data, c2)[0]
                blobs.append(data[c2 + 8:c2 + 8 + n])
        elif op == 0x0B:  # statistics: ..., channel message counts (u32 byte length, then u16 -> u64)
            end = c + 46 + struct.unpack_from("<I", data, c + 42)[0]
            counts = dict(struct.iter_unpack("<HQ", data[c + 46:end]))
        elif op == 0x0C and _string(data, c)[0] == "tick_index":
            has_index = True
    if not has_index or counts is None:
        return None
    import zstandard

    width = len(TickIndex.COLUMNS)
    dctx = zstandard.ZstdDecompressor()
    ticks = np.frombuffer(b"".join(dctx.decompress(b) for b in blobs), dtype="<f8").reshape(-1, width)
    by_leaf: dict[str, int] = {}
    for cid, t in topics.items():
        leaf = t.rsplit("/", 1)[-1]
        by_leaf[leaf] = by_leaf.get(leaf, 0) + counts.get(cid, 0)
    if not (len(ticks) == by_leaf.get("meas") == by_leaf.get("z_in") == by_leaf.get("cmd")):
        return None
    out = LogData(core=_core_meta(data), ticks=ticks)
    events = {cid for cid, t in topics.items() if t.rsplit("/", 1)[-1] == "events" and counts.get(cid)}
    if events:  # rare: the summary's chunk indexes lead to the few chunks that hold them
        out.events = _config_events(_channel_messages(data, events))
    out.source = "index"
    return out


def read_log(path: str | Path, use_index: bool = True, component: str | None = None) -> LogData:
    """A log's replay inputs: from its tick index if it has a complete one, else by the fast scanner if built
    (and the log is the recorder's flat JSON), else by the general reader. component: in a network log, the one
    source whose channels (.../COMPONENT/meas, z_in, cmd, events) and core record (core:COMPONENT) to read."""
    data = _read_bytes(path)
    got = _read_index(path, data) if use_index and component is None else None
    if got is not None:
        return got
    if _mcapscan is not None:
        try:
            return _read_fast(path, data, component)
        except ValueError:
            pass  # not our templates (hand-made or foreign log): the general reader copes
    return _read_general(path, data, component)


class Stream:
    """The records of one MCAP file in file order, chunks expanded, tolerant of a cut-off tail.

    Iterate it once; afterwards ``complete`` is True if the footer was read and ``error`` names what ended the
    file early (a killed writer's partial record). ``channels`` maps channel id to Channel as they appear."""

    def __init__(self, path: str | Path, tolerate: tuple[type[BaseException], ...] = (Exception,)):
        """tolerate: what ends the file early instead of being raised (a cut-off record raises one of McapError,
        EOFError, struct.error; a corrupt chunk others)."""
        self.path = Path(path)
        self.tolerate = tolerate
        self.channels: dict[int, Channel] = {}
        self.complete = False
        self.error: str | None = None

    def topic(self, rec: Message) -> str:
        """The topic of a message's channel (KeyError: a channel the file never declared)."""
        return self.channels[rec.channel_id].topic

    def __iter__(self) -> Iterator:
        with open(self.path, "rb") as f:
            records = StreamReader(f, skip_magic=False).records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    return
                except self.tolerate as e:  # a truncated file ends in a partial record
                    self.error = f"{type(e).__name__}: {e}"
                    return
                if isinstance(rec, Channel):
                    self.channels[rec.id] = rec
                elif isinstance(rec, Footer):
                    self.complete = True
                yield rec


def messages(path: str | Path, suffix: str) -> list[dict]:
    """The JSON messages of the channels whose topic ends in ``suffix``, in file order; a file cut off by SIGKILL
    gives what was complete, and so does one whose messages stop being readable (what came before is returned)."""
    s = Stream(path)
    out = []
    try:
        for r in s:
            if isinstance(r, Message) and s.topic(r).endswith(suffix):
                out.append(json.loads(r.data))
    except (KeyError, ValueError):  # an undeclared channel, a message that is not JSON: stop there
        pass
    return out


def scan(path: str | Path, keep_messages: bool = False) -> dict:
    """What a log holds: schemas, channels, message counts and bytes per topic, metadata, attachments, the
    recorder's drop counts, duration, whether it is complete (and the messages themselves if asked). A file cut
    off by SIGKILL, or one whose records stop making sense (a foreign event topic, an undeclared channel), is
    scanned up to there, and ``error`` says what stopped it."""
    s = Stream(path)
    schemas: dict[int, Schema] = {}
    counts: dict[str, int] = {}
    nbytes: dict[str, int] = {}
    metadata: dict[str, dict] = {}
    kept: list[Message] = []
    attachments: list[Attachment] = []
    drops: dict = {}
    t_first = t_last = None
    try:
        for rec in s:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Message):
                topic = s.topic(rec)
                counts[topic] = counts.get(topic, 0) + 1
                nbytes[topic] = nbytes.get(topic, 0) + len(rec.data)
                t_first = rec.log_time if t_first is None else min(t_first, rec.log_time)
                t_last = rec.log_time if t_last is None else max(t_last, rec.log_time)
                if topic.endswith("/events"):
                    ev = json.loads(rec.data)
                    if ev.get("kind") == "recorder_drops":
                        drops = json.loads(ev["detail"])
                if keep_messages:
                    kept.append(rec)
            elif isinstance(rec, Metadata):
                metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, Attachment):
                attachments.append(rec)
    except Exception as e:  # noqa: BLE001 - what came before stays reported
        s.error = f"{type(e).__name__}: {e}"
    return {"path": str(path), "complete": s.complete, "error": s.error, "schemas": schemas, "channels": s.channels,
            "counts": counts, "bytes": nbytes, "metadata": metadata, "drops": drops, "messages": kept,
            "attachments": attachments,
            "duration_s": (t_last - t_first) / 1e9 if t_first is not None else 0.0}
