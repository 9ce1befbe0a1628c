"""Fault injection on the live stack (loopback, free ports): kill -9 and SIGSTOP peers, restart the router,
fill the log directory. Each test asserts on the controller's status and log; every process is stopped."""

from __future__ import annotations

import resource
import signal

from conftest import SCENARIOS

from clients.bench.recovery import Rig
from schemas.scenario import load_scenario
from service.logio.reader import messages as read_messages
from service.replay import replay


def scn():
    return load_scenario(SCENARIOS / "paper-constant-load.toml")


def running(rig: Rig, t_s: float = 0.02, **daemon) -> dict:
    """Start controller, load and plant; the controller's status once plant time reached t_s."""
    rig.start("daemon", **daemon)
    rig.start("load")
    rig.start("plant")
    st = rig.wait_status(lambda s: rig.sample_t(s) >= t_s, 60.0)
    assert st, "the stack did not start"
    return st


def test_kill9_plant_degrades_and_a_new_plant_reinitialises_the_controller(tmp_path):
    with Rig(scn(), tmp_path, duration_s=5.0) as rig:
        running(rig)
        rig.signal("plant", signal.SIGKILL)
        st = rig.wait_status(lambda s: s["state"] == "degraded", 10.0)
        assert st and st["degraded_reason"] == "meas: stale"
        rig.start("plant", duration_s=0.03, out=str(tmp_path / "plant-2.mcap"))
        res = rig.plant_result()
        assert res["counters"]["commands"] == 300 and res["counters"]["timeouts"] == 0
        assert res["metrics"]["settle_s"] is not None  # the new plant is regulated from its own start
        st = rig.status()
        assert st["plant_restarts"] == 1
        rig.close()
        kinds = [e["kind"] for e in read_messages(rig.daemon_log(), "/events")]
        assert "degraded" in kinds and "plant_restart" in kinds
        assert kinds.index("degraded") < kinds.index("plant_restart")
        # the killed plant's own trace survives: it went through its recorder process, which finished the file
        from clients.live import wait_until

        assert wait_until(lambda: len(read_messages(rig.plant_out, "/plant")) >= 200, 20.0)
        # the log replays bit for bit across the restart (seqs repeat: ticks are keyed by (epoch, seq))
        r = replay(str(rig.daemon_log()), progress=False)
        assert r["identical"] and r["plant_restarts"] == 1 and r["compared"] > 300, r


def test_sigstop_neighbour_is_not_waited_for_and_comes_back_on_sigcont(tmp_path):
    with Rig(scn(), tmp_path, duration_s=5.0, comp={"local_reference_W": "measured"}) as rig:
        running(rig)
        rig.signal("load", signal.SIGSTOP)
        try:
            # its liveliness token stays (a hung process keeps its lease), so freshness decides
            st = rig.wait_status(lambda s: not s["neighbours"]["load"]["fresh"] and s["reference"] == "local", 10.0)
            assert st and st["neighbours"]["load"]["alive"] is True
            # one lockstep wait times out, then the loop runs on without it: plant time keeps advancing
            t_stopped = rig.sample_t(st)
            st = rig.wait_status(lambda s: rig.sample_t(s) >= t_stopped + 0.01, 10.0)
            assert st and st["loop"]["lockstep_timeouts"] >= 1 and st["neighbours"]["load"]["lagging"]
        finally:
            rig.signal("load", signal.SIGCONT)
        st = rig.wait_status(lambda s: s["neighbours"]["load"]["fresh"] and s["reference"] == "neighbours"
                             and not s["neighbours"]["load"]["lagging"], 10.0)
        assert st, rig.status()
        assert st["rejected"] == {}


def test_kill9_neighbour_token_gone_then_back(tmp_path):
    with Rig(scn(), tmp_path, duration_s=5.0) as rig:
        running(rig)
        rig.signal("load", signal.SIGKILL)
        # (the loop sees the token go, then sets its reference on its next tick: wait for both)
        st = rig.wait_status(lambda s: s["neighbours"]["load"]["alive"] is False and s["reference"] == "none", 10.0)
        assert st, rig.status()
        # held from then on (a status may catch the tick between its reference and its command: ask again)
        assert rig.wait_status(lambda s: s["reference"] == "none" and s["last_command"]["du_dt"] == 0.0, 5.0)
        t_gone = rig.sample_t(st)
        assert rig.wait_status(lambda s: rig.sample_t(s) >= t_gone + 0.005, 10.0)  # not waiting for the dead
        rig.start("load")
        assert rig.wait_status(lambda s: s["neighbours"]["load"]["alive"] and s["reference"] == "neighbours", 30.0)
        rig.close()
        log = rig.daemon_log()
        kinds = [e["kind"] for e in read_messages(log, "/events")]
        assert "neighbour_gone" in kinds and "neighbour_alive" in kinds
        # every tick the core did not step (no reference) answered du/dt = 0
        held = {z["seq"] for z in read_messages(log, "/z_in") if not z["stepped"]}
        assert held and all(c["du_dt"] == 0.0 for c in read_messages(log, "/cmd") if c["seq"] in held)


def test_router_restart_sessions_reconnect_and_the_loop_continues(tmp_path):
    with Rig(scn(), tmp_path, router=True, duration_s=5.0) as rig:
        rig.start("router")
        st = running(rig)
        rig.signal("router", signal.SIGKILL)
        ticks = rig.status(timeout_s=0.3)
        assert ticks is None  # nobody to route the query
        rig.start("router")
        st2 = rig.wait_status(lambda s: rig.sample_t(s) >= rig.sample_t(st) + 0.02, 60.0)
        assert st2 and st2["loop"]["ticks"] > st["loop"]["ticks"]
        assert st2["rejected"] == {}


def file_size_cap(limit: int):
    """preexec_fn: files of the process and its children stop growing at ``limit`` bytes (EFBIG), as on a full
    disk. It also bounds the shared-memory ring (a file in /dev/shm): 1024 slots of 128 B."""
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


def test_log_directory_filling_up_mid_run_degrades_logging_not_control(tmp_path):
    limit = 400_000
    with Rig(scn(), tmp_path, duration_s=30.0, comp={"log_queue": 1024}) as rig:
        rig.start("daemon", popen={"preexec_fn": file_size_cap(limit)})
        rig.start("load")
        rig.start("plant")
        st = rig.wait_status(lambda s: (s.get("logging") or {}).get("state") == "degraded", 120.0)
        assert st, rig.status()
        assert "too large" in st["logging"]["error"].lower()
        t_fail = rig.sample_t(st)
        st2 = rig.wait_status(lambda s: rig.sample_t(s) >= t_fail + 0.01, 30.0)
        assert st2 and st2["state"] == "active"  # control went on
        rig.close()
        log = rig.daemon_log()
        assert log.stat().st_size <= limit
        assert len(read_messages(log, "/cmd")) > 0  # what was written before stays readable


def test_no_room_for_the_recorder_at_start_degrades_logging_not_control(tmp_path):
    with Rig(scn(), tmp_path, duration_s=30.0, comp={"log_queue": 1024}) as rig:
        st = running(rig, 0.01, popen={"preexec_fn": file_size_cap(64_000)})  # not even the ring fits
        assert st["state"] == "active"
        assert st["logging"]["state"] == "degraded" and "recorder could not start" in st["logging"]["error"]


def test_a_recorder_whose_process_dies_at_once_finishes_its_file_and_exits(tmp_path):
    """The recorded process dies before its recorder has even started (SIGKILL right after spawning): the
    orphan must still drain the ring, close a readable file and exit, not idle forever."""
    import os
    import subprocess
    import sys

    from conftest import ROOT

    from clients.live import wait_until

    out = tmp_path / "orphan.mcap"
    code = (f"import os, sys; sys.path.insert(0, {str(ROOT)!r})\n"
            "from service.logio.ring import RingRecorder\nfrom schemas.codec import CMD\n"
            f"r = RingRecorder({str(out)!r}, {{'a/cmd': ('energyctl.Command', CMD)}}, {{}})\n"
            "for k in range(100): r.offer('a/cmd', k * 1e-4, (k, k * 1e-4, 0.0, 0.0, False))\n"
            "print(r.pid, flush=True)\nos._exit(0)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    pid = int(p.stdout.strip())

    def gone() -> bool:
        try:
            os.kill(pid, 0)
            return False
        except ProcessLookupError:
            return True

    try:
        assert wait_until(gone, 20.0), "the orphaned recorder is still running"
    finally:
        if not gone():
            os.kill(pid, signal.SIGKILL)
    assert [m["seq"] for m in read_messages(out, "/cmd")] == list(range(100))
