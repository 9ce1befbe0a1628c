"""The network live on loopback: the rig, the coordinator and one daemon per source as separate processes.

Lockstep over Zenoh must give the offline run's bits (every source's v, i, applied du/dt and the commands its daemon
sent), the plug-in handshake must close the breaker at the sample the offline layer does, each daemon's log must
replay identical and the coordinator's log its allocations; a daemon killed with SIGKILL is tripped and its share
taken over; a coordinator that goes away leaves the sources on their own terminals, and one that comes back resumes
from what they report. Every process is stopped at the end, also on failure (LiveNetwork.close)."""

from __future__ import annotations

import re
import signal

import numpy as np
import pytest

from clients.netlive import LiveNetwork
from clients.peers.netrig import read_rig_log
from schemas.network import load_network
from service.logio.reader import messages
from service.metrics import acceptance_checks
from service.network.netsim import run_network
from tests.conftest import ROOT, SCENARIOS

DEMO = ROOT / "clients" / "embedded" / "network-demo.toml"


def shortened(tmp_path, src, **times) -> str:
    """A copy of a scenario with its times moved: duration, the load step, and events by index (t_s)."""
    text = src.read_text()
    if "duration_s" in times:
        text = re.sub(r"duration_s = [0-9.]+", f"duration_s = {times['duration_s']}", text)
    if "step_s" in times:
        text = re.sub(r"steps = \[\[[0-9.]+,", f"steps = [[{times['step_s']},", text)
    new = iter(times.get("events", []))
    text = re.sub(r"(\[\[events\]\]\nt_s = )[0-9.]+", lambda m: f"{m.group(1)}{next(new)}", text)
    p = tmp_path / src.name
    p.write_text(text)
    return str(p)


def test_lockstep_over_zenoh_equals_the_offline_run(tmp_path):
    """Load step, trip and plug-in in 0.13 s: the rig's trace and every daemon's commands against run_network."""
    scen = shortened(tmp_path, DEMO, duration_s=0.13, step_s=0.03, events=[0.06, 0.09])
    net = load_network(scen)
    off = run_network(net)
    assert [(e.kind, e.target, e.accepted) for e in off.events] == [("load", "P", True), ("trip", "S2", True),
                                                                      ("connect", "S3", True)]
    with LiveNetwork(scen, tmp_path / "run") as live:
        live.start()
        res = live.wait_rig(180)
        live.close()
        assert res["counters"]["timeouts"] == 0
        rig = read_rig_log(str(live.logs / "rig.mcap"))
        assert len(rig.t) == len(off.t) == 1300
        for s in net.sources:
            for k in ("v", "i", "u"):
                assert float(np.max(np.abs(rig.sources[s][k] - off.sources[s][k]))) <= 1e-9, (s, k)
            [log] = live.daemon_logs(s)
            cmd = {d["seq"]: d["du_dt"] for d in messages(log, f"{s}/cmd")}
            sent = np.array([cmd[k] for k in range(len(off.t))])
            assert float(np.max(np.abs(sent - off.sources[s]["cmd_du"]))) <= 1e-9, s
        # the live events: the scenario's trip (the rig's) and the plug-in the coordinator granted, at the same ticks
        live_ev = sorted((round(e.t, 6), e.kind, e.target) for e in rig.events)
        assert live_ev == sorted((round(e.t, 6), e.kind, e.target) for e in off.events)
        # each daemon's log replays identical; the coordinator's its allocations and its verdict
        from service.network.layer_replay import replay_coordinator
        from service.replay import replay

        for s in net.sources:
            assert replay([str(p) for p in live.daemon_logs(s)], progress=False)["identical"], s
        rc = replay_coordinator(str(live.logs / "coordinator.mcap"))
        assert rc["identical"] and rc["verdicts"] == 1 and rc["offers"] >= 1 and rc["samples"] == 1300, rc
        # the plug-in was judged on the Z^{r,out} S3 forecast and announced itself
        import json

        co = json.loads((tmp_path / "run" / "coordinator.out").read_text().splitlines()[-1])
        assert [(v["source"], v.get("announced"), v["accepted"]) for v in co["verdicts"]] == [("S3", True, True)]
        # the acceptance checks from the rig's log agree with those of the offline run
        assert [c["ok"] for c in acceptance_checks(rig)] == [c["ok"] for c in acceptance_checks(off)]


def test_a_refused_plug_in_stays_open_and_says_why(tmp_path):
    """S3 with K_P = 10 /s cannot follow its share: the coordinator refuses, the breaker stays open, the daemon says
    why, and nothing moves (as offline)."""
    scen = shortened(tmp_path, SCENARIOS / "network" / "plug-in.toml", duration_s=0.08, step_s=0.02, events=[0.05])
    sets = ["sources.S3.controller.nested_K_P_per_s=10.0"]
    off = run_network(load_network(scen, sets))
    assert [e.accepted for e in off.events if e.kind == "connect"] == [False]
    with LiveNetwork(scen, tmp_path / "run", sets=sets) as live:
        live.start()
        live.wait_rig(120)
        rig = read_rig_log(str(live.logs / "rig.mcap"))
        assert not [e for e in rig.events if e.kind == "connect"]
        for s in ("S1", "S2", "S3"):
            assert float(np.max(np.abs(rig.sources[s]["v"] - off.sources[s]["v"]))) <= 1e-9
        live.close()
        status = (live.workdir / "S3.status.json").read_text()
        import json

        hs = json.loads(status)["network"]["handshake"]
        assert hs["requests"] >= 1 and hs["last"]["accepted"] is False
        assert hs["last"]["reason"] == next(e.reason for e in off.events if e.kind == "connect")
        assert json.loads(status)["network"]["breaker"] == "open"


@pytest.fixture
def trip_scenario(tmp_path):
    """two-source at 2.4 kW with no timed event (the trip comes from a killed daemon), 0.6 s."""
    text = (SCENARIOS / "network" / "two-source-trip.toml").read_text()
    text = text[:text.index("[[events]]")]
    text = re.sub(r"duration_s = [0-9.]+", "duration_s = 0.6", text)
    p = tmp_path / "trip-live.toml"
    p.write_text(text)
    return str(p)


def test_a_daemon_killed_is_tripped_and_its_share_taken_over(tmp_path, trip_scenario):
    with LiveNetwork(trip_scenario, tmp_path / "run") as live:
        live.start()
        with live.session() as z:
            live.wait_until(z, "coordinator", lambda st: st["t"] >= 0.2, 60)
            live.kill("S2", signal.SIGKILL)
            st = live.wait_until(z, "coordinator", lambda st: not st["sources"]["S2"]["connected"], 30)
        assert st["trips"] and st["trips"][0]["source"] == "S2" and st["sources"]["S1"]["share_now"] == 1.0
        res = live.wait_rig(120)
        rig = read_rig_log(str(live.logs / "rig.mcap"))
    assert not res["metrics"]["diverged"]
    [trip] = [e for e in res["metrics"]["events"] if e["kind"] == "trip"]
    assert trip["target"] == "S2" and 0.2 <= trip["t_s"] < 0.6
    assert trip["bus_back_in_band_s"]["bus"] is not None and trip["bus_back_in_band_s"]["bus"] <= 0.2, trip
    late = rig.t >= rig.t[-1] - 0.05
    assert abs(float(np.mean(rig.sources["S2"]["P"][late]))) < 0.05 * float(np.mean(rig.sources["S1"]["P"][late]))


def test_a_restarted_source_asks_to_connect_by_itself_and_status_says_why(tmp_path, trip_scenario):
    """A source's daemon killed (tripped) and started again as docs/network.md shows, without --connect-at: it idled
    with its breaker open and nothing said so. Now the coordinator's status says why S2 is not connected, and the
    restarted daemon, whose first allocation shows its breaker open although the scenario has it connected from the
    start, asks to connect by itself and comes back through the handshake."""
    with LiveNetwork(trip_scenario, tmp_path / "run", sets=["timing.duration_s=3.0"]) as live:
        live.start()
        with live.session() as z:
            live.wait_until(z, "coordinator", lambda st: st["t"] >= 0.1, 60)
            live.kill("S2", signal.SIGKILL)
            st = live.wait_until(z, "coordinator", lambda st: not st["sources"]["S2"]["connected"], 30)
            assert "tripped" in st["sources"]["S2"]["not_connected"], st["sources"]["S2"]
            assert st["sources"]["S1"]["not_connected"] is None
            t_restart = st["t"]
            live.start_source("S2")  # no --connect-at
            st = live.wait_until(z, "coordinator", lambda st: st["sources"]["S2"]["connected"], 60)
            assert any(v["source"] == "S2" and v["accepted"] and v["t"] >= t_restart for v in st["verdicts"]), st
            s2 = live.wait_until(z, "S2", lambda st: st["network"]["breaker"] == "closed", 30)
            assert s2["network"]["handshake"]["requests"] >= 1 and s2["network"]["not_connected"] is None
        res = live.wait_rig(120)
    assert not res["metrics"]["diverged"]
    assert [e["target"] for e in res["metrics"]["events"] if e["kind"] == "connect"] == ["S2"], res["metrics"]["events"]


def test_the_sources_fall_back_without_the_coordinator_and_it_resumes(tmp_path, trip_scenario):
    with LiveNetwork(trip_scenario, tmp_path / "run") as live:
        live.start()
        with live.session() as z:
            live.wait_until(z, "coordinator", lambda st: st["t"] >= 0.15, 60)
            live.kill("coordinator", signal.SIGKILL)
            # the sources: their allocation goes stale within 10 ms of sample time, and they follow their terminals
            for s in ("S1", "S2"):
                st = live.wait_until(z, s, lambda st: st["network"]["allocation"]["stale"], 30)
                assert st["reference"] == "last allocation (fallback)"
            v_refs = {s: live.query(z, s)["network"]["v_ref_V"] for s in ("S1", "S2")}
            live.start_coordinator()
            co = live.wait_until(z, "coordinator", lambda st: st["seq"] > 0, 30)
            assert co["resumed_v_ref"] == v_refs  # it resumed from what the daemons reported
            for s in ("S1", "S2"):
                live.wait_until(z, s, lambda st: not st["network"]["allocation"]["stale"], 30)
        res = live.wait_rig(120)
    assert not res["metrics"]["diverged"]
    fallback = [(tmp_path / "run" / f"{s}.status.json") for s in ("S1", "S2")]
    import json

    assert all(json.loads(p.read_text())["network"]["fallback_ticks"] > 0 for p in fallback)


def test_demo_network_reports_each_check_live_and_from_its_logs(tmp_path):
    """energyctl demo --network on a shortened demo: every check printed with its live value and the value recomputed
    from the logs (the same), lockstep equal to energyctl sim, and the exit code saying whether every check held."""
    import subprocess
    import sys

    scen = shortened(tmp_path, DEMO, duration_s=0.4, step_s=0.1, events=[0.2, 0.3])
    expected = acceptance_checks(run_network(load_network(scen)))
    p = subprocess.run([sys.executable, "-m", "clients.cli", "demo", "--network", scen, "--logs", str(tmp_path / "l")],
                       capture_output=True, text=True, timeout=300)
    out = p.stdout
    assert "the checks recomputed from the rig's log agree with the live run's" in out, out + p.stderr
    assert "lockstep over Zenoh equals energyctl sim of the same scenario" in out
    rows = [ln for ln in out.splitlines() if ln.rstrip().endswith((" ok", "FAIL"))]
    assert len(rows) == len(expected)
    for ln, ch in zip(rows, expected, strict=True):
        assert ln.startswith(ch["check"]) and ln.rstrip().endswith("ok" if ch["ok"] else "FAIL"), (ln, ch)
    assert p.returncode == (0 if all(ch["ok"] for ch in expected) else 1)
    logs = list((tmp_path / "l").glob("network-demo-*/logs/*.mcap"))
    assert {f.name.split("-")[0] for f in logs} >= {"rig.mcap", "coordinator.mcap", "S1", "S2", "S3"}


def test_bad_input_is_refused_by_name_and_the_network_goes_on(tmp_path, trip_scenario):  # noqa: PLR0915
    """Bad connect and breaker queries, a forged grid sample from the future and an allocation with an impossible
    v_ref: each refused with the field named and counted; no loop ends, nothing reaches a converter, and a source
    whose daemon is gone is refused a connect."""
    import json as _json

    from schemas.codec import ALLOC, GRID
    from service.daemon.bus import request

    with LiveNetwork(trip_scenario, tmp_path / "run", sets=["timing.duration_s=1.0"]) as live:
        live.start()
        with live.session() as z:
            st = live.wait_until(z, "coordinator", lambda st: st["t"] >= 0.05, 60)
            ask = lambda k, body, raw=None: request(z, f"energyctl/{k}", body, 5.0)  # noqa: E731
            ok, r = ask("coordinator/connect", {"source": "S1", "at_seq": "x"})
            assert not ok and "at_seq" in r["error"]
            for z_out, field in (({"P": [0.0, 1.0], "Qdot": [1.0, 0.0]}, "Z_out.Qdot"), ("big", "Z_out:"),
                                 ({"P": [0.0, True], "Qdot": [0.0, 1.0]}, "Z_out.P")):  # an announced Z^{r,out}
                ok, r = ask("coordinator/connect", {"source": "S2", "controller": {}, "Z_out": z_out})
                assert not ok and field in r["error"], (z_out, r)
            ok, r = request(z, "energyctl/coordinator/connect", None, 5.0)  # no payload: no source named
            assert not ok and "source" in r["error"]
            z.get("energyctl/coordinator/connect", payload="[" * 100_000, timeout=5.0)  # deep JSON: answered
            ok, r = ask("rig/breaker", {"target": ["S1"], "closed": False})
            assert not ok and "target" in r["error"]
            ok, r = ask("rig/breaker", {"target": "S1", "closed": "yes"})
            assert not ok and "closed" in r["error"]
            # a grid sample from far ahead, and one whose t is not seq x T: refused; the allocations go on
            seq = st["seq"]
            pub = z.declare_publisher("energyctl/rig/grid")
            pub.put(GRID.encode(seq + 100_000, (seq + 100_000) * 1e-4, [80.0, 80.0], [1.0, 1.0], [True, True], [80.0],
                                [100.0]))
            pub.put(GRID.encode(seq + 5, 123.0, [80.0, 80.0], [1.0, 1.0], [True, True], [80.0], [100.0]))
            # an allocation with v_ref 5 V to S2 (sent until one lands between two of the coordinator's): refused by
            # name, counted
            bad = z.declare_publisher("energyctl/S2/alloc")

            def refused(st) -> bool:
                bad.put(ALLOC.encode(seq, seq * 1e-4, -500.0, 0.0, 5.0, True, 0, False, 0.0, 0.0, 0.0, 0.0))
                return any(k.startswith("alloc.v_ref_V") for k in st["rejected"])

            s2 = live.wait_until(z, "S2", refused, 30)
            assert s2["network"]["v_ref_V"] > 70.0
            co = live.wait_until(z, "coordinator", lambda st: st["counters"]["rejected"] >= 6, 30)
            assert co["t"] > st["t"]  # still allocating
            # S2's daemon gone: tripped, and a connect in its name is refused
            live.kill("S2", signal.SIGKILL)
            live.wait_until(z, "coordinator", lambda st: not st["sources"]["S2"]["connected"], 30)
            ok, r = ask("coordinator/connect", {"source": "S2", "controller": {"K_per_s": 1000.0}})
            assert ok and r["accepted"] is False and "liveliness" in r["reason"]
            # and the operator sees it among the verdicts (counted as refused)
            live.wait_until(z, "coordinator", lambda st: st["counters"]["refused"] >= 1 and any(
                v["source"] == "S2" and not v["accepted"] and "liveliness" in v["reason"] for v in st["verdicts"]), 10)
        res = live.wait_rig(120)
    assert not res["metrics"]["diverged"]
    out = _json.loads((tmp_path / "run" / "coordinator.out").read_text().splitlines()[-1]) if (
        tmp_path / "run" / "coordinator.out").read_text().strip() else None
    assert out is None or not out.get("loop_ended_by_itself")
