"""energyctl replay: feed a log's recorded inputs through the same core, sample by sample, no clock.

A log (from the daemon or from ``energyctl sim --out``) holds, per tick, the measurement (``.../meas``),
what else the core was given (``.../z_in``: P^{r,in}, dP^{r,in}/dt, whether it stepped) and what it
answered (``.../cmd``), plus config changes (``.../events``, kind "config", applied before the seq
they name) and a ``core`` metadata record (controller config, model, period, delay). Replay rebuilds
the core from that record and compares every du/dt with ``==``: bit for bit.

A plant restart (a measurement with seq 0 after higher seqs, the daemon's own rule) begins a new epoch;
ticks are keyed by (epoch, seq) and the core is re-initialised at each new epoch, as the daemon did.
Epochs come from the measurement stream, which the recorder writes in tick order; events travel on a
side queue and are written when the ring is idle, so their place in the file is not their place in time.

Speed: a daemon log's tick index (service.logio.ring.TickIndex: one row of doubles per tick in zstd attachments,
used only when it accounts for every tick) is read without touching the JSON chunks; otherwise the log is
read into arrays (clients/_mcapscan.c parses the recorder's flat JSON without a Python object per message;
without it, mcap + json do the same, slower). The core steps each stretch between config changes and
restarts in one call (the compiled core's loop runs in C). Every fast path gives the same doubles as the
general one; the comparison with the logged commands is still ``==``.
"""

from __future__ import annotations

import json
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from schemas.codec import CMD, MEAS
from schemas.messages import TickInput
from schemas.scenario import ControllerConfig, apply_overrides, scenario_from_dict
from service.core import make_core

try:
    from service.logio import _mcapscan
except ImportError:  # not built (no C compiler): the general reader is used
    _mcapscan = None
if sys.byteorder != "little" or (_mcapscan is not None and _mcapscan.ROW != 9):
    _mcapscan = None


class ReplayError(RuntimeError):
    pass


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
    return [d for d in map(json.loads, raw) if d.get("kind") == "config"]


def _string(data: bytes, off: int) -> tuple[str, int]:
    k = struct.unpack_from("<I", data, off)[0]
    return bytes(data[off + 4:off + 4 + k]).decode(), off + 4 + k


def _core_meta(data: bytes) -> dict | None:
    """The 'core' metadata record (name, then a string map {"json": ...})."""
    for op, c, _ln in _top_level(data):
        if op == 0x0C:
            name, c = _string(data, c)
            if name != "core":
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
        raise ReplayError(f"{path}: not an MCAP file")
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
        raise ReplayError(f"chunk compression {comp!r} not supported")
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


def _read_fast(path: str | Path, data=None) -> LogData:
    out = LogData()
    table = bytearray(b"\xff" * 65536)
    events_ids: set[int] = set()
    keys = tuple(tuple(("" if k in NEEDED[c] else "~").encode() + k.encode() for k in ks) for c, ks in enumerate(KEYS))
    data = _read_bytes(path) if data is None else data
    out.core = _core_meta(data)
    for recs in _records(path, data):  # the top level first, then each chunk
        for cid, topic in _mcapscan.channels(recs):
            leaf = topic.decode().rsplit("/", 1)[-1]
            if leaf in LEAVES:
                table[cid] = LEAVES.index(leaf)
            elif leaf == "events":
                events_ids.add(cid)
        rows = np.frombuffer(_mcapscan.scan(recs, bytes(table), keys), dtype=np.float64)
        out.rows.append(rows.reshape(-1, ROW))
        for cid in events_ids:
            out.events += _config_events(_mcapscan.raw(recs, cid))
    return out


def _read_general(path: str | Path, data=None) -> LogData:
    out = LogData(core=_core_meta(_read_bytes(path) if data is None else data))
    rows: list[list[float]] = []
    events: list[bytes] = []
    topics: dict[int, str] = {}
    with open(path, "rb") as f:
        try:  # records in file order, chunks expanded: works on a file without summary too
            for rec in StreamReader(f).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                if not isinstance(rec, Message):
                    continue
                leaf = topics.get(rec.channel_id, "").rsplit("/", 1)[-1]
                if leaf in LEAVES:
                    code = LEAVES.index(leaf)
                    d = json.loads(rec.data)
                    r = [float(code), *(float(d[k]) for k in KEYS[code])]
                    rows.append(r + [0.0] * (ROW - len(r)))
                elif leaf == "events":
                    events.append(rec.data)
        except (McapError, EOFError, struct.error):  # cut off (killed writer): keep what was complete
            pass
    out.events = _config_events(events)
    out.rows.append(np.array(rows, dtype=np.float64).reshape(-1, ROW))
    return out


def _read_index(path: str | Path, data: bytes) -> LogData | None:
    """A log's replay inputs from its tick index (service.logio.ring.TickIndex attachments), or None when it has
    none or the index does not account for every tick of the file (no summary: a killed writer; a dropped
    ring slot; a tick split by rotation): then the JSON channels are read instead."""
    from service.logio.ring import TickIndex

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


def read_log(path: str | Path, use_index: bool = True) -> LogData:
    """A log's replay inputs: from its tick index if it has a complete one, else by the fast scanner if built
    (and the log is the recorder's flat JSON), else by the general reader."""
    data = _read_bytes(path)
    got = _read_index(path, data) if use_index else None
    if got is not None:
        return got
    if _mcapscan is not None:
        try:
            return _read_fast(path, data)
        except ValueError:
            pass  # not our templates (hand-made or foreign log): the general reader copes
    return _read_general(path, data)


@dataclass
class Ticks:
    """The replayable ticks, sorted by (epoch, seq): inputs as run_batch rows, logged commands, events."""

    core: dict
    keys: np.ndarray  # int64 epoch << SEQ_BITS | seq
    rows: np.ndarray  # n x 9 (or wider, the extra columns ignored): seq, t, i, v, u, i_load, P_r_in, P_r_in_dot,
    #                   stepped
    logged: np.ndarray  # n logged du/dt (NaN where no command was logged)
    logged_next: np.ndarray  # n logged planned du/dt (du_dt_next)
    has_cmd: np.ndarray  # bool
    cfg_events: dict[int, list]  # key -> controller configs applied before that tick
    restarts: int
    sources: list[str]  # per part: "index" or "json"


def _increasing(keys: np.ndarray) -> bool:
    """Strictly increasing: sorted, no key twice."""
    return len(keys) < 2 or bool((keys[1:] > keys[:-1]).all())


def _last_per_key(keys: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique keys and, for each, the values of its last occurrence (a later message wins)."""
    if _increasing(keys):  # the usual log: as is
        return keys, vals
    rk = keys[::-1]
    uk, idx = np.unique(rk, return_index=True)
    return uk, vals[::-1][idx]


def _epochs(seq: np.ndarray, is_meas: np.ndarray | None = None) -> np.ndarray:
    """Plant epoch of each row: a new one begins at a measurement with seq 0 after a higher one (a restart)."""
    sel = np.arange(len(seq)) if is_meas is None else np.nonzero(is_meas)[0]
    mseq = seq[sel]
    prev = np.concatenate(([-1.0], mseq[:-1]))
    restart = np.zeros(len(seq), dtype=np.int64)
    restart[sel] = (mseq == 0) & (prev > 0)
    return np.cumsum(restart)


def _place_config_events(events: list[dict], mk: np.ndarray, mt: np.ndarray, last_epoch: int) -> dict[int, list]:
    """Config changes by the tick key they precede. mk: the measurements' sorted keys, mt their times. A change
    belongs to the epoch of the sample before it (the daemon stamps that sample's t)."""
    placed: dict[int, list] = {}
    for d in events:
        s, ep_found = d["seq"], None
        for e in range(last_epoch + 1):
            for k in (s - 1, s):
                j = np.searchsorted(mk, (e << SEQ_BITS) | k)
                if ep_found is None and j < len(mk) and mk[j] == ((e << SEQ_BITS) | k) and mt[j] == d["t"]:
                    ep_found = e
        ep = last_epoch if ep_found is None else ep_found
        placed.setdefault((ep << SEQ_BITS) | s, []).append(json.loads(d["detail"]))
    return placed


def _from_index(data: list[LogData]) -> Ticks | None:
    """Ticks straight from the index rows (already one per tick, in order); None if a seq repeats within an
    epoch (then the general join decides which message wins)."""
    t = np.concatenate([d.ticks for d in data]) if len(data) > 1 else data[0].ticks
    epoch = _epochs(t[:, 0])
    keys = (epoch << SEQ_BITS) | t[:, 0].astype(np.int64)
    if not _increasing(keys):
        return None
    last_epoch = int(epoch[-1]) if len(t) else 0
    cfg_events = _place_config_events([e for d in data for e in d.events], keys, t[:, 1], last_epoch)
    return Ticks(data[0].core, keys, t, t[:, 9], t[:, 10], np.ones(len(t), dtype=bool), cfg_events, last_epoch,
                 [d.source for d in data])


def collect(parts: list, use_index: bool = True) -> Ticks:
    data = [read_log(p, use_index) for p in parts]
    if data[0].core is None:
        raise ReplayError(f"{parts[0]}: no 'core' metadata record (not an energyctl log, or written before "
                          "replay support)")
    if all(d.ticks is not None for d in data):
        fast = _from_index(data)
        if fast is not None:
            return fast
    rows = np.concatenate([r for d in data for r in d.as_rows()]) if data else np.zeros((0, 9))
    code, seq = rows[:, 0], rows[:, 1]
    is_meas = code == 0
    epoch = _epochs(seq, is_meas)
    key = (epoch << SEQ_BITS) | seq.astype(np.int64)
    mk, mv = _last_per_key(key[is_meas], rows[is_meas])
    zsel, csel = code == 1, code == 2
    zk, zv = _last_per_key(key[zsel], rows[zsel])
    ck, cv = _last_per_key(key[csel], rows[csel])
    if np.array_equal(mk, zk):  # every tick has both (the usual log): no join needed
        keys, m, z = mk, mv, zv
    else:
        keys = np.intersect1d(mk, zk, assume_unique=True)
        m, z = mv[np.searchsorted(mk, keys)], zv[np.searchsorted(zk, keys)]
    out = np.empty((len(keys), 9))
    out[:, 0:6] = m[:, 1:7]  # seq, t, i, v, u, i_load
    out[:, 6:8] = z[:, 3:5]  # P_r_in, P_r_in_dot
    out[:, 8] = z[:, 5]  # stepped
    pos = np.searchsorted(ck, keys)
    pos_c = np.minimum(pos, max(len(ck) - 1, 0))
    has_cmd = (pos < len(ck)) & (ck[pos_c] == keys) if len(ck) else np.zeros(len(keys), bool)
    logged = np.where(has_cmd, cv[pos_c, 3] if len(ck) else np.nan, np.nan)
    logged_next = np.where(has_cmd, cv[pos_c, 4] if len(ck) else np.nan, np.nan)
    last_epoch = int(epoch[-1]) if len(epoch) else 0
    cfg_events = _place_config_events([e for d in data for e in d.events], mk, mv[:, 2], last_epoch)
    return Ticks(data[0].core, keys, out, logged, logged_next, has_cmd, cfg_events, last_epoch,
                 [d.source for d in data])


def replay(path: str | Path | list, overrides: list[str] | None = None, controller: str | None = None,
           out: str | None = None, progress: bool = True, use_index: bool = True) -> dict:
    """Replay one log, or the parts of a rotated log in order (one core across all of them). use_index=False
    reads the JSON channels even where a tick index exists (the messages Foxglove shows)."""
    t0 = time.perf_counter()
    parts = [path] if isinstance(path, str | Path) else list(path)
    tk = collect(parts, use_index)
    path = parts[0] if len(parts) == 1 else ", ".join(map(str, parts))
    ovs = list(overrides or [])
    if controller:
        ovs.append(f'controller.kind="{controller}"')
    what_if = bool(ovs)
    core_meta = tk.core
    ctl = _controller(core_meta["controller"], ovs)
    model = scenario_from_dict({"model": core_meta["model"]}).model
    core = make_core(ctl, model, core_meta["period_s"], core_meta["delay_samples"])
    n = len(tk.keys)
    du = np.zeros(n)
    du_next = np.zeros(n)
    epochs = tk.keys >> SEQ_BITS
    # stretches between a restart (reset before the tick) or a config change (applied before it)
    cuts = set(np.nonzero(np.diff(epochs))[0] + 1) | {0, n}
    cfg_at = {}
    if not what_if:
        for k, cfgs in tk.cfg_events.items():
            j = int(np.searchsorted(tk.keys, k))
            if j < n and tk.keys[j] == k:
                cfg_at[j] = cfgs
                cuts.add(j)
    block = 200_000  # progress granularity
    cuts |= set(range(0, n, block))
    cuts_sorted = sorted(cuts)
    show = progress and n > 20_000
    for a, b in zip(cuts_sorted, cuts_sorted[1:], strict=False):
        if a > 0 and epochs[a] != epochs[a - 1]:  # the plant restarted: the daemon re-initialised its core here
            core.reset()
        for c in cfg_at.get(a, []):
            core.set_gains(ControllerConfig.model_validate(c))
        core.run_batch(tk.rows[a:b], du[a:b], du_next[a:b])
        if show:
            sys.stderr.write(f"\rreplay {100 * b // n:3d} %")
            sys.stderr.flush()
    if show:
        sys.stderr.write("\n")
    first = None
    if not what_if:
        bad = np.nonzero(tk.has_cmd & ((tk.logged != du) | (tk.logged_next != du_next)))[0]
        if len(bad):
            j = int(bad[0])
            f, logged, got = (("du_dt", tk.logged[j], du[j]) if tk.logged[j] != du[j]
                              else ("du_dt_next", tk.logged_next[j], du_next[j]))
            first = {"seq": int(tk.rows[j, 0]), "epoch": int(epochs[j]), "t": float(tk.rows[j, 1]),
                     "field": f, "logged": float(logged), "replayed": float(got)}
    wall = time.perf_counter() - t0
    span = float(tk.rows[-1, 1] - tk.rows[0, 1]) if n else 0.0
    res = {"log": str(path), "ticks": n, "compared": int(tk.has_cmd.sum()) if not what_if else 0,
           "plant_restarts": tk.restarts, "core": core.impl, "read_from": ",".join(tk.sources),
           "identical": first is None and not what_if, "first_divergence": first, "wall_s": wall,
           "log_span_s": span, "speed_x_realtime": span / wall if wall > 0 else None}
    if out:
        _write(out, core_meta, ctl, tk, du, du_next)
        res["out"] = out
    return res


def _controller(base: dict, overrides: list[str]) -> ControllerConfig:
    data = apply_overrides({"controller": base}, [o if o.startswith("controller.") else f"controller.{o}"
                                                  for o in overrides])
    return scenario_from_dict(data).controller


def _write(out: str, core_meta: dict, ctl: ControllerConfig, tk: Ticks, du: np.ndarray, du_next: np.ndarray) -> None:
    from service.core import core_metadata
    from service.logio.mcapfile import McapFile

    f = McapFile(out)
    model = scenario_from_dict({"model": core_meta["model"]}).model
    f.metadata("core", {"json": core_metadata(ctl, model, core_meta["period_s"], core_meta["delay_samples"])})
    f.metadata("replay", {"json": json.dumps({"what_if_of": core_meta})})
    for leaf, schema in (("meas", "energyctl.Measurement"), ("z_in", "energyctl.TickInput"),
                         ("cmd", "energyctl.Command"), ("events", "energyctl.Event")):
        f.channel(f"replay/{leaf}", schema)
    epochs = (tk.keys >> SEQ_BITS).tolist()
    cur_epoch = 0
    for j, r in enumerate(tk.rows.tolist()):
        seq, t = int(r[0]), r[1]
        if epochs[j] != cur_epoch:  # keep the epochs apart in the what-if log too
            f.add("replay/events", t, {"t": t, "seq": 0, "kind": "plant_restart", "detail": "{}"})
            cur_epoch = epochs[j]
        f.add("replay/meas", t, dict(zip(MEAS.fields, (seq, *r[1:6]), strict=True)))
        f.add("replay/z_in", t, {"seq": seq, "t": t, "P_r_in": r[6], "P_r_in_dot": r[7], "stepped": bool(r[8])})
        f.add("replay/cmd", t, dict(zip(CMD.fields, (seq, t, float(du[j]), float(du_next[j]), False), strict=True)))
    f.close()
