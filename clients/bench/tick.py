"""Benches that drive a real daemon by hand, without the network.

``energyctl bench tick``: the daemon's whole tick (decode, checks, core, publish, record), and of it the command's
``put`` (Zenoh's work on the loop thread) and the rest (compute). An opened daemon
(loopback Zenoh session, no peers, recorder process writing to a temporary directory) is handed the
measurements of a closed-loop simulator run one by one through the same method the loop calls, with the
loop's own statistics update; nothing arrives over a socket and nothing waits, so this is what our code
costs per tick, apart from the wake-ups and cross-process scheduling that `bench latency` also sees. The
compiled and the Python core are measured in the same run.

``energyctl bench replay``: the same daemon records a long 10 kHz log this way (a real daemon log: every
channel, the tick index, the metadata), then ``energyctl replay`` replays it from the tick index and from
the JSON channels, same run.
"""

from __future__ import annotations

import gc
import tempfile
import time
from pathlib import Path

from clients.bench.latency import percentiles
from schemas.codec import MEAS


def _trace(scenario_path: str, n: int):
    from schemas.scenario import load_scenario
    from service.sim import run

    scn = load_scenario(scenario_path, [f"timing.duration_s={n / 10_000.0}"])
    return scn, {k: v.tolist() for k, v in run(scn).trace.items()}


def drive_daemon(scn, tr: dict, log_dir: str, impl: str | None = None, hooks: dict | None = None,
                 n: int | None = None, skip: set[int] = frozenset()) -> tuple[list[int], dict]:
    """Tick an opened daemon by hand through the trace's measurements (the first n, but those in skip: lost on the
    way); (exec times ns, 0 where skipped; final status). hooks: {tick: fn(daemon)} called between ticks, where the
    loop applies config changes."""
    from clients.live import configs_from_scenario
    from schemas.component import ComponentConfig, config_from_dict
    from service.core import make_core
    from service.daemon.bus import free_tcp_port
    from service.daemon.daemon import Daemon

    m = len(tr["t"]) if n is None else n
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False,
                                         rate_hz=scn.timing.control_rate_hz)
    # the controller the trace was made with (not the realtime stacks' load power and regulation): the daemon's
    # commands are then the trace's, and its loop-delay estimate from the trace's u holds
    comp["controller"] = {**scn.controller.model_dump(), "delay_compensation_samples": None}
    comp["neighbour_stale_s"] = 86_400.0  # never stale here (the most the config takes: a day)
    comp["log_dir"] = log_dir
    comp["delay_samples"] = scn.timing.delay_samples
    comp["log_queue"] = 1 << 20  # the writer keeps up on average; a long run must not drop at start-up
    d = Daemon(config_from_dict(ComponentConfig, comp))
    c = d.cfg
    d.core = make_core(c.controller, c.model, d.period_s, c.delay_samples, impl)
    d.open()
    nb = d.neighbours[0]
    times = [0] * m
    try:
        now = time.monotonic_ns
        gc.collect()
        gc.freeze()
        for k in range(m):
            if hooks and k in hooks:
                hooks[k](d)
            if k in skip:
                continue
            payload = MEAS.encode(k, tr["t"][k], tr["i_meas"][k], tr["v_meas"][k], tr["u_meas"][k],
                                  tr["i_load_meas"][k])
            # the neighbour's message for this very sample (stamped with its time, as in lockstep)
            nb.P, nb.P_dot, nb.t, nb.rx_ns, nb.count = -tr["P_r_in"][k], -tr["P_r_in_dot"][k], tr["t"][k], now(), k + 1
            t0 = now()
            d._tick(payload, t0)
            t1 = now()
            d.stats.record(0, t1 - t0, d.put_ns, d.control_ns)
            times[k] = t1 - t0
        gc.unfreeze()
        st = d.status()
    finally:
        d.close()
    st["log_path"] = getattr(d, "log_path", None)
    return times, st


def bench_tick(scenario_path: str, n: int = 20_000) -> dict:
    scn, tr = _trace(scenario_path, n)
    m = len(tr["t"])
    res: dict = {"bench": "tick", "scenario": scn.name, "ticks": m}
    for impl in ("c", "python"):
        with tempfile.TemporaryDirectory() as tmp:
            try:
                times, st = drive_daemon(scn, tr, tmp, impl)
            except ImportError:
                continue
        loop = st["loop"]
        res[impl] = {**percentiles(times), "core_impl": impl,
                     "compute_p50_us": loop["compute_us"]["p50"], "compute_p99_us": loop["compute_us"]["p99"],
                     "control_p50_us": loop["control_us"]["p50"], "control_p99_us": loop["control_us"]["p99"],
                     "put_p50_us": loop["publish_us"]["p50"], "put_p99_us": loop["publish_us"]["p99"],
                     "recorder_drops": (st.get("logging") or {}).get("drops"),
                     "loop_delay_measured": st["loop_delay"]["measured_samples"]}
    return res


def bench_replay(scenario_path: str, seconds: float = 20.0, keep: str | None = None) -> dict:
    """Record seconds of a 10 kHz daemon log by hand, replay it from the index and from the JSON channels."""
    import service.replay as rp

    scn, tr = _trace(scenario_path, int(seconds * 10_000))
    with tempfile.TemporaryDirectory() as tmp:
        _times, st = drive_daemon(scn, tr, keep or tmp)
        log = st["log_path"]
        res: dict = {"bench": "replay", "log": log if keep else None, "ticks": len(tr["t"]),
                     "log_bytes": Path(log).stat().st_size, "recorder_drops": (st.get("logging") or {}).get("drops")}
        for name, use_index in (("index", True), ("json", False)):
            r = rp.replay(log, progress=False, use_index=use_index)
            res[name] = {"identical": r["identical"], "compared": r["compared"], "read_from": r["read_from"],
                         "wall_s": r["wall_s"], "speed_x_realtime": r["speed_x_realtime"]}
    return res
