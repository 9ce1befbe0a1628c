"""energyctl bench tick: the daemon's whole tick (decode, checks, core, publish, record) without the network.

An opened daemon (loopback Zenoh session, no peers, recorder process writing to a temporary directory)
is handed the measurements of a closed-loop simulator run one by one through the same method the loop
calls, with the loop's own statistics update; nothing arrives over a socket and nothing waits, so this is
what our code costs per tick, apart from the wake-ups and cross-process scheduling that `bench latency`
also sees. The compiled and the Python core are measured in the same run.
"""

from __future__ import annotations

import gc
import tempfile
import time

from schemas.codec import MEAS


def bench_tick(scenario_path: str, n: int = 20_000) -> dict:
    from schemas.component import ComponentConfig, config_from_dict
    from schemas.scenario import load_scenario
    from service.bus import free_tcp_port
    from service.daemon import Daemon
    from service.sim import run

    from .live import configs_from_scenario

    scn = load_scenario(scenario_path, [f"timing.duration_s={n / 10_000.0}"])
    tr = {k: v.tolist() for k, v in run(scn).trace.items()}
    m = len(tr["t"])
    payloads = [MEAS.encode(k, tr["t"][k], tr["i_meas"][k], tr["v_meas"][k], tr["u_meas"][k], tr["i_load_meas"][k])
                for k in range(m)]
    res: dict = {"bench": "tick", "scenario": scn.name, "ticks": m}
    for impl in ("c", "python"):
        with tempfile.TemporaryDirectory() as tmp:
            comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False,
                                                 rate_hz=scn.timing.control_rate_hz)
            comp["neighbour_stale_s"] = 1e9
            comp["log_dir"] = tmp
            comp["delay_samples"] = scn.timing.delay_samples
            d = Daemon(config_from_dict(ComponentConfig, comp))
            try:
                d.core = _core(d, impl)
            except ImportError:
                continue
            d.open()
            nb = d.neighbours[0]
            try:
                times = [0] * m
                now = time.monotonic_ns
                gc.collect()
                gc.freeze()
                for k in range(m):
                    nb.P, nb.P_dot, nb.rx_ns, nb.count = -tr["P_r_in"][k], -tr["P_r_in_dot"][k], now(), k + 1
                    t0 = now()
                    d._tick(payloads[k], t0)
                    t1 = now()
                    d.stats.record(0, t1 - t0)
                    times[k] = t1 - t0
                gc.unfreeze()
                st = d.status()
            finally:
                d.close()
            times.sort()
            res[impl] = {"p50_us": times[m // 2] / 1e3, "p99_us": times[int(m * 0.99)] / 1e3,
                         "max_us": times[-1] / 1e3, "core_impl": d.core.impl,
                         "recorder_drops": (st.get("logging") or {}).get("drops"),
                         "loop_delay_measured": st["loop_delay"]["measured_samples"]}
    return res


def _core(d, impl: str):
    from service.core import make_core

    c = d.cfg
    return make_core(c.controller, c.model, d.period_s, c.delay_samples, impl)
