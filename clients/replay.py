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

Speed: the log is read into arrays (clients/_mcapscan.c parses the recorder's flat JSON without a Python
object per message; without it, mcap + json do the same, slower), and the core steps each stretch between
config changes and restarts in one call (the compiled core's loop runs in C). Both fast paths give the
same doubles as the general ones; the comparison with the logged commands is still ``==``.
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
    from clients import _mcapscan
except ImportError:  # not built (no C compiler): the general reader is used
    _mcapscan = None
if sys.byteorder != "little" or (_mcapscan is not None and _mcapscan.ROW != 9):
    _mcapscan = None


class ReplayError(RuntimeError):
    pass


LEAVES = ("meas", "z_in", "cmd")  # channel codes 0, 1, 2
KEYS = (MEAS.fields, tuple(TickInput.model_fields), CMD.fields)
NEEDED = (set(MEAS.fields), {"seq", "P_r_in", "P_r_in_dot", "stepped"}, {"seq", "du_dt"})  # what replay reads
ROW = 9  # a row: channel code, then up to 8 fields
SEQ_BITS = 40  # key = epoch << SEQ_BITS | seq


@dataclass
class LogData:
    """A log's replay inputs in file order: one row per message of meas / z_in / cmd (code, then its fields in
    schema order, zero-padded), the config events, the core metadata, and where the epochs ended."""

    core: dict | None = None
    rows: list[np.ndarray] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)


def _top_level(data: bytes):
    """(opcode, content offset, content length) of each complete top-level record after the magic; a cut-off
    file (killed writer) ends at its last complete record."""
    off, n = 8, len(data)
    while off + 9 <= n:
        op, ln = data[off], struct.unpack_from("<Q", data, off + 1)[0]
        if off + 9 + ln > n:
            return
        yield op, off + 9, ln
        off += 9 + ln


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


def _read_bytes(path: str | Path) -> bytes:
    data = Path(path).read_bytes()
    if data[:8] != b"\x89MCAP0\r\n":
        raise ReplayError(f"{path}: not an MCAP file")
    return data


def _records(path: str | Path, data: bytes):
    """Each record sequence of an MCAP file: the top level itself, then every chunk decompressed."""
    import zstandard

    yield memoryview(data)[8:]  # the top level (channels, metadata, unchunked messages)
    dctx = zstandard.ZstdDecompressor()
    for op, c, _ln in _top_level(data):
        if op == 0x06:  # chunk: start, end, uncompressed size, crc, compression, records
            size = struct.unpack_from("<Q", data, c + 16)[0]
            comp, c = _string(data, c + 28)
            rl = struct.unpack_from("<Q", data, c)[0]
            raw = data[c + 8:c + 8 + rl]
            if comp == "zstd":
                raw = dctx.decompress(raw, max_output_size=size)
            elif comp == "lz4":
                import lz4.frame

                raw = lz4.frame.decompress(raw)
            elif comp:
                raise ReplayError(f"{path}: chunk compression {comp!r} not supported")
            yield raw


def _read_fast(path: str | Path) -> LogData:
    out = LogData()
    table = bytearray(b"\xff" * 65536)
    events_ids: set[int] = set()
    keys = tuple(tuple(("" if k in NEEDED[c] else "~").encode() + k.encode() for k in ks) for c, ks in enumerate(KEYS))
    data = _read_bytes(path)
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
            out.events += [d for d in map(json.loads, _mcapscan.raw(recs, cid)) if d.get("kind") == "config"]
    return out


def _read_general(path: str | Path) -> LogData:
    out = LogData(core=_core_meta(_read_bytes(path)))
    rows: list[list[float]] = []
    topics: dict[int, str] = {}
    with open(path, "rb") as f:
        try:  # records in file order, chunks expanded: works on a file without summary too
            for rec in StreamReader(f).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                if not isinstance(rec, Message):
                    continue
                message = rec
                leaf = topics.get(rec.channel_id, "").rsplit("/", 1)[-1]
                if leaf in LEAVES:
                    code = LEAVES.index(leaf)
                    d = json.loads(message.data)
                    r = [float(code), *(float(d[k]) for k in KEYS[code])]
                    rows.append(r + [0.0] * (ROW - len(r)))
                elif leaf == "events":
                    d = json.loads(message.data)
                    if d.get("kind") == "config":
                        out.events.append(d)
        except (McapError, EOFError, struct.error):  # cut off (killed writer): keep what was complete
            pass
    out.rows.append(np.array(rows, dtype=np.float64).reshape(-1, ROW))
    return out


def read_log(path: str | Path) -> LogData:
    """A log's replay inputs, by the fast scanner if built (and the log is the recorder's flat JSON), else
    by the general reader."""
    if _mcapscan is not None:
        try:
            return _read_fast(path)
        except ValueError:
            pass  # not our templates (hand-made or foreign log): the general reader copes
    return _read_general(path)


@dataclass
class Ticks:
    """The replayable ticks, sorted by (epoch, seq): inputs as run_batch rows, logged commands, events."""

    core: dict
    keys: np.ndarray  # int64 epoch << SEQ_BITS | seq
    rows: np.ndarray  # n x 9: seq, t, i, v, u, i_load, P_r_in, P_r_in_dot, stepped
    logged: np.ndarray  # n logged du/dt (NaN where no command was logged)
    has_cmd: np.ndarray  # bool
    cfg_events: dict[int, list]  # key -> controller configs applied before that tick
    restarts: int


def _last_per_key(keys: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique keys and, for each, the values of its last occurrence (a later message wins)."""
    rk = keys[::-1]
    uk, idx = np.unique(rk, return_index=True)
    return uk, vals[::-1][idx]


def collect(parts: list) -> Ticks:
    data = [read_log(p) for p in parts]
    if data[0].core is None:
        raise ReplayError(f"{parts[0]}: no 'core' metadata record (not an energyctl log, or written before "
                          "replay support)")
    rows = np.concatenate([r for d in data for r in d.rows]) if data else np.zeros((0, 9))
    code, seq = rows[:, 0], rows[:, 1]
    is_meas = code == 0
    mseq = seq[is_meas]
    prev = np.concatenate(([-1.0], mseq[:-1]))
    restart_at_meas = (mseq == 0) & (prev > 0)  # the plant restarted: a new epoch
    restart = np.zeros(len(rows), dtype=np.int64)
    restart[np.nonzero(is_meas)[0]] = restart_at_meas
    epoch = np.cumsum(restart)
    key = (epoch << SEQ_BITS) | seq.astype(np.int64)
    mk, mv = _last_per_key(key[is_meas], rows[is_meas])
    zsel, csel = code == 1, code == 2
    zk, zv = _last_per_key(key[zsel], rows[zsel])
    ck, cv = _last_per_key(key[csel], rows[csel])
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
    last_epoch = int(epoch[-1]) if len(epoch) else 0
    cfg_events: dict[int, list] = {}
    for d in (e for dd in data for e in dd.events):
        # a config change belongs to the epoch of the sample before it (the daemon stamps that t)
        s, ep_found = d["seq"], None
        for e in range(last_epoch + 1):
            for k in (s - 1, s):
                j = np.searchsorted(mk, (e << SEQ_BITS) | k)
                if ep_found is None and j < len(mk) and mk[j] == ((e << SEQ_BITS) | k) and mv[j, 2] == d["t"]:
                    ep_found = e
        ep = last_epoch if ep_found is None else ep_found
        cfg_events.setdefault((ep << SEQ_BITS) | s, []).append(json.loads(d["detail"]))
    return Ticks(data[0].core, keys, out, logged, has_cmd, cfg_events, last_epoch)


def replay(path: str | Path | list, overrides: list[str] | None = None, controller: str | None = None,
           out: str | None = None, progress: bool = True) -> dict:
    """Replay one log, or the parts of a rotated log in order (one core across all of them)."""
    t0 = time.perf_counter()
    parts = [path] if isinstance(path, str | Path) else list(path)
    tk = collect(parts)
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
        core.run_batch(tk.rows[a:b], du[a:b])
        if show:
            sys.stderr.write(f"\rreplay {100 * b // n:3d} %")
            sys.stderr.flush()
    if show:
        sys.stderr.write("\n")
    first = None
    if not what_if:
        bad = np.nonzero(tk.has_cmd & (tk.logged != du))[0]
        if len(bad):
            j = int(bad[0])
            first = {"seq": int(tk.rows[j, 0]), "epoch": int(epochs[j]), "t": float(tk.rows[j, 1]),
                     "field": "du_dt", "logged": float(tk.logged[j]), "replayed": float(du[j])}
    wall = time.perf_counter() - t0
    span = float(tk.rows[-1, 1] - tk.rows[0, 1]) if n else 0.0
    res = {"log": str(path), "ticks": n, "compared": int(tk.has_cmd.sum()) if not what_if else 0,
           "plant_restarts": tk.restarts, "core": core.impl,
           "identical": first is None and not what_if, "first_divergence": first, "wall_s": wall,
           "log_span_s": span, "speed_x_realtime": span / wall if wall > 0 else None}
    if out:
        _write(out, core_meta, ctl, tk, du)
        res["out"] = out
    return res


def _controller(base: dict, overrides: list[str]) -> ControllerConfig:
    data = apply_overrides({"controller": base}, [o if o.startswith("controller.") else f"controller.{o}"
                                                  for o in overrides])
    return scenario_from_dict(data).controller


def _write(out: str, core_meta: dict, ctl: ControllerConfig, tk: Ticks, du: np.ndarray) -> None:
    from service.core import core_metadata
    from service.recorder import McapFile

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
        f.add("replay/cmd", t, dict(zip(CMD.fields, (seq, t, float(du[j]), False), strict=True)))
    f.close()
