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

Speed: the log is read into arrays by ``service.logio.reader.read_log`` (from the daemon's tick index when it
is complete). The core steps each stretch between config changes and restarts in one call (the compiled
core's loop runs in C). Every fast path gives the same doubles as the general one; the comparison with the
logged commands is still ``==``.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.codec import CMD, MEAS
from schemas.scenario import ControllerConfig, apply_overrides, scenario_from_dict
from service.core import make_core
from service.logio.reader import SEQ_BITS, LogData, LogError, component_names, read_log

ReplayError = LogError  # what replay raises on a log it cannot use


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
    stopped_at_gap: dict | None = None  # a recovered log: the first dropped chunk, where the ticks end (_before_gap)


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


def _before_gap(tk: Ticks, gaps: list[dict], part: str) -> Ticks:
    """A recovered log (energyctl log recover dropped corrupt chunks): only the ticks before the first lost chunk.
    Every message of a lost chunk has a log time at or after the chunk's start, so each tick stamped before it is
    whole; after it the core's state is unknown (the lost ticks carried it), so nothing after is compared."""
    if any(g.get("start_s") is None for g in gaps):
        raise ReplayError(f"{part}: recovered from a log that lost a chunk whose time span is unknown; replay needs "
                          "every tick in order")
    first = min(gaps, key=lambda g: g["start_s"])
    late = np.nonzero(tk.rows[:, 1] >= first["start_s"])[0]
    keep = int(late[0]) if len(late) else len(tk.keys)
    if keep == 0:
        raise ReplayError(f"{part}: recovered from a log that lost its first ticks (a corrupt chunk from t = "
                          f"{first['start_s']:.6f} s, byte {first['offset']}): the core's state at the first readable "
                          "tick is unknown, nothing to replay")
    k = slice(0, keep)
    return Ticks(tk.core, tk.keys[k], tk.rows[k], tk.logged[k], tk.logged_next[k], tk.has_cmd[k], tk.cfg_events,
                 int(tk.keys[keep - 1] >> SEQ_BITS), tk.sources, first)


def collect(parts: list, use_index: bool = True, component: str | None = None) -> Ticks:
    tk, data = _collect(parts, use_index, component)
    gaps = [g for d in data for g in d.gaps]
    return _before_gap(tk, gaps, str(parts[0])) if gaps else tk


def _collect(parts: list, use_index: bool = True, component: str | None = None) -> tuple[Ticks, list[LogData]]:
    data = [read_log(p, use_index, component) for p in parts]
    if data[0].core is None and component is None and (names := component_names(parts[0])):
        raise ReplayError(f"{parts[0]}: a network log: name the component to replay (--component "
                          f"{' | '.join(names)})")
    if data[0].core is None and component is not None:
        raise ReplayError(f"{parts[0]}: no component {component!r} (it has: "
                          f"{', '.join(component_names(parts[0])) or 'none'})")
    if data[0].core is None:
        raise ReplayError(f"{parts[0]}: no 'core' metadata record: not a controller's log (replay takes the "
                          "daemon's source-*.mcap or energyctl sim --out; a plant's or a demo's combined log holds no "
                          "core to rebuild), or written before replay support")
    if all(d.ticks is not None for d in data):
        fast = _from_index(data)
        if fast is not None:
            return fast, data
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
                 [d.source for d in data]), data


def replay(path: str | Path | list, overrides: list[str] | None = None, controller: str | None = None,
           out: str | None = None, progress: bool = True, use_index: bool = True, impl: str = "auto",
           component: str | None = None) -> dict:
    """Replay one log, or the parts of a rotated log in order (one core across all of them). use_index=False
    reads the JSON channels even where a tick index exists (the messages Foxglove shows). impl: the core's
    implementation (service.core.make_core). component: in a network log, the source to replay."""
    t0 = time.perf_counter()
    parts = [path] if isinstance(path, str | Path) else list(path)
    tk = collect(parts, use_index, component)
    path = parts[0] if len(parts) == 1 else ", ".join(map(str, parts))
    ovs = list(overrides or [])
    if controller:
        ovs.append(f'controller.kind="{controller}"')
    what_if = bool(ovs)
    core_meta = tk.core
    ctl = _controller(core_meta["controller"], ovs)
    model = scenario_from_dict({"model": core_meta["model"]}).model
    core = make_core(ctl, model, core_meta["period_s"], core_meta["delay_samples"], impl)
    n = len(tk.keys)
    du = np.zeros(n)
    du_next = np.zeros(n)
    epochs = tk.keys >> SEQ_BITS
    # stretches between a restart (reset before the tick) or a config change (applied before it)
    cuts = set(np.nonzero(np.diff(epochs))[0] + 1) | {0, n}
    # samples answered outside the law with a rate of their own (a network source's idle mode): the core is told
    # that rate (core.hold(seq, du_dt)), one by one; a daemon's holds are 0 and stay in the batches
    held = np.nonzero((tk.rows[:, 8] == 0) & tk.has_cmd & (tk.logged != 0))[0] if n else np.zeros(0, dtype=int)
    held_set = set(held.tolist())
    cuts |= held_set | {j + 1 for j in held_set}
    cfg_at = {}
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
            if set(c) == {"v_ref_V"}:  # a network layer's v_ref move: part of the inputs, kept in a what-if too
                core.set_gains(core.cfg.model_copy(update=c))
            elif not what_if:  # an operator's config set: a what-if replaces it
                core.set_gains(ControllerConfig.model_validate(c))
        if a in held_set:
            core.hold(int(tk.rows[a, 0]), float(tk.logged[a]))
            du[a], du_next[a] = tk.logged[a], 0.0
            continue
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
           "log_span_s": span, "speed_x_realtime": span / wall if wall > 0 else None,
           "stopped_at_gap": tk.stopped_at_gap}
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
