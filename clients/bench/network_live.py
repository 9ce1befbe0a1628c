"""energyctl bench network-live: the live network on loopback (rig, coordinator, a daemon per source as
processes): the time from each event until every bus is back within +-2 % (plug-in, a daemon killed with SIGKILL,
the coordinator lost and restarted), lockstep or realtime, and with --realtime the highest control rate at which the
two-source network regulates, with the CPU each process takes."""

from __future__ import annotations

import json
import os
import re
import signal
import tempfile
import time
from pathlib import Path

import numpy as np

from clients.netlive import LiveNetwork
from clients.peers.netrig import read_rig_log
from service.metrics import BAND_SETTLE, acceptance_checks, back_in_band, worst_back

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "clients" / "embedded" / "network-demo.toml"
TWO_SOURCE = ROOT / "scenarios" / "network" / "two-source.toml"
TRIP = ROOT / "scenarios" / "network" / "two-source-trip.toml"
TICK_S = os.sysconf("SC_CLK_TCK")


def realtime_sets(rate_hz: float, sources: list[str], delay_ms: float = 4.0) -> list[str]:
    """The realtime stack's settings at a rate, as scenarios/network/realtime.toml's at 1 kHz: delay_ms of loop delay
    in whole samples (at least 2), at most 20 V of source-voltage change per period, K = 400 /s on the observer's
    estimate without planned commands (docs/decisions/0027), hold u while open or idle in fallback (below 300 W), a
    plug-in's share and a return from a fallback over 50 ms."""
    d = max(2, round(delay_ms * 1e-3 * rate_hz))
    return [f"timing.control_rate_hz={rate_hz}", f"timing.delay_samples={d}", 'layer.open_idle="hold"',
            "layer.plug_in_ramp_s=0.05", "layer.resume_ramp_s=0.05", "layer.fallback_idle_power_W=300",
            *(f"sources.{s}.controller.{kv}" for s in sources
              for kv in (f"limits.du_dt_max_V_per_s={20 * rate_hz}", "K_per_s=400", "observer_gain=0.5",
                         "plan_next_period=false"))]


def cpu_s(pid: int) -> float:
    """CPU seconds of a process and its children (a daemon's recorder process), from /proc."""
    total = 0.0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            f = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(d.name) == pid or int(f[1]) == pid:
            total += (int(f[11]) + int(f[12])) / TICK_S
    return total


def _no_events(src: Path, work: Path, duration_s: float) -> str:
    """The scenario without its timed events and its varying load (a step only), run for duration_s."""
    text = src.read_text()
    if "[[events]]" in text:
        text = text[:text.index("[[events]]")]
    if "[loads.Pvar]" in text:
        text = text[:text.index("[loads.Pvar]")]
    text = re.sub(r"duration_s = [0-9.]+", f"duration_s = {duration_s}", text)
    p = work / f"{src.stem}-live.toml"
    p.write_text(text)
    return str(p)


def _back_after(rig, t0: float) -> float | None:
    """Seconds from t0 until every bus stays within +-2 % of nominal to the end of the run (None: never)."""
    v_nom = rig.net.nominal_v_V
    return worst_back(back_in_band(rig.t, v, t0, float(rig.t[-1]) + 1e-9, v_nom, BAND_SETTLE)
                      for v in rig.buses.values())


def _bus_min_after(rig, t0: float) -> float:
    sel = rig.t >= t0
    return min(float(v[sel].min()) for v in rig.buses.values())


def plug_in(work: Path, realtime: bool, sets: list[str]) -> dict:
    """S3's plug-in at 0.8 s; realtime runs to 2 s, time for a refused request to be asked again (0.5 s later)."""
    sets = [*sets, "timing.duration_s=2.0"] if realtime else sets
    with LiveNetwork(DEMO, work / "plug-in", sets, realtime=realtime) as live:
        live.start()
        res = live.wait_rig(900)
        live.close()
        rig = read_rig_log(str(live.logs / "rig.mcap"))
    evs = [e for e in res["metrics"]["events"] if e["kind"] == "connect"]
    if not evs:  # refused, or not closed within the run: the rig's and coordinator's logs say which
        return {"asked_at_s": 0.8, "closed_at_s": None, "diverged": res["metrics"]["diverged"],
                "logs": str(live.logs), "checks_failed": [c["check"] for c in acceptance_checks(rig) if not c["ok"]]}
    ev = evs[0]
    hs = json.loads((live.workdir / "S3.status.json").read_text())["network"]["handshake"]
    return {"asked_at_s": 0.8, "closed_at_s": ev["t_s"], "handshake_s": ev["t_s"] - 0.8,
            "requests": hs["requests"], "forecast_ms": (hs["last"] or {}).get("forecast_ms"),
            "bus_back_in_band_s": worst_back(ev["bus_back_in_band_s"].values()), "inrush_A": ev.get("inrush_A"),
            "bus_move_V": max((ev.get("bus_move_V") or {}).values(), default=None),
            "checks_failed": [c["check"] for c in acceptance_checks(rig) if not c["ok"]]}


def trip(work: Path, realtime: bool, sets: list[str], at_s: float = 0.3) -> dict:
    """S2's daemon killed with SIGKILL once the network runs at 2.4 kW."""
    scen = _no_events(TRIP, work, 0.8)
    with LiveNetwork(scen, work / "trip", sets, realtime=realtime) as live:
        live.start()
        with live.session() as z:
            live.wait_until(z, "coordinator", lambda st: st["t"] >= at_s, 120)
            live.kill("S2", signal.SIGKILL)
        res = live.wait_rig(900)
        rig = read_rig_log(str(live.logs / "rig.mcap"))
    T = 1.0 / rig.net.timing.control_rate_hz
    t_kill = (res["last_answered"]["S2"] + 1) * T  # the first sample S2 did not answer
    trips = [e for e in rig.events if e.kind == "trip"]
    t_open = trips[0].t if trips else None
    late = rig.t >= rig.t[-1] - 0.05
    carried = 100.0 * float(np.mean(rig.sources["S1"]["P"][late])) / float(
        sum(np.mean(rig.sources[s]["P"][late]) for s in rig.sources) or 1.0)
    return {"killed_at_s": t_kill, "breaker_open_after_s": None if t_open is None else t_open - t_kill,
            "bus_back_in_band_s": _back_after(rig, t_kill), "bus_min_V": _bus_min_after(rig, t_kill),
            "S1_carries_pct": carried, "diverged": res["metrics"]["diverged"]}


def coordinator_loss(work: Path, realtime: bool, sets: list[str]) -> dict:
    """The coordinator killed with SIGKILL at 2.4 kW, restarted later: the sources fall back, then resume. Realtime
    runs longer: a coordinator takes a second or two to start (imports, asking the daemons)."""
    at_s, back_at_s, duration = (1.0, 2.0, 4.0) if realtime else (0.3, 0.5, 0.8)
    scen = _no_events(TRIP, work, duration)
    with LiveNetwork(scen, work / "coordinator", sets, realtime=realtime) as live:
        live.start()
        with live.session() as z:
            live.wait_until(z, "coordinator", lambda st: st["t"] >= at_s, 120)
            live.kill("coordinator", signal.SIGKILL)
            st = live.wait_until(z, "S1", lambda st: st["network"]["allocation"]["stale"], 60)
            t_stale = st["last_sample"]["t"]
            while live.query(z, "S1")["last_sample"]["t"] < back_at_s:
                time.sleep(0.01)
            live.start_coordinator()
            co = live.wait_until(z, "coordinator", lambda st: st["seq"] > 0, 60)
            st = live.wait_until(z, "S1", lambda st: not st["network"]["allocation"]["stale"], 60)
            t_fresh = st["last_sample"]["t"]
        res = live.wait_rig(900)
        live.close()
        rig = read_rig_log(str(live.logs / "rig.mcap"))
        from service.logio.reader import messages

        allocs = [d["seq"] for p in live.daemon_logs("S1") for d in messages(p, "S1/alloc")]
    T = 1.0 / rig.net.timing.control_rate_hz
    seqs = sorted(allocs)
    gap = max(range(1, len(seqs)), key=lambda k: seqs[k] - seqs[k - 1])
    t_lost, t_back = (seqs[gap - 1] + 1) * T, seqs[gap] * T
    v_nom = rig.net.nominal_v_V
    sel = (rig.t >= t_lost) & (rig.t < t_back)
    dev = max(float(np.max(np.abs(v[sel] - v_nom))) for v in rig.buses.values()) / v_nom * 100 if sel.any() else None
    return {"lost_at_s": t_lost, "stale_seen_at_s": t_stale, "resumed_at_s": t_back, "fresh_seen_at_s": t_fresh,
            "worst_bus_dev_without_pct": dev, "bus_back_in_band_after_loss_s": _back_after(rig, t_lost),
            "bus_back_in_band_after_resume_s": _back_after(rig, t_back), "resumed_v_ref": co["resumed_v_ref"],
            "diverged": res["metrics"]["diverged"]}


def rate_run(work: Path, rate_hz: float, seconds: float) -> dict:
    """two-source live in realtime at one rate: regulation (the acceptance checks of its load step) and CPU per
    process over the sampling."""
    scen = _no_events(TWO_SOURCE, work, seconds)
    sets = realtime_sets(rate_hz, ["S1", "S2"])
    with LiveNetwork(scen, work / f"rate-{rate_hz:g}", sets, realtime=True) as live:
        live.start()
        try:
            with live.session() as z:
                live.wait_until(z, "coordinator", lambda st: st["seq"] > 0, 120)
        except RuntimeError:  # the rig ended first (it diverged within moments): its result says so
            pass
        c0 = {n: cpu_s(p.pid) for n, p in live.by_name.items()}
        t0 = time.perf_counter()
        c1, t1 = dict(c0), t0
        rig_p = live.by_name["rig"]
        while rig_p.poll() is None:  # the others' CPU just before the rig ends
            c1 = {n: cpu_s(p.pid) for n, p in live.by_name.items() if n != "rig"}
            t1 = time.perf_counter()
            time.sleep(0.2)
        res = live.wait_rig(600)
        live.close()
        rig = read_rig_log(str(live.logs / "rig.mcap"))
        statuses = {s: json.loads((live.workdir / f"{s}.status.json").read_text())
                    for s in ("S1", "S2")}
    wall = max(1e-9, t1 - t0)
    cpu = {n: 100.0 * (c1[n] - c0[n]) / wall for n in c1}
    cpu["rig"] = res["cpu"]["rig_pct"]
    checks = acceptance_checks(rig)
    from schemas.network import load_network
    from service.network.netsim import run_network

    offline = acceptance_checks(run_network(load_network(scen, sets)))  # the same rate and settings, offline
    c = res["counters"]
    return {"rate_hz": rate_hz, "delay_samples": int(sets[1].split("=")[1]),
            "regulates": all(ch["ok"] for ch in checks), "failed": [ch["check"] for ch in checks if not ch["ok"]],
            "offline_regulates": all(ch["ok"] for ch in offline),
            "bus_ss_dev_pct": next((ch["value"] for ch in checks if "steady deviation" in ch["check"]), None),
            "step_bus_back_s": next((ch["value"] for ch in checks if "buses back" in ch["check"]), None),
            "sharing_pp": next((ch["value"] for ch in checks if "sharing" in ch["check"]), None),
            "samples_per_s": res["rate_achieved_hz"],
            "periods_without_command_pct": 100.0 * sum(c.get(f"{s}_stale_periods", 0) + c.get(f"{s}_planned_periods", 0)
                                                       for s in ("S1", "S2")) / (2 * max(1, res["samples"])),
            "late_commands": sum(c.get(f"{s}_late", 0) for s in ("S1", "S2")),
            "command_age": res.get("command_age"),
            "daemon_missing_samples": {s: st["loop"]["missing_samples"] for s, st in statuses.items()},
            "cpu_pct": {n: round(v, 1) for n, v in cpu.items()}}


def bench_network_live(realtime: bool, rates: list[float], seconds: float, progress) -> dict:
    out: dict = {"pacing": "realtime" if realtime else "lockstep", "machine_cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="energyctl-netlive-") as tmp:
        work = Path(tmp)
        sets_demo = realtime_sets(1000.0, ["S1", "S2", "S3"]) if realtime else []
        sets_two = realtime_sets(1000.0, ["S1", "S2"]) if realtime else []
        out["rate_hz"] = 1000.0 if realtime else 10000.0
        for name, fn, sets in (("plug_in", plug_in, sets_demo), ("trip_sigkill", trip, sets_two),
                               ("coordinator_loss", coordinator_loss, sets_two)):
            progress(f"{name} ...")
            out[name] = fn(work, realtime, sets)
            progress(f"{name}: {out[name]}")
        if realtime:
            out["rates"] = []
            out["events_note"] = "plug-in, trip and coordinator loss at 1 kHz with realtime_sets"
            for r in rates:
                progress(f"rate {r:g} Hz ...")
                out["rates"].append(rate_run(work, r, seconds))
                progress(f"rate {r:g} Hz: {out['rates'][-1]}")
            ok = [x["rate_hz"] for x in out["rates"] if x["regulates"]]
            out["highest_regulating_rate_hz"] = max(ok, default=None)
    return out
