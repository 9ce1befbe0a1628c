"""``energyctl bench network-scale``: how a network's cost grows with its number of sources.

* offline: radial(n) (clients.bench.network) at 4 ... 64 sources, the best of ``repeat`` runs: the cost per source
  per control tick, flat when the total is linear in n;
* live: radial(n) at 4 ... 32 sources in lockstep across ``hosts`` network-namespace hosts through the secure
  profile's routers (clients.nethosts.run_hosted, as ``energyctl demo --network --hosts``): the wall time per
  simulated second, each process's CPU time from /proc between the rig's first sample and its last (per daemon per
  sample: flat when linear in n; split into the daemons' Python threads and Zenoh's runtime threads, and the share
  of it their idle rate makes, which grows with the wall time of a sample), and whether the run equals
  ``energyctl sim`` of the same scenario.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

OFFLINE_SIZES = (4, 8, 16, 32, 64)
LIVE_SIZES = (4, 8, 16, 32)


def grid_work_us(n: int, number: int = 20000) -> float:
    """A daemon's own per-sample work on a grid sample of n sources, in this one process (us): decoding it
    (schemas.codec.GRID) and forming the shares from it (service.network.layer.Sharing.step): the part of its cost
    that grows with n by itself, without other processes around."""
    import timeit

    from schemas.codec import GRID
    from service.network.layer import Sharing

    v, i_out, on = [400.0 + j for j in range(n)], [1.0 + 0.01 * j for j in range(n)], [True] * n
    payload = GRID.encode(1, 1e-4, v, i_out, on, [400.0], [100.0 * n])
    sharing = Sharing([1.0] * n, 1e-4, "live-sum", 10.0, 0.0, on)
    k = iter(range(1, 10 ** 9))

    def one() -> None:
        g = GRID.decode(payload)
        sharing.step(next(k), [g[2][j] * g[3][j] if g[4][j] else 0.0 for j in range(n)], g[4])

    return min(timeit.repeat(one, number=number, repeat=3)) / number * 1e6


def bench_network_scale(offline_sizes=OFFLINE_SIZES, live_sizes=LIVE_SIZES, seconds: float = 0.1,
                        offline_seconds: float = 0.2, repeat: int = 2, hosts: int = 4, work: str | None = None,
                        progress=None) -> dict:
    from clients.bench.network import bench_network
    from clients.nethosts import run_hosted, write_radial
    from clients.netns import unavailable_reason
    from clients.secure import LOCKSTEP_WAIT_BEFORE_DROP_US

    say = progress or (lambda m: None)
    out: dict = {"bench": "network-scale"}
    if offline_sizes:
        off = bench_network(tuple(offline_sizes), offline_seconds, repeat, progress=lambda m: say(f"offline {m}"))
        out["offline"] = {"simulated_s": offline_seconds,
                          "us_per_source_tick": {n: round(r["us_per_source_tick"], 2) for n, r in off["sizes"].items()},
                          "cost_growth_per_source": round(off["cost_growth_per_source"], 3)}
    if live_sizes:
        reason = unavailable_reason()
        if reason is not None:
            out["live"] = {"skipped": reason}
            return out
        base = Path(work or tempfile.mkdtemp(prefix="energyctl-scale-"))
        rows = {}
        for n in live_sizes:
            scn = write_radial(base / f"radial-{n}.toml", n, seconds)
            r = run_hosted(scn, base / f"run-{n}", hosts, progress=lambda m, n=n: say(f"live {n}: {m}"),
                           wait_before_drop_us=LOCKSTEP_WAIT_BEFORE_DROP_US, idle_probe_s=2.0)
            cpu = r["cpu_s"]
            rows[n] = {"ok": r["ok"], "why": r["why"], "identical_to_sim": r["identity"]["equal"],
                       "samples": r["rig"]["samples"], "wall_per_sim_s": r["wall_per_sim_s"],
                       "cpu_per_daemon_per_sample_us": r["cpu_per_daemon_per_sample_us"],
                       "cpu_per_daemon_per_sample_by_thread_us": r["cpu_per_daemon_per_sample_by_thread_us"],
                       "switches_per_daemon_per_sample": r["switches_per_daemon_per_sample"],
                       "grid_work_in_one_process_us": round(grid_work_us(n), 1),
                       "cpu_total_per_sample_us": r["cpu_total_per_sample_us"],
                       "cpu_routers_per_sample_us": round(sum(c for k, c in cpu.items() if k.startswith("router-"))
                                                          / r["rig"]["samples"] * 1e6, 1),
                       "cpu_coordinator_per_sample_us": round(cpu.get("coordinator", 0.0) / r["rig"]["samples"] * 1e6,
                                                              1),
                       "idle_cpu_per_daemon_pct": r.get("idle_cpu_per_daemon_pct"),
                       # what that idle rate (Zenoh's keep-alives, the daemon's timers) adds to each sample: it
                       # grows with the wall time a sample takes, not with the work of a sample
                       "idle_cpu_per_daemon_per_sample_us": None if r.get("idle_cpu_per_daemon_pct") is None else
                       round(r["idle_cpu_per_daemon_pct"] / 100.0 * r["wall_per_sim_s"] / r["rig"]["samples"]
                             * seconds * 1e6, 1),
                       "rig_samples_per_s": round(r["rig"]["rate_achieved_hz"], 1),
                       "timeouts": r["rig"]["counters"]["timeouts"], "startup_s": r["startup_s"],
                       "rss_mb": r["rss_mb"], "run_wall_s": r["wall_s"]}
            say(f"live {n}: {rows[n]}")
        first, last = rows[live_sizes[0]], rows[live_sizes[-1]]
        out["live"] = {"hosts": hosts, "simulated_s": seconds, "sizes": rows, "work": str(base),
                       "cpu_per_daemon_growth": round(last["cpu_per_daemon_per_sample_us"]
                                                      / first["cpu_per_daemon_per_sample_us"], 3),
                       "wall_per_sim_s_per_source_growth": round((last["wall_per_sim_s"] / live_sizes[-1])
                                                                 / (first["wall_per_sim_s"] / live_sizes[0]), 3)}
    return out
