"""``energyctl bench core``: the core's per-step cost, compiled and Python."""

from __future__ import annotations

import time


def bench_core(scn, repeat: int) -> dict:
    """Per-step cost of the core's step on a recorded closed-loop input stream: the compiled twin and the
    Python reference in the same run (interleaved passes, so machine noise hits both alike)."""
    import gc

    from service.core import make_core
    from service.core.types import Incoming, Sample
    from service.sim import run

    tr = {k: v.tolist() for k, v in run(scn).trace.items()}  # Python floats, as the daemon sees them
    T = 1.0 / scn.timing.control_rate_hz
    n = len(tr["t"])
    samples = [Sample(k, tr["t"][k], tr["i_meas"][k], tr["v_meas"][k], tr["u_meas"][k], tr["i_load_meas"][k])
               for k in range(n)]
    incs = [Incoming(tr["P_r_in"][k], tr["P_r_in_dot"][k]) for k in range(n)]
    impls = ["python"]
    try:
        make_core(scn.controller, scn.model, T, scn.timing.delay_samples, "c")
        impls.insert(0, "c")
    except ImportError:
        pass
    times: dict[str, list[int]] = {m: [] for m in impls}
    pc = time.perf_counter_ns
    gc.freeze()
    gc.disable()
    try:
        for _ in range(max(1, repeat)):
            for m in impls:
                core = make_core(scn.controller, scn.model, T, scn.timing.delay_samples, m)
                step, tm = core.step, times[m]
                for k in range(n):
                    t0 = pc()
                    step(samples[k], incs[k])
                    tm.append(pc() - t0)
    finally:
        gc.enable()
        gc.unfreeze()
    res: dict = {"bench": "core", "scenario": scn.name, "controller": scn.controller.kind,
                 "mapping": scn.controller.mapping, "delay_samples": scn.timing.delay_samples, "steps": n,
                 "passes": max(1, repeat)}
    from clients.bench.latency import percentiles

    for m, tm in times.items():
        res[m] = {"mean_us": sum(tm) / len(tm) / 1e3, **percentiles(tm)}
    if "c" in res:
        res["python_over_c_p50"] = res["python"]["p50_us"] / res["c"]["p50_us"]
    return res
