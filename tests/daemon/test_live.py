"""The daemon on Zenoh with the plant and load peers, on loopback (free ports, no multicast scouting)."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from conftest import ROOT, SCENARIOS
from mcap.reader import make_reader

from clients.live import configs_from_scenario, run_live, wait_until
from clients.peers.load import run_load
from clients.query import QueryError, query
from schemas.codec import CMD, MEAS
from schemas.component import ComponentConfig, LoadPeerConfig, ZenohConfig, config_from_dict
from schemas.scenario import load_scenario
from service.daemon.bus import free_tcp_port
from service.daemon.daemon import Daemon
from service.sim import run


def read_topic(path, suffix):
    with open(path, "rb") as f:
        reader = make_reader(f)
        return [json.loads(m.data) for _s, c, m in reader.iter_messages() if c.topic.endswith(suffix)]


def test_lockstep_over_zenoh_reproduces_the_offline_run(tmp_path):
    scn = load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.05", "feasibility.window_s=0.02"])
    out = tmp_path / "lockstep.mcap"
    res = run_live(scn, lockstep=True, rate_hz=None, out=str(out), duration_s=None, workdir=str(tmp_path))
    assert res["counters"]["timeouts"] == 0 and res["counters"]["commands"] == 500
    # the CPU budget: the plant's and the load's shares of one CPU and how busy the machine was; the controller's
    # needs 1025 ticks (it reads its CPU time every 1024), this run has 500
    cpu = res["cpu"]
    assert cpu["plant_pct"] > 0 and cpu["load_pct"] > 0 and 0 < cpu["host_busy_pct"] <= 100
    assert cpu["controller_pct"] is None
    live = read_topic(out, "/plant")
    sim = run(scn).trace
    v_live = np.array([m["v"] for m in live])
    i_live = np.array([m["i"] for m in live])
    assert len(v_live) == len(sim["v"])
    np.testing.assert_allclose(v_live, sim["v"], rtol=1e-9, atol=0)
    np.testing.assert_allclose(i_live, sim["i"], rtol=1e-9, atol=1e-9)
    cmds = read_topic(out, "/cmd")
    np.testing.assert_allclose([c["du_dt"] for c in cmds], sim["du_dt"], rtol=1e-9, atol=1e-9)
    # the daemon's own log replays bit for bit
    from service.replay import replay

    r = replay(res["daemon_log"], progress=False)
    assert r["identical"] and r["compared"] == 500 and r["read_from"] == "index"
    # the daemon measured the plant's delay line from u and its own commands, and compensates exactly that
    ld = res["daemon"]["loop_delay"]
    assert ld["measured_samples"] == scn.timing.delay_samples == 3 and not ld["mismatch"]
    # the load announced each window half a window ahead; the daemon forecast its Z^{r,out} for it and published
    # it on .../z (P parts: the negated box), in this run before the window started
    W = scn.feasibility.window_s
    boxes = {m["window"]: m for m in read_topic(res["daemon_log"], "/z_nb/load")}
    z_out = read_topic(res["daemon_log"], "/z_out")
    # (the forecast worker runs at the lowest priority, a window's request superseded by the next one's while it
    # is busy: on a machine loaded beside this run, window 1 went unforecast. Which windows it reaches is the
    # machine's speed; that each one it reaches is forecast, published and drawn right is asserted)
    events = {(e := json.loads(ev["detail"]))["window"]: e for ev in read_topic(res["daemon_log"], "/events")
              if ev["kind"] == "forecast"}
    assert events and set(events) <= {0, 1, 2} and all(e["feasible"] for e in events.values()), events
    first = {}
    for m in z_out:
        first.setdefault(m["window"], m)
    for w, m in first.items():  # each window's first Z^{r,out}: the negated box of that window's announcement
        if w >= 1 and m["t"] < w * W:  # published ahead of its window: the forecast of the announced box
            assert (m["P_min"], m["P_max"]) == (-boxes[w]["P_max"], -boxes[w]["P_min"])
    # the report draws each window's Z^{r,in} and the forecast Z^{r,out} from those events
    from clients.report import feasibility_bands, load_series

    log = load_series(res["daemon_log"])
    assert log["forecasts"] == events
    bands = feasibility_bands(log)
    assert [b[0] for b in bands] == pytest.approx([k * W for k in sorted(events)])
    for k, b in zip(sorted(events), bands, strict=True):
        assert b[6] is not None and b[6][2] and b[2:6] == tuple(events[k]["z_in"]), (k, b)


@pytest.fixture
def daemon_and_load():
    """A daemon (clock trigger, 2 kHz) with one neighbour load peer; no plant: feed measurements by hand."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _plant, load = configs_from_scenario(scn, ep, lockstep=False, rate_hz=2000.0)
    comp["neighbour_stale_s"] = 0.2
    comp["loop"]["trigger"] = "clock"
    cfg = config_from_dict(ComponentConfig, comp)
    d = Daemon(cfg)
    d.open()
    loop = threading.Thread(target=d.run_loop, daemon=True)
    loop.start()
    stop = threading.Event()
    load["plant_id"] = None
    load["rate_hz"] = 200.0
    lt = threading.Thread(target=run_load, args=(config_from_dict(LoadPeerConfig, load), stop), daemon=True)
    lt.start()
    try:
        yield d, ep, stop
    finally:
        stop.set()
        d.stop()
        loop.join(2.0)
        lt.join(2.0)
        d.close()


def zc(ep):
    return ZenohConfig(mode="peer", connect=[ep])


def test_status_config_and_neighbour_freshness(daemon_and_load):
    d, ep, stop_load = daemon_and_load
    assert wait_until(lambda: d.neighbours[0].count > 5, 10.0)
    st = query(zc(ep), "energyctl", "source", "status", timeout_s=5.0)
    # no plant feeds this daemon: its measurements are stale, so it holds, degraded
    assert st["state"] == "degraded" and st["degraded_reason"] == "meas: stale"
    assert st["neighbours"]["load"]["fresh"] is True
    assert st["loop"]["ticks"] > 0 and "p99" in st["loop"]["exec_us"]
    cfg = query(zc(ep), "energyctl", "source", "config")
    assert cfg["controller"]["K_per_s"] == 2000.0
    # a set is validated, applied at a tick boundary, and reported
    ans = query(zc(ep), "energyctl", "source", "config", sets=["controller.K_per_s=800.0"])
    assert ans["controller"]["K_per_s"] == 800.0 and d.core.cfg.K_per_s == 800.0
    assert d.core._gains[1] == 800.0  # the core's cached gain changed too
    with pytest.raises(QueryError, match="K_per_s"):
        query(zc(ep), "energyctl", "source", "config", sets=["controller.K_per_s=-1"])
    with pytest.raises(QueryError, match="only controller"):
        query(zc(ep), "energyctl", "source", "config", sets=["model.R_ohm=1"])
    assert d.core.cfg.K_per_s == 800.0
    # lifecycle
    query(zc(ep), "energyctl", "source", "config", sets=["lifecycle=inactive"])
    assert wait_until(lambda: d.state == "inactive", 5.0)
    # the neighbour going silent flips its freshness
    stop_load.set()
    assert wait_until(lambda: not query(zc(ep), "energyctl", "source", "status")["neighbours"]["load"]["fresh"], 5.0)


def test_a_wildcard_get_learns_which_queryable_answered(daemon_and_load):
    """Replies are made on the queryable's own key: a get on energyctl/** is answered by .../status and
    .../config (and refused by .../config/set, which needs a body), each reply keyed by its leaf."""
    from service.daemon.bus import open_session

    _d, ep, _stop = daemon_and_load
    with open_session(zc(ep)) as s:
        replies = list(s.get("energyctl/**", timeout=5.0))
    ok = {str(r.ok.key_expr): json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None}
    assert set(ok) == {"energyctl/source/status", "energyctl/source/config"}
    assert ok["energyctl/source/status"]["id"] == "source" and "controller" in ok["energyctl/source/config"]
    assert any(r.err is not None for r in replies)  # config/set without {"set": [...]}


def test_the_daemon_forecasts_each_announced_window_and_checks_it_ahead(daemon_and_load):
    """The load announces each window's box half a window ahead; the daemon forecasts its own Z^{r,out} for it in
    its worker process, whatever the loop's state (here it holds: no plant). Publishing: the lockstep test."""
    d, ep, _stop = daemon_and_load

    def forecast():
        return query(zc(ep), "energyctl", "source", "status")["feasibility"]["forecast"]

    # one forecast per window, a constant load's from the cache; a window announced while the worker is still busy
    # with the one before is skipped for the newer one (a loaded machine), so wait for three to be answered
    assert wait_until(lambda: (f := forecast()).get("computed", 0) + f.get("cache_hits", 0) >= 3, 20.0)
    f = forecast()
    box = d.neighbours[0].box(f["window"])
    assert f["feasible"] and f["reason"] == "" and box is not None
    assert f["Z_out"]["P"] == [-box[1], -box[0]] and f["Z_out"]["P_dot"] == [-box[3], -box[2]]
    assert f["Z_out"]["Qdot"][0] < 0 < f["Z_out"]["Qdot"][1]  # a load that may switch moves Qdot^{r,out}
    assert f["computed"] >= 1 and f["window"] >= 2
    # a gain too low for the incoming range (tau' = 1/K grows): the next window is flagged before it starts
    query(zc(ep), "energyctl", "source", "config", sets=["controller.K_per_s=10.0"])
    assert wait_until(lambda: forecast()["feasible"] is False, 10.0)
    assert forecast()["reason"].startswith("Qdot^r,out")


def plant_side(d: Daemon):
    """On the daemon's own session, a plant's two keys: the seqs of the commands it sends (a list a subscriber fills,
    and the subscriber), and a publisher of measurements."""
    got: list[int] = []
    sub = d.session.declare_subscriber("energyctl/source/cmd",
                                       lambda m: got.append(CMD.decode(m.payload.to_bytes())[0]))
    return got, sub, d.session.declare_publisher("energyctl/source/meas")


def lockstep_daemon(catch_up: int) -> Daemon:
    """An opened lockstep daemon of the paper's stack at 10 kHz (loopback, no forecast worker, a 1 s lockstep wait)
    answering the newest ``catch_up`` queued samples; its loop is driven by the test."""
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=True, rate_hz=10000.0)
    comp["loop"].update(catch_up=catch_up, lockstep_timeout_s=1.0)
    comp["forecast"] = {"enabled": False}
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    return d


def test_a_lockstep_loop_waits_for_its_neighbours_only_on_a_sample_it_steps_on():
    """Lockstep waited for the neighbours' messages of the seq read off any payload before checking it: a bit flip in
    a frame's magic, a truncated frame, a seq beyond 2^53, a NaN, a v out of range (held) with a seq far ahead held
    the loop for the whole lockstep_timeout_s and marked every neighbour lagging. Now the sample is checked first and
    only one the core steps on is waited for; the others are rejected (or held: answered with du/dt = 0) at once,
    and the next sample is answered with the neighbours still followed."""
    d = lockstep_daemon(catch_up=8)
    try:
        nb = d.neighbours[0]
        nb.seq, nb.count, nb.P, nb.rx_ns, nb.alive = 1, 1, 1200.0, time.monotonic_ns(), True  # its z for sample 1
        got, sub, pub = plant_side(d)
        far = MEAS.struct.pack(0xE1, 1, 2**40, 1e-4, 15.0, 80.0, 80.15, 15.0)
        bad = [b"\xe2" + far[1:], far[:1] + b"\x07" + far[2:], far[:20], far + b"\x00",
               MEAS.struct.pack(0xE1, 1, 2**63, 1e-4, 15.0, 80.0, 80.15, 15.0),
               MEAS.encode(2**40, 1e-4, float("nan"), 80.0, 80.15, 15.0),
               MEAS.encode(2**40, 1e-4, 15.0, 8000.0, 80.15, 15.0)]  # held: answered with a hold, not stepped on
        for payload in [*bad, MEAS.encode(1, 1e-4, 15.0, 80.0, 80.15, 15.0)]:
            pub.put(payload)
        # the malformed ones are refused on receipt (Daemon._admit, issue 31): queued are the held one and the sample
        assert wait_until(lambda: d.meas_q.qsize() + sum(d.rx_rejected.values()) == len(bad) + 1, 5.0)
        assert d.meas_q.qsize() == 2
        d.run_loop(max_ticks=2)
        assert wait_until(lambda: got == [2**40, 1], 5.0), got
        assert d.stats.lockstep_timeouts == 0 and not nb.lagging
        assert sum(d.status()["rejected"].values()) == len(bad), d.status()["rejected"]
        sub.undeclare()
    finally:
        d.close()


def test_frames_the_lockstep_loop_passes_over_are_counted():
    """With loop.catch_up = 1 the loop answers the newest queued frame; the ones it passed over (queued while it
    waited or stalled) were dropped without a count. Now each is counted in status loop.meas_skipped (frames that can
    never be the next sample are refused before they are queued, and counted there), and none stalls the loop."""
    d = lockstep_daemon(catch_up=1)
    try:
        nb = d.neighbours[0]
        nb.seq, nb.count, nb.P, nb.rx_ns, nb.alive = 4, 1, 1200.0, time.monotonic_ns(), True  # its z up to sample 4
        got, sub, pub = plant_side(d)
        frames = [MEAS.encode(k, k * 1e-4, 15.0, 80.0, 80.15, 15.0) for k in range(1, 5)]
        for payload in frames:
            pub.put(payload)
        assert wait_until(lambda: d.meas_q.qsize() == len(frames), 5.0)
        d.run_loop(max_ticks=1)
        assert wait_until(lambda: got == [4], 5.0), got
        st = d.status()
        assert st["loop"]["meas_skipped"] == len(frames) - 1, st["loop"]
        assert d.stats.lockstep_timeouts == 0 and not nb.lagging
        sub.undeclare()
    finally:
        d.close()


@pytest.mark.parametrize(("catch_up", "answered"), [(1, [5]), (3, [3, 4, 5])])
def test_a_sample_triggered_loop_answers_the_newest_queued_samples_in_order(catch_up, answered):
    """loop.catch_up: of six queued samples, the newest catch_up are answered, oldest first; 1 = only the newest."""
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=10000.0)
    comp["neighbours"] = []
    comp["loop"].update(trigger="sample", wait="block", catch_up=catch_up)
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    try:
        got, sub, pub = plant_side(d)
        for k in range(6):
            pub.put(MEAS.encode(k, k * 1e-4, 15.0, 80.0, 80.15, 15.0))
        assert wait_until(lambda: d.meas_q.qsize() == 6, 5.0)
        d.run_loop(max_ticks=len(answered))
        assert wait_until(lambda: len(got) == len(answered), 5.0)
        assert got == answered and d.core.steps == len(answered)
        sub.undeclare()
    finally:
        d.close()


def test_samples_arriving_while_the_loop_is_held_up_keep_only_the_newest_in_memory():
    """The sample trigger's queue is bounded (service.daemon.daemon.MEAS_QUEUE_MAX), keeping the newest: samples that
    arrive while the loop thread is held up cannot pile up in memory (a 10 kHz soak grew 26 MB at once), the
    dropped ones are counted in status, and the loop then answers the newest sample."""
    from service.daemon.daemon import MEAS_QUEUE_MAX

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=10000.0)
    comp["neighbours"] = []
    comp["loop"].update(trigger="sample", wait="block", catch_up=1)
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    n = 3 * MEAS_QUEUE_MAX
    try:
        got, sub, pub = plant_side(d)
        for k in range(n):  # the loop is not running: held up
            pub.put(MEAS.encode(k, k * 1e-4, 15.0, 80.0, 80.15, 15.0))
        assert wait_until(lambda: d.meas_q.dropped == n - MEAS_QUEUE_MAX, 10.0), d.meas_q.dropped
        assert d.meas_q.qsize() == MEAS_QUEUE_MAX
        assert d.status()["loop"]["meas_queue_dropped"] == n - MEAS_QUEUE_MAX
        d.run_loop(max_ticks=1)
        assert wait_until(lambda: len(got) == 1, 5.0)
        assert got == [n - 1]  # the newest
        sub.undeclare()
    finally:
        d.close()


@pytest.mark.parametrize("shared_memory", [None, True])
def test_sessions_use_no_shared_memory_pool_unless_asked(shared_memory):
    """A reply over 3 KiB (a long status) made Zenoh create its 16 MiB shared-memory pool (/dev/shm/*.zenoh) and a
    10 kHz soak's daemon grew 26 MB: our sessions turn shared memory off unless zenoh.shared_memory is set."""
    import glob
    import os

    from service.daemon.bus import open_session

    def pools() -> set[str]:
        return set(glob.glob("/dev/shm/*.zenoh"))

    before = pools()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    a = open_session(ZenohConfig(listen=[ep], shared_memory=shared_memory))
    b = open_session(ZenohConfig(connect=[ep], shared_memory=shared_memory))
    try:
        a.declare_queryable("t/big", lambda q: q.reply(q.key_expr, b"x" * 8192))
        assert wait_until(lambda: any(r.ok is not None for r in b.get("t/big", timeout=1.0)), 10.0)
        made = pools() - before
        assert (len(made) > 0) == bool(shared_memory), made
    finally:
        a.close()
        b.close()
        for f in pools() - before:
            os.unlink(f)


def test_query_without_a_controller_fails_clearly():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with pytest.raises(QueryError, match="no answer"):
        query(ZenohConfig(mode="peer", listen=[ep]), "energyctl", "nobody", "status", timeout_s=0.5)


def test_readme_documents_every_cli_command():
    text = (ROOT / "README.md").read_text()
    for cmd in ("energyctl run", "energyctl plant", "energyctl load", "energyctl query", "energyctl demo"):
        assert cmd in text


def test_sigterm_stops_the_daemon_within_a_second_and_it_reports(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from clients.live import _toml

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _plant, _load = configs_from_scenario(scn, ep, lockstep=False, rate_hz=2000.0)
    comp["loop"]["trigger"] = "clock"
    comp["log_dir"] = str(tmp_path / "logs")
    path = tmp_path / "c.toml"
    path.write_text(_toml(comp))
    stats = tmp_path / "status.json"
    p = subprocess.Popen([sys.executable, "-m", "clients.cli", "run", "--config", str(path), "--stats-out", str(stats)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert wait_until(lambda: "active" in (p.stderr.readline() or ""), 15.0)

        def ticking() -> bool:
            try:
                return query(zc(ep), "energyctl", "source", "status", timeout_s=1.0)["loop"]["ticks"] > 0
            except QueryError:
                return False

        assert wait_until(ticking, 15.0)
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        out, _err = p.communicate(timeout=5.0)
        assert time.monotonic() - t0 < 1.0 + 0.5  # one period plus process teardown
        assert p.returncode == 0
        assert json.loads(out.strip().splitlines()[-1])["loop"]["ticks"] > 0
        status = json.loads(stats.read_text())
        assert status["state"] == "shutdown"
        # the log was closed: it has a summary, and its channels are there
        with open(status["logging"]["path"], "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and any(c.topic.endswith("/cmd") for c in summary.channels.values())
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_two_controlled_components_on_one_network_each_reproduce_their_own_run(tmp_path):
    """Two controllers, each with its own plant and neighbour load, share one Zenoh network (the second
    stack connects to the first's endpoint). Both lockstep runs equal their offline runs: no cross-talk."""
    from clients.live import Processes, _toml, child_env

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    stacks = {}
    for n, name in enumerate(("paper-constant-load", "paper-varying-load")):
        scn = load_scenario(SCENARIOS / f"{name}.toml", ["timing.duration_s=0.02"])
        out = tmp_path / f"plant{n}.mcap"
        comp, plant, load = configs_from_scenario(scn, ep, lockstep=True, out=str(out))
        if n:  # the second stack: other ids, and its controller joins the first one's network
            sfx = str(n)
            comp.update(id="source" + sfx, plant_id="source" + sfx, neighbours=["load" + sfx],
                        zenoh={"mode": "peer", "connect": [ep]})
            plant.update(id="plant" + sfx, controller_id="source" + sfx, wait_for=["load" + sfx])
            load.update(id="load" + sfx, plant_id="source" + sfx)
        for role, d in (("component", comp), ("plant", plant), ("load", load)):
            (tmp_path / f"{role}{n}.toml").write_text(_toml(d))
        stacks[n] = (scn, out)
    env = child_env()
    with Processes() as procs:
        plants = []
        for n in stacks:
            procs.start(f"daemon{n}", ["run", "--config", str(tmp_path / f"component{n}.toml")], env=env)
            procs.start(f"load{n}", ["load", "--config", str(tmp_path / f"load{n}.toml")], env=env)
        for n in stacks:
            plants.append(procs.start(f"plant{n}", ["plant", "--config", str(tmp_path / f"plant{n}.toml"), "--json"],
                                      env=env))
        results = []
        for p in plants:
            so, se = p.communicate(timeout=120)
            assert p.returncode == 0, se[-800:]
            results.append(json.loads(so.strip().splitlines()[-1]))
            assert results[-1]["counters"]["commands"] == 200 and results[-1]["counters"]["timeouts"] == 0
    for scn, out in stacks.values():
        v_live = np.array([m["v"] for m in read_topic(out, "/plant")])
        np.testing.assert_allclose(v_live, run(scn).trace["v"], rtol=1e-9, atol=0)
    # the plant's log carries its metrics (written by its recorder at the end); the report shows them
    from clients.report import report

    rep = report([str(stacks[1][1])], str(tmp_path / "report"))
    assert rep["metrics"]["plant1"]["v_min"] == results[1]["metrics"]["v_min"]


def test_the_daemon_is_alive_only_when_its_recorder_is_writing_and_its_loop_runs(tmp_path):
    """The liveliness token is the plant's start signal: it must not appear while the recorder process is still
    starting (importing Python for about a second, which took the CPU from the first samples), nor before the
    loop thread is ready to tick (its start-up garbage collection alone missed realtime samples)."""
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    comp, _p, _l = configs_from_scenario(scn, ep, lockstep=False, rate_hz=1000.0)
    comp["log_dir"] = str(tmp_path)
    d = Daemon(config_from_dict(ComponentConfig, comp))
    try:
        d.open()
        assert d.recorder is not None and d.recorder._ready.is_set()  # open() waited for the writer ...
        assert len(list(tmp_path.glob("source-*.mcap"))) == 1  # ... which had created the file
        assert d.token is None  # but the loop is not running yet: not alive
        loop = threading.Thread(target=d.run_loop, daemon=True)
        loop.start()
        assert wait_until(lambda: d.token is not None, 5.0)  # announced by the running loop
        d.stop()
        loop.join(5.0)
        assert not loop.is_alive()
    finally:
        d.stop()
        d.close()


def test_the_neighbours_power_is_carried_forward_to_the_samples_time_by_its_rate(daemon_by_hand):
    """P^{r,in} at sample time t from a neighbour message stamped t_j: P_j + dP_j/dt (t - t_j) while the message is
    younger than neighbour_stale_s, by at most neighbour_extrapolate_s (a realtime load publishes at 200 Hz under a
    1 kHz loop: up to 5 ms old, ~100 W off on the demo's load swings; silent for 32 ms, its rate carried it 560 W
    off); carried back as well when the message is newer than the sample (a sample answered late, after a stall);
    the plain value when t == t_j (lockstep) or when the clocks disagree (more than neighbour_stale_s apart)."""
    d = daemon_by_hand
    nb = d.neighbours[0]
    seen = []

    class Spy:  # on what steps the core (the compiled tick, or the core itself): its P_r_in and P_r_in_dot
        def __init__(self, inner, step):
            self._inner, self._step = inner, step

        def step(self, *args):
            seen.append(args[6:8])
            return self._step(*args)

        def __getattr__(self, name):  # the rest of the compiled tick (accept, close) as it is
            return getattr(self._inner, name)

    if d._fast is not None:
        d._fast = Spy(d._fast, d._fast.step)
    else:
        d.core.step_values = Spy(None, d.core.step_values).step
    nb.P, nb.P_dot = 1200.0, 2.0e4
    # (sample time, message time): same instant; 3 ms later; a message stamped 1 ms after the sample; one older
    # than neighbour_extrapolate_s but not stale; one newer by more than that; one older than neighbour_stale_s
    h = d.cfg.neighbour_extrapolate_s
    assert 0.003 < h < d.cfg.neighbour_stale_s - 0.003
    d._max_gap = 10**6  # the samples below are on the plant's clock, the last one 2 neighbour_stale_s (20 s) later
    for t, t_j in ((0.010, 0.010), (0.013, 0.010), (0.014, 0.015), (0.020 + h + 0.003, 0.020),
                   (0.034, 0.034 + h + 0.002), (0.040 + 2 * d.cfg.neighbour_stale_s, 0.015)):
        nb.t = t_j
        d._tick(MEAS.encode(round(t / d.period_s), t, 15.0, 80.0, 80.15, 15.0), 1)  # on the plant's clock
    assert len(seen) == 6, (d.rejected, d.last_reject)
    assert seen[0] == (-1200.0, -2.0e4)  # same instant: exactly the message
    assert seen[1][0] == pytest.approx(-(1200.0 + 2.0e4 * 0.003), rel=1e-12)  # 3 ms later: 1260 W
    assert seen[2][0] == pytest.approx(-(1200.0 - 2.0e4 * 0.001), rel=1e-9)  # 1 ms before the message: 1180 W
    assert seen[3][0] == pytest.approx(-(1200.0 + 2.0e4 * h), rel=1e-12)  # carried no further than the horizon ...
    assert seen[4][0] == pytest.approx(-(1200.0 - 2.0e4 * h), rel=1e-12)  # ... either way
    assert seen[5][0] == -1200.0  # clocks apart: not carried


def test_a_realtime_plant_starts_its_clock_at_the_controllers_first_answer():
    """Realtime pacing arms on the answer to sample 0 (a converter enabled by its controller): a controller that
    takes 150 ms to give it gets sample 1 only after that answer, and the plant does not time out; without the
    arm, sample 1 went out a period after sample 0, long before its answer."""
    import time

    from clients.peers.plant import run_plant
    from schemas.component import PlantPeerConfig

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    _c, plant, _l = configs_from_scenario(scn, ep, lockstep=False, rate_hz=1000.0, duration_s=0.02)
    plant.update(wait_for=[], out=None, nice=None, zenoh={"mode": "peer", "listen": [ep]})
    ctl = ZenohConfig(mode="peer", connect=[ep])
    from service.daemon.bus import open_session

    s = open_session(ctl)
    arrivals: dict[int, float] = {}
    answered_0 = []
    pub = s.declare_publisher("energyctl/source/cmd")

    def answer(seq: int, t: float) -> None:
        if seq == 0:
            answered_0.append(time.monotonic())
        pub.put(CMD.encode(seq, t, 0.0, 0.0, False))

    def on_meas(m) -> None:
        v = MEAS.decode(m.payload.to_bytes())
        arrivals[v[0]] = time.monotonic()
        if v[0] == 0:
            threading.Timer(0.15, answer, args=(0, v[1])).start()  # a slow first answer
        else:
            answer(v[0], v[1])

    sub = s.declare_subscriber("energyctl/source/meas", on_meas)
    token = s.liveliness().declare_token("energyctl/source/alive")
    try:
        res = run_plant(config_from_dict(PlantPeerConfig, plant), threading.Event())
    finally:
        token.undeclare()
        sub.undeclare()
        s.close()
    c = res["counters"]
    # ordering only: how many later commands are late depends on this machine's load, not on the arm
    assert c["samples"] == 20 and c["timeouts"] == 0, c
    assert answered_0 and arrivals[1] >= answered_0[0]  # sample 1 only after the answer to sample 0


QUERIER = """
import json, sys, time
from clients.query import ask
from schemas.component import ZenohConfig
from service.daemon.bus import open_session
s = open_session(ZenohConfig(mode="peer", connect=[sys.argv[1]]))
print("ready", flush=True)
for line in sys.stdin:  # a round of 20 queries per line, at an operator's or a dashboard's pace (100 a second at most)
    answered = 0
    for k in range(20):
        answered += bool(ask(s, "energyctl", "source", "status" if k % 3 else "config", timeout_s=5.0))
        time.sleep(0.01)
    print(json.dumps({"answered": answered}), flush=True)
s.close()
"""


def test_queries_are_answered_while_the_clock_loop_holds_its_rate(daemon_and_load):
    """Status and config queries are served on their own thread: 120 of them at up to 100 a second from another
    process, every one answered, while the 2 kHz clock loop keeps its clock (a period is either ticked or counted as
    an overrun, so ticks + overruns follow it), in windows with queries and in quiet ones alternated with them. What
    the queries cost in overruns is a benchmark's figure, not this test's (`energyctl bench soak` answers a status
    query stream beside the loop): run alone, 0.15 % of the periods with queries against 0.07-0.7 % without; with
    two CPU hogs beside it 9.4 % against 9.9 %; but late in the whole suite, with this daemon inside pytest's
    process beside what earlier tests left, 20-50 % against 8-15 %."""
    import subprocess
    import sys

    from clients.live import child_env

    d, ep, _stop = daemon_and_load
    assert wait_until(lambda: d.stats.ticks > 200, 10.0)

    def window(run) -> tuple[int, int, float]:
        """(ticks, overruns, periods of the clock) while run() runs."""
        ticks0, over0, t0 = d.stats.ticks, d.stats.overruns, time.monotonic()
        run()
        elapsed = time.monotonic() - t0
        return d.stats.ticks - ticks0, d.stats.overruns - over0, elapsed * d.cfg.loop.rate_hz

    p = subprocess.Popen([sys.executable, "-c", QUERIER, ep], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=child_env(), cwd=ROOT)
    answers, busy, quiet = [], [], []
    try:
        assert p.stdout.readline().strip() == "ready", p.stderr.read()
        for _ in range(6):
            def round_of_queries() -> None:
                p.stdin.write("go\n")
                p.stdin.flush()
                answers.append(p.stdout.readline())

            busy.append(window(round_of_queries))
            quiet.append(window(lambda: threading.Event().wait(busy[-1][2] / d.cfg.loop.rate_hz)))
    finally:
        p.kill()
        p.communicate(timeout=10)
    assert sum(json.loads(a)["answered"] for a in answers) == 120
    for ticks, over, periods in busy + quiet:
        assert ticks + over == pytest.approx(periods, rel=0.05, abs=3)  # the loop ran on its clock all along
    share = [sum(w[1] for w in ws) / sum(w[2] for w in ws) for ws in (busy, quiet)]
    print(f"overruns: {100 * share[0]:.2f} % of the periods with queries, {100 * share[1]:.2f} % without")


def test_a_config_set_changes_the_gain_from_the_next_tick_on(daemon_by_hand):
    """A set waits for the loop; the loop applies it between two ticks (_apply_pending); the next command is the one
    a core with the new gain computes from the same history, bit for bit, and differs from the old gain's."""
    from service.core import make_core

    d = daemon_by_hand
    c = d.cfg
    old_k = c.controller.K_per_s
    samples = [MEAS.encode(k, k * d.period_s, 15.0 + 0.1 * k, 80.0 - 0.05 * k, 80.15, 15.0) for k in range(8)]
    ref_new = make_core(c.controller, c.model, d.period_s, c.delay_samples)
    ref_old = make_core(c.controller, c.model, d.period_s, c.delay_samples)
    nb = d.neighbours[0]
    P_in, P_in_dot = -nb.P, -nb.P_dot

    def ref_step(core, payload):
        return core.step_values(*MEAS.decode(payload), P_in, P_in_dot)[0]

    for p in samples[:5]:
        d._tick(p, 1)
        assert d.last_cmd[2] == ref_step(ref_new, p) == ref_step(ref_old, p)
    answer = {}
    setter = threading.Thread(target=lambda: answer.update(r=d.apply_sets([f"controller.K_per_s={old_k / 4}"])))
    setter.start()
    assert wait_until(lambda: d._pending is not None, 5.0)  # validated, waiting for the loop
    assert d.core.cfg.K_per_s == old_k
    d._apply_pending()  # the loop, between two ticks
    setter.join(5.0)
    ok, body = answer["r"]
    assert ok and body["controller"]["K_per_s"] == old_k / 4 and d.core.cfg.K_per_s == old_k / 4
    ref_new.set_gains(d.core.cfg)
    for p in samples[5:]:
        d._tick(p, 1)
        new, old = ref_step(ref_new, p), ref_step(ref_old, p)
        assert d.last_cmd[2] == new and new != old


def test_a_short_soak_regulates_answers_every_query_and_loses_no_record():
    """bench soak for 6 s at 2 kHz (the realtime demo's rate; 3 kHz, the highest bench realtime found here on a quiet
    day, left v 10.05 % off on a noisy one): the plant reports its regulation, v stays near v_ref, every status query
    is answered, the recorder drops nothing and nothing is rejected. The soak's former stack (clock trigger, one
    sample of delay, the paper's gain) diverged at 3 kHz within seconds in every run, and the daemon rejected every
    later sample as out of range."""
    from clients.bench.soak import bench_soak
    from clients.commands.demo import DEMO_REALTIME_SETS

    res = bench_soak(0.1, rate_hz=2000.0, query_hz=20.0, warmup_s=2.0, sets=DEMO_REALTIME_SETS, progress=None)
    assert res["plant_error"] is None and res["diverged"] is False
    assert res["v_dev_after_50ms_pct"] < 10.0  # a loose band: this is not the realtime bench's ±2 %
    assert res["queries"]["failed"] == 0 and res["queries"]["answered"] == res["queries"]["sent"] > 50
    assert res["recorder_written"] > 10_000 and not res["recorder_drops"] and res["recorder_state"] == "ok"
    assert res["rejected"] == {} and res["loop_ticks"] > 8_000
    assert res["rss_kib_end"] > 0 and res["cpu"]["plant_pct"] > 0


@pytest.mark.parametrize(("zenoh", "expected"), [
    ({"connect": ["tcp/127.0.0.1:7447"]}, ["tcp/127.0.0.1:0"]),  # a local stack: loopback only
    ({}, ["tcp/127.0.0.1:0"]),
    ({"connect": ["tcp/[::1]:7447", "tcp/localhost:7448"]}, ["tcp/127.0.0.1:0"]),
    ({"connect": ["tcp/192.0.2.7:7447"]}, None),  # another host: Zenoh's own default, reachable from there
    ({"connect": ["tcp/127.0.0.1:7447"], "multicast_scouting": True}, None),
    ({"connect": ["tcp/127.0.0.1:7447"], "listen": ["tcp/127.0.0.1:9000"]}, ["tcp/127.0.0.1:9000"]),
    ({"mode": "client", "connect": ["tcp/127.0.0.1:7447"]}, None),
])
def test_a_peer_that_only_talks_to_this_host_listens_on_loopback(zenoh, expected):
    """Zenoh's default for a peer is every interface, and its gossip then links two local peers over the host's
    own non-loopback address; a peer that can only meet peers on this host listens on loopback instead."""
    from service.daemon.bus import zenoh_config

    got = json.loads(zenoh_config(ZenohConfig(**zenoh)).get_json("listen/endpoints"))
    if expected is None:
        assert got != ["tcp/127.0.0.1:0"]
    else:
        assert got == expected
