"""``energyctl bench sim``: how much faster than real time the offline closed loop runs."""

from __future__ import annotations

import time


def bench_sim(scn, repeat: int) -> dict:
    """Wall time of ``repeat`` offline runs of scn (set up for 1 s simulated at 10 kHz control, 100 kHz plant)."""
    from service.sim import run

    walls = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        run(scn)
        walls.append(time.perf_counter() - t0)
    best, worst = min(walls), max(walls)
    return {"bench": "sim", "scenario": scn.name, "simulated_s": 1.0, "control_hz": 10000, "plant_hz": 100000,
            "wall_s_best": best, "wall_s_worst": worst, "realtime_ratio_best": 1.0 / best,
            "realtime_ratio_worst": 1.0 / worst}
