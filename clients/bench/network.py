"""``energyctl bench network``: what a network costs offline, per source, at 2, 4, 8 and 16 sources.

The networks are radial feeders made by ``radial``: buses in a chain, four sources per bus, each behind its own
line, a constant-power load at every bus (300 W per source, 2x from 0.3 s); the shipped
``scenarios/network/radial-16.toml`` is ``radial(16)``.
"""

from __future__ import annotations

import time


def radial(n_sources: int, duration_s: float = 1.0) -> dict:
    """A radial network scenario (a dict for schemas.network.network_from_dict): ceil(n / 4) buses in a chain
    (0.05 ohm, 50 uH between neighbours, 4.7 mF each), n sources spread over them round robin, each behind a line
    of 0.10-0.20 ohm (1 mH per ohm), equal shares, +-10 % model errors of alternating signs, 300 W of load per
    source at the buses (doubled at 0.3 s), 10 kHz control, 2 samples of delay, noise 0.05 V and A."""
    n_bus = max(1, -(-n_sources // 4))
    buses = {f"B{b + 1}": {"C_F": 4.7e-3} for b in range(n_bus)}
    lines: dict[str, dict] = {}
    for b in range(1, n_bus):
        lines[f"F{b}"] = {"a": f"B{b}", "b": f"B{b + 1}", "R_ohm": 0.05, "L_H": 50e-6}
    sources: dict[str, dict] = {}
    per_bus = [0] * n_bus
    for j in range(n_sources):
        name, bus = f"S{j + 1}", j % n_bus
        sign = 1.0 if j % 2 == 0 else -1.0
        sources[name] = {"R_ohm": 0.01, "L_H": 1.12e-3, "C_F": 6.8e-3,
                         "model_error": {"R": 0.1 * sign, "L": -0.1 * sign, "C": 0.1 * sign},
                         "controller": {"K_per_s": 1000.0}}
        R = 0.10 + 0.10 * (j % 3) / 2
        lines[f"L{j + 1}"] = {"a": name, "b": f"B{bus + 1}", "R_ohm": R, "L_H": R * 1e-3}
        per_bus[bus] += 1
    loads = {f"P{b + 1}": {"bus": f"B{b + 1}", "kind": "steps", "value": 300.0 * k, "steps": [[0.3, 600.0 * k]]}
             for b, k in enumerate(per_bus)}
    return {"kind": "network", "name": f"radial-{n_sources}",
            "description": f"{n_sources} sources on a radial feeder of {n_bus} buses; 300 W per source, doubled "
                           "at 0.3 s",
            "timing": {"control_rate_hz": 10000.0, "plant_step_s": 1e-5, "delay_samples": 2,
                       "duration_s": duration_s},
            "sensor": {"noise_v_V": 0.05, "noise_i_A": 0.05},
            "layer": {"mode": "live-sum", "window_s": 0.05, "v_ref_gain": 0.8},
            "sources": sources, "buses": buses, "lines": lines, "loads": loads}


def bench_network(sizes: tuple[int, ...] = (2, 4, 8, 16), seconds: float = 0.2, repeat: int = 2,
                  progress=None) -> dict:
    """Best wall time of ``repeat`` offline runs of ``seconds`` of radial(n) for each n: the cost per source per
    control tick (us), which should stay flat as n grows (linear cost), and the real-time ratio."""
    from schemas.network import network_from_dict
    from service.network.netsim import run_network

    rows = {}
    for n in sizes:
        net = network_from_dict(radial(n, seconds))
        best = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            res = run_network(net)
            best = min(best, time.perf_counter() - t0)
        ticks = len(res.t)
        rows[n] = {"wall_s": best, "realtime_ratio": seconds / best, "us_per_source_tick": best / ticks / n * 1e6,
                   "diverged": res.metrics["diverged"]}
        if progress:
            progress(f"{n} sources: {best:.2f} s for {seconds:g} s, {rows[n]['us_per_source_tick']:.1f} us per "
                     "source per tick")
    first, last = rows[sizes[0]], rows[sizes[-1]]
    return {"bench": "network", "simulated_s": seconds, "sizes": rows,
            "cost_growth_per_source": last["us_per_source_tick"] / first["us_per_source_tick"]}
