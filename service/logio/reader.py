"""The one reader of energyctl's MCAP logs: replay, ``log info`` / ``log recover``, the report and the fault
benches all read through here.

Two ways in, for two needs:

* ``Stream`` / ``scan`` / ``messages``: every record in file order, chunks expanded, without the summary, so a
  file cut short by SIGKILL yields everything up to its last complete record (``complete`` says whether the
  footer was reached, ``error`` what ended it early); each chunk is checked whole (frame, size, CRC) and a corrupt
  one is skipped and listed in ``damage`` with its byte offset, the chunks after it still read
  (docs/decisions/0040-damaged-logs.md).
* ``read_log``: a log's replay inputs as arrays. From the daemon's tick index (``ring.TickIndex``: one row of
  doubles per tick in zstd attachments, used only when it accounts for every tick) without touching the JSON
  chunks; else by the compiled scanner (``_mcapscan.c`` parses the recorder's flat JSON without a Python
  object per message); else by the general reader over ``Stream``. Every path gives the same doubles.
"""

from __future__ import annotations

import json
import struct
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

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


class CorruptLog(LogError):
    """A log with a corrupt chunk (or record): what replay cannot use, since it needs every tick in order."""

    def __init__(self, offset: int, reason: str, path: str | Path | None = None):
        self.offset, self.reason = offset, reason
        super().__init__(f"{path or 'log'}: corrupt chunk at byte {offset}: {reason}")


MAGIC = b"\x89MCAP0\r\n"
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
    gaps: list[dict] = field(default_factory=list)  # a recovered log: the corrupt chunks dropped (_gaps)

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


def _walk(buf, off: int = 0, end: int | None = None):
    """(opcode, content offset, content length) of each complete record of a record sequence from off (to end); a
    cut-off one (killed writer) ends at its last complete record."""
    n = len(buf) if end is None else end
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


def _metadata(data: bytes, want: str) -> dict[str, str] | None:
    """The string map of the top-level metadata record named want (name, then the map), or None."""
    for op, c, _ln in _top_level(data):
        if op == 0x0C:
            name, c = _string(data, c)
            if name != want:
                continue
            end = c + 4 + struct.unpack_from("<I", data, c)[0]
            c += 4
            out = {}
            while c < end:
                k, c = _string(data, c)
                out[k], c = _string(data, c)
            return out
    return None


def _core_meta(data: bytes, component: str | None = None) -> dict | None:
    """The 'core' metadata record (name, then a string map {"json": ...}); a network log's component has its own,
    'core:NAME'."""
    m = _metadata(data, "core" if component is None else f"core:{component}")
    return json.loads(m["json"]) if m and "json" in m else None


def _gaps(data: bytes) -> list[dict]:
    """What ``energyctl log recover`` dropped from the file this one was recovered from (its 'recovered' metadata:
    Damage.as_dict of each corrupt chunk), [] for any other log."""
    m = _metadata(data, "recovered")
    return json.loads(m["dropped"]) if m and m.get("dropped") else []


def _read_bytes(path: str | Path):
    """The file, memory-mapped (read-only): a reader that follows the summary touches only the pages it needs."""
    import mmap

    with open(path, "rb") as f:
        try:
            data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # an empty file cannot be mapped
            data = b""
    if len(data) == 0:
        raise LogError(f"{path}: an empty file (0 bytes): not an MCAP log")
    if data[:8] != MAGIC:
        raise LogError(f"{path}: not an MCAP file (its first bytes are {bytes(data[:8])!r}, not the MCAP magic)")
    return data


def _unchunk(content, dctx=None) -> bytes:
    """A chunk record's content (from its start time on) decompressed, after checking it whole: the header, the data
    filling the record, the zstd/lz4 frame, the uncompressed size and the CRC (when the writer stored one).
    ValueError says what failed."""
    try:
        _start, _end, size, crc, comp_len = struct.unpack_from("<QQQII", content, 0)
        if comp_len > 64:
            raise ValueError(f"compression name of {comp_len} bytes")
        comp = bytes(content[32:32 + comp_len]).decode()
        rl = struct.unpack_from("<Q", content, 32 + comp_len)[0]
    except (struct.error, UnicodeDecodeError) as e:
        raise ValueError(f"chunk header does not parse ({type(e).__name__})") from None
    raw_off = 40 + comp_len
    if raw_off + rl != len(content):
        raise ValueError(f"chunk data of {rl} bytes does not fill its record ({len(content) - raw_off})")
    if comp not in ("zstd", "lz4", ""):
        raise ValueError(f"compression {comp!r} not supported")
    raw = content[raw_off:]
    try:
        if comp == "zstd":
            if dctx is None:
                import zstandard

                dctx = zstandard.ZstdDecompressor()
            recs = dctx.decompress(raw, max_output_size=min(size, 1 << 32))
        elif comp == "lz4":
            import lz4.frame

            recs = lz4.frame.decompress(raw)
        else:
            recs = bytes(raw)
    except Exception as e:  # noqa: BLE001 - zstd/lz4 raise their own error types on a corrupt frame
        raise ValueError(f"{comp} frame does not decompress ({type(e).__name__}: {e})") from None
    if len(recs) != size:
        raise ValueError(f"decompressed to {len(recs)} bytes, the header says {size}")
    if crc and zlib.crc32(recs) != crc:
        raise ValueError(f"CRC mismatch (stored {crc:08x}, computed {zlib.crc32(recs):08x})")
    return recs


def _chunk(data: bytes, c: int, ln: int, dctx) -> bytes:
    """The records of the chunk whose content starts at c (ln bytes), decompressed and checked (_unchunk);
    CorruptLog names the chunk's offset if it is not intact."""
    try:
        return _unchunk(memoryview(data)[c:c + ln], dctx)
    except ValueError as e:
        raise CorruptLog(c - 9, str(e)) from None


def _records(path: str | Path, data: bytes):
    """Each record sequence of an MCAP file: the top level itself, then every chunk decompressed."""
    import zstandard

    yield memoryview(data)[8:]  # the top level (channels, metadata, unchunked messages)
    dctx = zstandard.ZstdDecompressor()
    for op, c, _ln in _top_level(data):
        if op == 0x06:
            yield _chunk(data, c, _ln, dctx)


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
        at, length = struct.unpack_from("<QQ", data, c + 16)  # the chunk record: its offset and length
        recs = _chunk(data, at + 9, length - 9, dctx)
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
    # corrupt chunk is raised (replay needs every tick), and so is a message that is not the expected JSON
    s = Stream(path)
    for rec in s:
        if s.damage:
            raise CorruptLog(s.damage[0].offset, s.damage[0].reason)
        if not isinstance(rec, Message):
            continue
        topic = s.channels[rec.channel_id].topic if rec.channel_id in s.channels else None
        if topic is None or not _mine(topic, component):
            continue
        leaf = topic.rsplit("/", 1)[-1]
        if leaf in LEAVES:
            code = LEAVES.index(leaf)
            try:
                d = json.loads(rec.data)
                r = [float(code), *(float(d[k]) for k in KEYS[code])]
            except (ValueError, KeyError, TypeError) as e:
                raise LogError(f"{path}: a message on {topic} in the record at byte {s.at} is not the expected JSON "
                               f"({type(e).__name__}: {e})") from None
            rows.append(r + [0.0] * (ROW - len(r)))
        elif leaf == "events":
            events.append(rec.data)
    if s.damage:
        raise CorruptLog(s.damage[0].offset, s.damage[0].reason)
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
    for op, c, ln in _top_level(data):
        if op == 0x04:  # channel: id, schema id, topic
            topics[struct.unpack_from("<H", data, c)[0]] = _string(data, c + 4)[0]
        elif op == 0x09:  # attachment: log time, create time, name, media type, data
            name, c2 = _string(data, c + 16)
            media, c2 = _string(data, c2)
            if name == TickIndex.NAME and media == TickIndex.MEDIA_TYPE:
                n = struct.unpack_from("<Q", data, c2)[0]
                blob = data[c2 + 8:c2 + 8 + n]
                crc = struct.unpack_from("<I", data, c + ln - 4)[0]  # of the record's preceding fields
                if crc and zlib.crc32(data[c:c + ln - 4]) != crc:
                    return None  # a corrupt index: the JSON channels (checked chunk by chunk) are read instead
                blobs.append(blob)
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
    try:
        ticks = np.frombuffer(b"".join(dctx.decompress(b) for b in blobs), dtype="<f8").reshape(-1, width)
    except (zstandard.ZstdError, ValueError):  # an index blob that does not decompress to whole rows
        return None
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
    try:
        got = _read_index(path, data) if use_index and component is None else None
        if got is None and _mcapscan is not None:
            try:
                got = _read_fast(path, data, component)
            except ValueError:
                pass  # not our templates (hand-made or foreign log): the general reader copes
        if got is None:
            got = _read_general(path, data, component)
        got.gaps = _gaps(data)
        return got
    except CorruptLog as e:
        raise CorruptLog(e.offset, f"{e.reason}; replay needs every tick in order: 'energyctl log info' lists the "
                                   "damage, 'energyctl log recover' rewrites the intact chunks", path) from None


_FOOTER_LEN = 9 + 20 + 8  # footer record (summary start, summary offset start, summary crc) and the closing magic


@dataclass
class Damage:
    """A stretch of a log that cannot be read: a chunk whose bytes are corrupt (zstd error, CRC mismatch, a record
    inside it that does not parse), or a top-level record that does not frame (then reading resumes at the next
    chunk the summary lists). ``messages``: how many messages it held, from the message indexes after the chunk
    (None: not known); start_s/end_s its log-time span (None when its header is unreadable too)."""

    offset: int
    length: int
    what: str
    reason: str
    messages: int | None = None
    start_s: float | None = None
    end_s: float | None = None

    def describe(self) -> str:
        span = (f", t {self.start_s:.6f}..{self.end_s:.6f} s" if self.start_s is not None and self.end_s is not None
                else "")
        lost = "" if self.messages is None else f", {self.messages} messages lost"
        return f"{self.what} at byte {self.offset} ({self.length} bytes{span}{lost}): {self.reason}"

    def as_dict(self) -> dict:
        return {"offset": self.offset, "length": self.length, "what": self.what, "reason": self.reason,
                "messages": self.messages, "start_s": self.start_s, "end_s": self.end_s}


_READERS = {0x01: Header, 0x02: Footer, 0x03: Schema, 0x04: Channel, 0x07: MessageIndex, 0x08: ChunkIndex,
            0x09: Attachment, 0x0A: AttachmentIndex, 0x0B: Statistics, 0x0C: Metadata, 0x0D: MetadataIndex,
            0x0E: SummaryOffset, 0x0F: DataEnd}
_IN_CHUNK = {0x03: Schema, 0x04: Channel}


def _parse(op: int, content) -> object:
    """One record from its content (opcode known), all of its bytes used; ValueError if it does not parse."""
    stream = ReadDataStream(BytesIO(bytes(content)))
    try:
        rec = Message.read(stream, len(content)) if op == 0x05 else _READERS[op].read(stream)
    except (McapError, struct.error, UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"record 0x{op:02x} does not parse ({type(e).__name__}: {e})") from None
    if stream.count > len(content) or (op == 0x05 and len(content) < 22):
        raise ValueError(f"record 0x{op:02x} overruns its length {len(content)}")
    if op == 0x09:  # an attachment ends in the CRC of its preceding fields (0: none stored)
        crc = struct.unpack_from("<I", content, len(content) - 4)[0]
        if crc and zlib.crc32(content[:len(content) - 4]) != crc:
            raise ValueError(f"attachment {rec.name!r}: CRC mismatch")
    return rec


def _chunk_records(content) -> list:
    """A chunk's schemas, channels and messages, after checking it whole (_unchunk) and every inner record framing
    and parsing. ValueError says what failed."""
    recs = _unchunk(content)
    out = []
    off = 0
    for op, c, ln in _walk(recs):
        off = c + ln
        if op == 0x05:  # the bulk: unpacked here rather than through a stream object per message
            if ln < 22:
                raise ValueError(f"a message record of {ln} bytes inside the chunk")
            cid, seq, t_log, t_pub = struct.unpack_from("<HIQQ", recs, c)
            out.append(Message(channel_id=cid, log_time=t_log, data=recs[c + 22:c + ln], publish_time=t_pub,
                               sequence=seq))
        elif op in _IN_CHUNK:
            out.append(_parse(op, recs[c:c + ln]))
    if off != len(recs):
        raise ValueError(f"a record inside the chunk is cut off at {off} of {len(recs)} bytes")
    return out


def _summary(data) -> tuple[int, list, list[int]] | None:
    """(summary start, its schema and channel records, the chunk offsets its chunk indexes list) of a file whose
    footer and summary are intact (summary CRC checked when stored), else None."""
    n = len(data)
    f = n - _FOOTER_LEN
    if f < 8 or bytes(data[n - 8:]) != MAGIC or data[f] != 0x02 or struct.unpack_from("<Q", data, f + 1)[0] != 20:
        return None
    start, _offsets, crc = struct.unpack_from("<QQI", data, f + 9)
    if start == 0 or not 8 <= start <= f:
        return None
    if crc and zlib.crc32(data[start:n - 12]) != crc:
        return None
    decls, chunks = [], []
    for op, c, ln in _walk(data, start, f):
        if op in _IN_CHUNK:
            try:
                decls.append(_parse(op, data[c:c + ln]))
            except ValueError:
                return None
        elif op == 0x08:
            chunks.append(struct.unpack_from("<Q", data, c + 16)[0])
    return start, decls, sorted(chunks)


class Stream:
    """The records of one MCAP file in file order, chunks expanded: what can be read is read, and what cannot is
    said, with its byte offset.

    Iterate it once (LogError at once if the file is empty or not MCAP). Afterwards ``complete`` is True if the
    footer was read; ``error`` says where the file was cut off (a killed writer's partial record), and ``damage``
    lists the corrupt chunks and records that were skipped (``Damage``): a corrupt chunk is checked whole (CRC,
    framing) and skipped, the chunks after it are still read; a top-level record that does not frame resumes at the
    next chunk the file's summary lists (the summary's schemas and channels are then declared too, so messages in
    later chunks keep their channel). ``channels`` maps channel id to Channel as they appear; ``at`` is the byte
    offset of the top-level record the last yielded one came from."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.channels: dict[int, Channel] = {}
        self.complete = False
        self.error: str | None = None
        self.damage: list[Damage] = []
        self.at = 0
        self._declared = False

    def topic(self, rec: Message) -> str:
        """The topic of a message's channel (KeyError: a channel the file never declared)."""
        return self.channels[rec.channel_id].topic

    def _resume(self, off: int, summary) -> tuple[int | None, list]:
        """After damage at off: where reading can go on (the next chunk the summary lists, else its start; None
        without a summary), and the summary's schemas and channels to declare (the first time only)."""
        if summary is None:
            return None, []
        start, decls, chunks = summary
        new = [] if self._declared else decls
        self._declared = True
        for r in new:
            if isinstance(r, Channel) and r.id not in self.channels:
                self.channels[r.id] = r
        nxt = [c for c in chunks if c > off]
        return (nxt[0] if nxt else (start if start > off else None)), new

    def __iter__(self) -> Iterator:
        data = _read_bytes(self.path)
        n = len(data)
        summary = ...  # read when first needed
        pending: Damage | None = None  # the last corrupt chunk: the message indexes after it count what it held
        off = 8
        while off < n:
            op = data[off]
            ln = struct.unpack_from("<Q", data, off + 1)[0] if off + 9 <= n else None
            frames = ln is not None and off + 9 + ln <= n and (op in (0x05, 0x06) or op in _READERS or op >= 0x80)
            if not frames:
                if summary is ...:
                    summary = _summary(data)
                nxt, decls = self._resume(off, summary)
                if nxt is None:  # no summary to resume from: the file ends here
                    self.error = (f"cut off at byte {off} of {n}: a record that does not fit in the file (a writer "
                                  "killed mid-record, or a corrupt length)")
                    return
                self.damage.append(Damage(off, nxt - off, "unreadable record",
                                          f"opcode 0x{op:02x}, length {ln}: does not frame; resumed at byte {nxt}"))
                pending = None
                off = nxt
                yield from decls
                continue
            self.at = off
            content = memoryview(data)[off + 9:off + 9 + ln]
            if op == 0x06:
                try:
                    recs = _chunk_records(content)
                except ValueError as e:
                    hdr = struct.unpack_from("<QQ", data, off + 9) if ln >= 16 else None
                    pending = Damage(off, 9 + ln, "corrupt chunk", str(e), None,
                                     *((hdr[0] / 1e9, hdr[1] / 1e9) if hdr else (None, None)))
                    self.damage.append(pending)
                    if summary is ...:
                        summary = _summary(data)
                    yield from self._resume(off, summary)[1]  # channels declared in the lost chunk
                    off += 9 + ln
                    continue
                pending = None
                for r in recs:
                    if isinstance(r, Channel):
                        self.channels[r.id] = r
                    yield r
                off += 9 + ln
                continue
            if op >= 0x80:  # a private record (the MCAP spec reserves these opcodes): not ours to read
                off += 9 + ln
                continue
            try:
                rec = _parse(op, content)
            except ValueError as e:
                self.damage.append(Damage(off, 9 + ln, "corrupt record", str(e)))
                off += 9 + ln
                continue
            off += 9 + ln
            if isinstance(rec, MessageIndex):
                if pending is not None:
                    pending.messages = (pending.messages or 0) + len(rec.records)
                continue
            pending = None
            if isinstance(rec, Channel):
                self.channels[rec.id] = rec
            elif isinstance(rec, Footer):
                self.complete = True
                yield rec
                return
            yield rec
        if not self.complete:
            self.error = f"cut off at byte {n}: no footer (a writer that did not finish)"


def messages(path: str | Path, suffix: str) -> list[dict]:
    """The JSON messages of the channels whose topic ends in ``suffix``, in file order; a file cut off by SIGKILL
    gives what was complete (one still empty or shorter than its magic, being written: none), a corrupt chunk is
    skipped, and one whose messages stop being readable gives what came before."""
    s = Stream(path)
    out = []
    try:
        for r in s:
            if isinstance(r, Message) and r.channel_id in s.channels and s.topic(r).endswith(suffix):
                out.append(json.loads(r.data))
    except LogError:  # empty or not (yet) MCAP: nothing to read
        pass
    except ValueError:  # a message that is not JSON: stop there
        pass
    return out


def scan(path: str | Path, keep_messages: bool = False) -> dict:
    """What a log holds: schemas, channels, message counts and bytes per topic, metadata, attachments, the
    recorder's drop counts, duration, whether it is complete (and the messages themselves if asked). LogError if
    the file is empty or not MCAP. A file cut off by SIGKILL is scanned up to its last complete record (``error``
    says where); a corrupt chunk or record is skipped and listed in ``damage`` (``Damage``), the rest still read;
    messages on a channel declared nowhere readable are counted in ``undeclared``; one whose records stop making
    sense (a foreign, non-JSON event topic) is scanned up to there, and ``error`` says what stopped it."""
    s = Stream(path)
    schemas: dict[int, Schema] = {}
    counts: dict[str, int] = {}
    nbytes: dict[str, int] = {}
    metadata: dict[str, dict] = {}
    kept: list[Message] = []
    attachments: list[Attachment] = []
    drops: dict = {}
    undeclared = 0
    t_first = t_last = None
    it = iter(s)
    try:
        for rec in it:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Message):
                if rec.channel_id not in s.channels:
                    undeclared += 1
                    continue
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
    except LogError:
        raise
    except Exception as e:  # noqa: BLE001 - what came before stays reported
        s.error = f"stopped at the record at byte {s.at}: {type(e).__name__}: {e}"
    return {"path": str(path), "complete": s.complete, "error": s.error, "damage": s.damage,
            "undeclared": undeclared, "schemas": schemas, "channels": s.channels,
            "counts": counts, "bytes": nbytes, "metadata": metadata, "drops": drops, "messages": kept,
            "attachments": attachments,
            "duration_s": (t_last - t_first) / 1e9 if t_first is not None else 0.0}
