"""energyctl bench recorder: the daemon's stream set at 10 kHz through the Recorder, vs the bare mcap writer.

Part 1 (bare): pre-encoded JSON messages straight into an mcap Writer (zstd chunks), as fast as it
goes: messages/s and bytes/s of the library alone.
Part 2 (paced): a loop thread scheduled like the daemon's clock loop (absolute time, sleep then spin)
offers to the daemon's recorder (shared-memory ring, writer process) per tick what the daemon offers
(meas, z_in, cmd every tick, grouped in one slot; est and z_out every 10th) for the
given duration; reports the loop's overruns, the recorder's drops, and the recorder's sustained
messages/s and bytes/s. The ratio is part 2's sustained rate over part 1's capacity.
"""

from __future__ import annotations

import gc
import json
import os
import tempfile
import threading
import time
from pathlib import Path

from mcap.writer import CompressionType, Writer

from clients.machine import StealMeter
from schemas.codec import CMD, EST, MEAS, TICK_IN, Z
from schemas.messages import Estimate, TickInput
from service.logio.ring import RingRecorder

EST_FIELDS = tuple(Estimate.model_fields)
ZIN_FIELDS = tuple(TickInput.model_fields)


def _streams(k: int, t: float) -> list[tuple[str, tuple, tuple]]:
    out = [("meas", MEAS.fields, (k, t, 15.0 + 1e-3 * k, 80.0, 80.15, 15.0)),
           ("z_in", ZIN_FIELDS, (k, t, -1200.0, 0.0, True)),
           ("cmd", CMD.fields, (k, t, 123.456 + k, 23.456 + k, False))]
    if k % 10 == 0:
        out.append(("est", EST_FIELDS, (t, 21.9, 1.5, 3.2, -1200.0, -1199.0, -1200.0, 10.0, -5.0, -1200.0, 3.0,
                                        -1.2 * t, 0.1 * t)))
        out.append(("z_out", Z.fields, (k // 10, t, -1200.0, 0.0, 3.0, -1.2 * t, 0.1 * t, 0, -1300.0, -1100.0,
                                        -10.0, 10.0)))
    return out


def bench_bare(n_ticks: int, path: Path) -> dict:
    msgs = [[(topic, json.dumps(dict(zip(f, v, strict=True)), separators=(",", ":")).encode())
             for topic, f, v in _streams(k, k * 1e-4)] for k in range(n_ticks)]
    t0 = time.perf_counter()
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=1 << 20, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = {t: w.register_channel(t, "json", sid) for t in ("meas", "z_in", "cmd", "est", "z_out")}
        n = 0
        for k, tick in enumerate(msgs):
            ns = k * 100_000
            for topic, data in tick:
                w.add_message(cid[topic], ns, data, ns)
                n += 1
        w.finish()
    wall = time.perf_counter() - t0
    return {"messages": n, "wall_s": wall, "msgs_per_s": n / wall, "bytes_per_s": path.stat().st_size / wall}


def bench_paced(seconds: float, rate_hz: float, path: Path | None, writer_cpus: list[int] | None = None) -> dict:
    """path None: the same loop with a no-op offer (the machine's own overrun baseline)."""
    topics = {"meas": ("energyctl.Measurement", MEAS), "z_in": ("energyctl.TickInput", TICK_IN),
              "cmd": ("energyctl.Command", CMD), "est": ("energyctl.Estimate", EST),
              "z_out": ("energyctl.Interaction", Z), "events": ("energyctl.Event", None)}
    rec = RingRecorder(path, topics, {"bench": {"json": "{}"}}, writer_cpus=writer_cpus,
                       groups=[("meas", "z_in", "cmd")]) if path is not None else None
    period = int(1e9 / rate_hz)
    n_ticks = int(seconds * rate_hz)
    stats = {"overruns": 0, "ticks": 0}
    offer = rec.offer if rec is not None else (lambda topic, t, v: None)
    offer_group = rec.offer_group if rec is not None else (lambda g, t, *v: None)

    def loop() -> None:
        now = time.monotonic_ns
        gc.freeze()
        nxt = now() + period
        for k in range(n_ticks):
            wait = nxt - now()
            if wait > 200_000:
                time.sleep((wait - 200_000) * 1e-9)
            while now() < nxt:
                pass
            t = k / rate_hz
            (_m, _fm, m), (_z, _fz, z), (_c, _fc, c), *rest = _streams(k, t)
            offer_group(0, t, *m, *z, *c)  # as the daemon's tick: meas, z_in and cmd in one slot
            for topic, _f, v in rest:
                offer(topic, t, v)
            stats["ticks"] += 1
            nxt += period
            end = now()
            if end > nxt:
                missed = (end - nxt) // period + 1
                stats["overruns"] += missed
                nxt += missed * period
        gc.unfreeze()

    t0 = time.perf_counter()
    th = threading.Thread(target=loop, name="loop")
    th.start()
    th.join()
    loop_wall = time.perf_counter() - t0
    if rec is None:
        return {"ticks": stats["ticks"], "overruns": stats["overruns"],
                "overrun_pct": 100.0 * stats["overruns"] / max(1, stats["ticks"])}
    rec.close()
    wall = time.perf_counter() - t0
    size = path.stat().st_size
    return {"rate_hz": rate_hz, "seconds": seconds, "ticks": stats["ticks"], "overruns": stats["overruns"],
            "overrun_pct": 100.0 * stats["overruns"] / max(1, stats["ticks"]),
            "drops": sum(rec.drops.values()), "ring_slots": rec.slots,
            "written": rec.written, "msgs_per_s": rec.written / loop_wall, "bytes_per_s": size / loop_wall,
            "close_s": wall - loop_wall, "file_bytes": size, "recorder_error": rec.error}


def bench_recorder(seconds: float = 10.0, rate_hz: float = 10_000.0, writer_cpus: list[int] | None = None) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="energyctl-rec-"))
    try:
        bare = bench_bare(20_000, tmp / "bare.mcap")
        with StealMeter() as m0:
            baseline = bench_paced(seconds, rate_hz, None)
        baseline["host_steal_pct"] = m0.pct
        with StealMeter() as m1:
            paced = bench_paced(seconds, rate_hz, tmp / "paced.mcap", writer_cpus)
        paced["host_steal_pct"] = m1.pct
    finally:
        for p in tmp.glob("*.mcap"):
            os.unlink(p)
        tmp.rmdir()
    return {"bench": "recorder", "bare_writer": bare, "loop_without_recorder": baseline, "recorder_paced": paced,
            "ratio_sustained_to_bare_capacity": paced["msgs_per_s"] / bare["msgs_per_s"]}


if __name__ == "__main__":
    print(json.dumps(bench_recorder(), indent=1))
