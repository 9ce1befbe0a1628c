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
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from mcap.reader import make_reader

from schemas.scenario import ControllerConfig, apply_overrides, scenario_from_dict
from service.core import ControlCore
from service.types import Incoming, Sample


class ReplayError(RuntimeError):
    pass


Key = tuple[int, int]  # (epoch, seq)


def read_log(path: str | Path, epoch: int = 0, last_seq: int = -1) -> tuple[
        dict, dict[Key, dict], dict[Key, dict], dict[Key, dict], dict[Key, list], tuple[int, int]]:
    """(core metadata, meas, z_in, cmd, config events, (last epoch, last seq)), keyed by (epoch, seq); reads
    in file order, so a log whose writer was killed (no summary) still replays up to its last complete
    chunk. ``epoch``, ``last_seq``: where the previous part of a rotated log ended."""
    meas: dict[Key, dict] = {}
    zin: dict[Key, dict] = {}
    cmd: dict[Key, dict] = {}
    cfg: list[dict] = []
    core = None
    with open(path, "rb") as f:
        reader = make_reader(f)
        for rec in reader.iter_metadata():
            if rec.name == "core":
                core = json.loads(rec.metadata["json"])
        f.seek(0)
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            leaf = channel.topic.rsplit("/", 1)[-1]
            if leaf not in ("meas", "z_in", "cmd", "events"):
                continue
            d = json.loads(message.data)
            if leaf == "meas":
                if d["seq"] == 0 and last_seq > 0:
                    epoch += 1
                last_seq = d["seq"]
                meas[epoch, d["seq"]] = d
            elif leaf == "z_in":
                zin[epoch, d["seq"]] = d
            elif leaf == "cmd":
                cmd[epoch, d["seq"]] = d
            elif d.get("kind") == "config":
                cfg.append(d)
    if core is None:
        raise ReplayError(f"{path}: no 'core' metadata record (not an energyctl log, or written before replay support)")
    cfg_events: dict[Key, list] = {}
    for d in cfg:  # a config change belongs to the epoch of the sample before it (the daemon stamps that t)
        s = d["seq"]
        eps = [e for e in range(epoch + 1) for k in (s - 1, s) if (e, k) in meas and meas[e, k]["t"] == d["t"]]
        cfg_events.setdefault((eps[0] if eps else epoch, d["seq"]), []).append(json.loads(d["detail"]))
    return core, meas, zin, cmd, cfg_events, (epoch, last_seq)


def replay(path: str | Path | list, overrides: list[str] | None = None, controller: str | None = None,
           out: str | None = None, progress: bool = True) -> dict:
    """Replay one log, or the parts of a rotated log in order (one core across all of them)."""
    t0 = time.perf_counter()
    parts = [path] if isinstance(path, str | Path) else list(path)
    core_meta, meas, zin, cmd, cfg_events, (epoch, last) = read_log(parts[0])
    for extra in parts[1:]:
        _, m2, z2, c2, e2, (epoch, last) = read_log(extra, epoch, last)
        meas.update(m2)
        zin.update(z2)
        cmd.update(c2)
        for k, v in e2.items():
            cfg_events.setdefault(k, []).extend(v)
    path = parts[0] if len(parts) == 1 else ", ".join(map(str, parts))
    ovs = list(overrides or [])
    if controller:
        ovs.append(f'controller.kind="{controller}"')
    what_if = bool(ovs)
    ctl = _controller(core_meta["controller"], ovs)
    model = scenario_from_dict({"model": core_meta["model"]}).model
    core = ControlCore(ctl, model, core_meta["period_s"], core_meta["delay_samples"])
    seqs = sorted(s for s in meas if s in zin)
    first = None
    replayed: list[tuple] = []
    n = len(seqs)
    step_report = max(1, n // 20)
    cur_epoch = 0
    for j, (ep, seq) in enumerate(seqs):
        if ep != cur_epoch:  # the plant restarted: the daemon re-initialised its core here
            core.reset()
            cur_epoch = ep
        for c in cfg_events.get((ep, seq), []):
            if not what_if:
                core.set_gains(ControllerConfig.model_validate(c))
        m, z = meas[ep, seq], zin[ep, seq]
        if z["stepped"]:
            o = core.step(Sample(seq, m["t"], m["i"], m["v"], m["u"], m["i_load"]),
                          Incoming(z["P_r_in"], z["P_r_in_dot"]))
            du = o.du_dt
        else:
            du = 0.0
        replayed.append(((ep, seq), m["t"], du))
        logged = cmd.get((ep, seq))
        if first is None and not what_if and logged is not None and logged["du_dt"] != du:
            first = {"seq": seq, "epoch": ep, "t": m["t"], "field": "du_dt", "logged": logged["du_dt"],
                     "replayed": du}
        if progress and n > 20_000 and j % step_report == 0:
            sys.stderr.write(f"\rreplay {100 * j // n:3d} %")
            sys.stderr.flush()
    if progress and n > 20_000:
        sys.stderr.write("\rreplay 100 %\n")
    wall = time.perf_counter() - t0
    span = (meas[seqs[-1]]["t"] - meas[seqs[0]]["t"]) if seqs else 0.0
    res = {"log": str(path), "ticks": n, "compared": sum(1 for s in seqs if s in cmd) if not what_if else 0,
           "plant_restarts": epoch,
           "identical": first is None and not what_if, "first_divergence": first, "wall_s": wall,
           "log_span_s": span, "speed_x_realtime": span / wall if wall > 0 else None}
    if out:
        _write(out, core_meta, ctl, replayed, meas, zin)
        res["out"] = out
    return res


def _controller(base: dict, overrides: list[str]) -> ControllerConfig:
    data = apply_overrides({"controller": base}, [o if o.startswith("controller.") else f"controller.{o}"
                                                  for o in overrides])
    return scenario_from_dict(data).controller


def _write(out: str, core_meta: dict, ctl: ControllerConfig, replayed, meas, zin) -> None:
    from schemas.codec import CMD, MEAS
    from schemas.messages import TickInput
    from service.core import core_metadata
    from service.recorder import McapFile

    f = McapFile(out)
    model = scenario_from_dict({"model": core_meta["model"]}).model
    f.metadata("core", {"json": core_metadata(ctl, model, core_meta["period_s"], core_meta["delay_samples"])})
    f.metadata("replay", {"json": json.dumps({"what_if_of": core_meta})})
    for leaf, schema in (("meas", "energyctl.Measurement"), ("z_in", "energyctl.TickInput"),
                         ("cmd", "energyctl.Command"), ("events", "energyctl.Event")):
        f.channel(f"replay/{leaf}", schema)
    zf = tuple(TickInput.model_fields)
    cur_epoch = 0
    for (ep, seq), t, du in replayed:
        if ep != cur_epoch:  # keep the epochs apart in the what-if log too
            f.add("replay/events", t, {"t": t, "seq": 0, "kind": "plant_restart", "detail": "{}"})
            cur_epoch = ep
        f.add("replay/meas", t, {k: meas[ep, seq][k] for k in MEAS.fields})
        f.add("replay/z_in", t, {k: zin[ep, seq][k] for k in zf})
        f.add("replay/cmd", t, dict(zip(CMD.fields, (seq, t, du, False), strict=True)))
    f.close()
