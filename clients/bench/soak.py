"""energyctl bench soak: the realtime stack (daemon recording, plant, load) for minutes, status queries at 100 Hz.

The stack is the one ``bench realtime`` and ``demo --realtime`` run (the same settings, an 8 ms loop-delay
schedule), so that the soak measures a daemon that regulates: until 2026-12-02 it ran a clock-triggered loop with
the paper's gain, the plant diverged in the first second, and the soak measured a daemon holding every sample as
out of range. Reports the daemon's resident memory over time (growth and slope after a warm-up), the loop's
overruns, the recorder's drops, how many status queries were answered, and whether v stayed regulated (issue 3's
criteria for the run, ``clients.bench.realtime.judge``).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from clients.bench.realtime import judge, schedule_samples, within_band
from clients.live import COME_UP_S, Processes, _last_json, _toml, configs_from_scenario, wait_until
from clients.machine import StealMeter
from schemas.component import ZenohConfig
from schemas.scenario import load_scenario
from service.daemon.bus import free_tcp_port, key, open_session

EMBEDDED = Path(__file__).parent.parent / "embedded" / "demo.toml"


def rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def half_growth(t: np.ndarray, m: np.ndarray, warmup_s: float, half: int) -> float | None:
    """RSS growth (KiB) over the first (half 0) or second (1) half of the samples after the warm-up."""
    after = np.nonzero(t >= warmup_s)[0]
    if len(after) < 3:
        return None
    mid = after[len(after) // 2]
    lo, hi = (after[0], mid) if half == 0 else (mid, after[-1])
    return float(m[hi] - m[lo])


def soak_configs(endpoint: str, log_dir: Path, seconds: float, rate_hz: float, sets: list[str] | None = None,
                 delay: str = "8ms", record: bool = True, cpus: dict[str, list[int]] | None = None
                 ) -> tuple[dict, dict, dict]:
    """The soak's daemon, plant and load configs: ``bench realtime``'s stack for the embedded scenario (with
    ``sets``) at ``rate_hz`` and the ``delay`` schedule, the daemon recording to ``log_dir`` in files of a minute,
    the plant running ``seconds`` and writing no trace, the load outliving it."""
    scn = load_scenario(EMBEDDED, sets or [])
    comp, plant, load = configs_from_scenario(scn, endpoint, lockstep=False, rate_hz=rate_hz,
                                              controller_delay=schedule_samples(delay, rate_hz),
                                              out=str(log_dir / "plant.mcap"), duration_s=seconds, cpus=cpus)
    comp["log_rotate_s"] = 60.0
    if not record:
        comp.pop("log_dir", None)
    plant["out"] = None
    load["duration_s"] = seconds + 60.0  # stopped with the daemon, after the plant
    return comp, plant, load


class StatusPoller:
    """The daemon's status queried at query_hz on a thread of its own (``thread``, until ``stop``), counting the
    queries sent, answered and failed into ``counts``."""

    def __init__(self, session, query_hz: float, counts: dict[str, int]):
        self.session, self.query_hz, self.counts = session, query_hz, counts
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        queries, session, stop = self.counts, self.session, self.stop
        sel = key("energyctl", "source", "status")
        period = 1.0 / self.query_hz
        nxt = time.monotonic()
        while not stop.is_set():
            nxt += period
            queries["sent"] += 1
            try:
                ok = any(r.ok is not None for r in session.get(sel, timeout=1.0))
                queries["answered" if ok else "failed"] += 1
            except Exception:  # noqa: BLE001 - counted
                queries["failed"] += 1
            delay_s = nxt - time.monotonic()
            if delay_s > 0:
                time.sleep(delay_s)


def bench_soak(minutes: float, rate_hz: float = 10_000.0, query_hz: float = 100.0, warmup_s: float = 30.0,
               record: bool = True, cpus: dict[str, list[int]] | None = None, sets: list[str] | None = None,
               delay: str = "8ms", progress=sys.stderr) -> dict:
    """sets: scenario overrides (the CLI passes the realtime demo's, then the user's --set); delay: the loop-delay
    schedule (samples, or a time as in ``bench realtime --delays``)."""
    seconds = minutes * 60.0
    warmup_s = min(warmup_s, seconds / 3)
    tmp = Path(tempfile.mkdtemp(prefix="energyctl-soak-"))
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    comp, plant, load = soak_configs(ep, tmp, seconds, rate_hz, sets, delay, record, cpus)
    d_samples = comp["delay_samples"]
    for name, d in (("component", comp), ("plant", plant), ("load", load)):
        (tmp / f"{name}.toml").write_text(_toml(d))
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2]) + os.pathsep + env.get("PYTHONPATH", "")
    stats = tmp / "status.json"
    rss: list[tuple[float, int]] = []
    queries = {"sent": 0, "answered": 0, "failed": 0}
    steal = None
    with Processes(out_dir=tmp) as procs:
        d = procs.start("daemon", ["run", "--config", str(tmp / "component.toml"), "--stats-out", str(stats)],
                        env=env)
        procs.start("load", ["load", "--config", str(tmp / "load.toml")], env=env)
        pp = procs.start("plant", ["plant", "--config", str(tmp / "plant.toml"), "--json"], env=env)
        session = open_session(ZenohConfig(mode="peer", connect=[ep]))
        poller = StatusPoller(session, query_hz, queries)

        try:
            if not wait_until(lambda: any(r.ok is not None for r in
                                          session.liveliness().get(key("energyctl", "source", "alive"), timeout=0.5)),
                              COME_UP_S):
                raise RuntimeError(f"daemon did not come up within {COME_UP_S:g} s")
            if query_hz > 0:
                poller.thread.start()
            steal = StealMeter().start()
            t0 = time.monotonic()
            last_report = t0
            # until the plant has run its samples and said how it went (its metrics over the whole run take a few
            # seconds at the end); the RSS of the daemon once a second meanwhile
            while pp.poll() is None and time.monotonic() - t0 < seconds + 120.0:
                time.sleep(1.0)
                r = rss_kib(d.pid)
                el = time.monotonic() - t0
                if r is not None and el <= seconds:
                    rss.append((el, r))
                if progress is not None and time.monotonic() - last_report >= 30:
                    last_report = time.monotonic()
                    progress.write(f"\rsoak {min(el, seconds):.0f}/{seconds:.0f} s, daemon RSS {r} KiB   ")
                    progress.flush()
            steal.stop()
            poller.stop.set()
            if query_hz > 0:
                poller.thread.join(2.0)
        finally:
            session.close()
        outputs = procs.stop_all(timeout_s=10.0)
    if progress is not None:
        progress.write("\n")
    status = json.loads(stats.read_text()) if stats.exists() else {}
    t = np.array([a for a, _ in rss])
    m = np.array([b for _, b in rss], dtype=float)
    after = t >= warmup_s
    slope = float(np.polyfit(t[after], m[after], 1)[0]) if after.sum() > 2 else None
    _rc, plant_out, plant_err = outputs.get("plant", (None, "", ""))
    plant_res = _last_json(plant_out)
    rr = judge({**plant_res, "daemon": status}) if plant_res.get("metrics") else {}
    loop = status.get("loop", {})
    logging = status.get("logging") or {}
    shutil.rmtree(tmp, ignore_errors=True)  # the logs (GBs at 10 kHz), configs and the children's output
    return {"bench": "soak", "minutes": minutes, "rate_hz": rate_hz, "query_hz": query_hz, "warmup_s": warmup_s,
            "cpus": cpus,
            "rss_kib_after_warmup": float(m[after][0]) if after.any() else None,
            "rss_kib_end": float(m[-1]) if len(m) else None,
            "rss_growth_kib_after_warmup": float(m[after][-1] - m[after][0]) if after.any() else None,
            "rss_slope_kib_per_min": slope * 60 if slope is not None else None,
            # a leak grows as much in the second half as in the first; an allocator warming up (arenas, caches)
            # grows in the first and levels off
            "rss_growth_kib_first_half": half_growth(t, m, warmup_s, 0),
            "rss_growth_kib_second_half": half_growth(t, m, warmup_s, 1),
            # where it levels off: the resident size at each whole minute
            "rss_kib_by_minute": [int(m[np.searchsorted(t, 60.0 * j)]) for j in range(1, int(t[-1] // 60) + 1)]
            if len(t) else [],
            "loop_ticks": loop.get("ticks"), "overruns": loop.get("overruns"), "overrun_pct": loop.get("overrun_pct"),
            "no_new_sample": loop.get("no_new_sample"), "missing_samples": loop.get("missing_samples"),
            "meas_queue_dropped": loop.get("meas_queue_dropped"),
            "loop_exec_us": loop.get("exec_us"), "loop_publish_us": loop.get("publish_us"),
            "loop_compute_us": loop.get("compute_us"), "loop_control_us": loop.get("control_us"),
            "loop_period_us": loop.get("period_us"),
            "recorder_written": logging.get("written"), "recorder_drops": logging.get("drops"),
            "recorder_state": logging.get("state"), "queries": queries,
            "rejected": status.get("rejected"), "final_state": status.get("state"),
            # the stack's regulation over the whole run, by issue 3's criteria (None: the plant gave no result)
            "delay_samples": d_samples,
            "regulated": bool(rr) and within_band(rr),
            **{k: rr.get(k) for k in ("v_dev_after_50ms_pct", "diverged", "missed_or_late_pct",
                                      "plant_late_samples_pct")},
            # when v deviated most (s into the plant's run) and how long it spent outside the band
            **{k: plant_res.get("metrics", {}).get(k) for k in ("hold_max_dev_t_s", "hold_outside_band_s")},
            "latency_us": plant_res.get("latency_us"), "cpu": plant_res.get("cpu"),
            "plant_error": None if plant_res else plant_err[-800:],
            "host_steal_pct": steal.pct if steal is not None else None}
