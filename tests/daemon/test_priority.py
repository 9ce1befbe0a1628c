"""Process priorities (service/priority.py): control above, the recorder and forecast processes below."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest
from conftest import ROOT, SCENARIOS

from schemas.codec import MEAS
from schemas.scenario import OutgoingForecastConfig, load_scenario
from service import priority
from service.priority import FORECAST_NICE, RECORDER_NICE


def nice_of(pid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, pid)


def in_new_process(lines: list[str]) -> subprocess.CompletedProcess:
    """Run Python lines in a fresh interpreter (priorities set there do not leak into the test process)."""
    res = subprocess.run([sys.executable, "-c", "\n".join(lines)], cwd=ROOT, capture_output=True, text=True,
                         timeout=30)
    assert res.returncode == 0, res.stderr
    return res


def test_background_processes_run_below_the_process_that_starts_them(tmp_path):
    """The recorder's writer and the forecast worker lower themselves to their own level whatever their parent
    runs at (spawned processes inherit the parent's nice value, which a realtime daemon raises)."""
    from service.daemon.forecast_worker import ForecastWorker
    from service.logio.ring import RingRecorder

    rec = RingRecorder(tmp_path / "x.mcap", {"m": ("energyctl.Measurement", MEAS)}, {})
    fw = ForecastWorker(load_scenario(SCENARIOS / "paper-feasibility.toml").model, 1e-4, 0,
                        OutgoingForecastConfig(enabled=True), 1.0)
    try:
        assert rec.wait_ready()
        fw.start()  # returns once its process has run its initializer and answered
        parent = nice_of(0)
        assert nice_of(rec.pid) == max(parent, RECORDER_NICE)
        (pid,) = list(fw._pool._processes)
        assert nice_of(pid) == max(parent, FORECAST_NICE) and nice_of(pid) > nice_of(rec.pid)
    finally:
        fw.close()
        rec.close()


def test_a_stopping_recorders_writer_is_raised_to_the_recorded_process_priority(tmp_path):
    """At its stop the writer drains the rest of the ring at the recorded process's own priority (at nice 10 beside
    a busy loop that took seconds, past the stop's grace); where the process may not lower a nice value, hurry says
    so and the writer stays where it is."""
    from service.logio.ring import RingRecorder

    rec = RingRecorder(tmp_path / "x.mcap", {"m": ("energyctl.Measurement", MEAS)}, {})
    try:
        assert rec.wait_ready()
        parent = nice_of(0)
        if parent >= RECORDER_NICE:
            pytest.skip(f"this process runs at nice {parent}, no higher than the writer's {RECORDER_NICE}")
        assert nice_of(rec.pid) == RECORDER_NICE
        raised = priority.hurry(rec.pid)
        tids = [int(t) for t in os.listdir(f"/proc/{rec.pid}/task")]
        if raised:
            assert [nice_of(t) for t in tids] == [parent] * len(tids)
        else:  # unprivileged: refused, nothing moved
            assert nice_of(rec.pid) == RECORDER_NICE
    finally:
        rec.close()


def _long_job(s: float) -> float:
    import time

    time.sleep(s)
    return s


def test_closing_a_forecast_worker_does_not_wait_for_the_forecast_in_flight():
    """A forecast in flight is moot at a stop: close ends the worker process, which a 60 s job would otherwise hold
    for a minute (at nice 19 beside other work a 40 ms forecast took seconds, past the stop's grace)."""
    import time

    from service.daemon.forecast_worker import ForecastWorker

    fw = ForecastWorker(load_scenario(SCENARIOS / "paper-feasibility.toml").model, 1e-4, 0,
                        OutgoingForecastConfig(enabled=True), 1.0)
    fw.start()
    (proc,) = list(fw._pool._processes.values())
    job = fw._pool.submit(_long_job, 60.0)
    while not job.running():  # taken by the worker (the call queue holds one more than the workers)
        time.sleep(0.01)
    t0 = time.monotonic()
    fw.close()
    assert time.monotonic() - t0 < 30.0 and not proc.is_alive() and fw._pool is None
    assert job.done() and job.exception() is not None  # ended with its worker, never finished


def test_a_configured_nice_value_reaches_the_threads_started_after_it():
    """set_nice in the main thread before anything starts: a thread started afterwards (as Zenoh's are) runs at
    that priority too (Linux keeps nice per thread and a new thread inherits its creator's)."""
    res = in_new_process(["import os, threading",
                          "from service.priority import set_nice",
                          "assert set_nice(5) is None",
                          "out = []",
                          "t = threading.Thread(target=lambda: out.append(os.getpriority(os.PRIO_PROCESS, 0)))",
                          "t.start(); t.join()",
                          "print(os.getpriority(os.PRIO_PROCESS, 0), out[0])"])
    assert res.stdout.split() == ["5", "5"]


def test_a_refused_priority_is_said_and_not_fatal(monkeypatch):
    """Without CAP_SYS_NICE raising priority fails: set_nice says why in one line and leaves the priority."""
    before = nice_of(0)

    def refuse(*_a):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "setpriority", refuse)
    msg = priority.set_nice(before - 5)
    assert msg is not None and "CAP_SYS_NICE" in msg and f"running at nice {before}" in msg
    assert nice_of(0) == before
    assert priority.set_nice(None) is None and priority.set_nice(before) is None  # nothing to do: no message


def test_run_says_once_that_it_could_not_raise_its_priority():
    """energyctl run/plant/load where raising priority is refused (no CAP_SYS_NICE; simulated, since the tests
    run as root): one stderr line naming the value, and the process goes on at its own priority."""
    res = in_new_process(["import os",
                          "def refuse(*a): raise PermissionError(1, 'Operation not permitted')",
                          "os.setpriority = refuse",
                          "from clients.live import start_process",
                          "from schemas.component import ComponentConfig",
                          "stop = start_process(ComponentConfig(id='x', nice=-5), 'run')",
                          "print(os.getpriority(os.PRIO_PROCESS, 0), stop.is_set())"])
    assert res.stderr.count("energyctl run: cannot set nice -5") == 1
    assert res.stdout.split() == [str(nice_of(0)), "False"]


def test_the_recorders_writer_runs_on_the_cpus_it_is_given(tmp_path):
    """log_writer_cpus keeps the writer process off the loop's CPU; a CPU the machine lacks is a config error
    naming the field."""
    import pytest
    from pydantic import ValidationError

    from schemas.component import ComponentConfig
    from service.logio.ring import RingRecorder

    have = sorted(os.sched_getaffinity(0))
    if len(have) < 2:
        pytest.skip("needs two CPUs")
    rec = RingRecorder(tmp_path / "x.mcap", {"m": ("energyctl.Measurement", MEAS)}, {}, writer_cpus=[have[-1]])
    try:
        assert rec.wait_ready()
        assert os.sched_getaffinity(rec.pid) == {have[-1]}
    finally:
        rec.close()
    with pytest.raises(ValidationError, match="log_writer_cpus"):
        ComponentConfig.model_validate({"id": "a", "log_writer_cpus": [max(have) + 100]})


def test_a_configured_timer_slack_reaches_later_threads_and_the_background_processes_get_the_default_back(tmp_path):
    """timer_slack_ns is set first thing, like nice: a thread started afterwards (as Zenoh's and the loop's are)
    has it; the recorder's writer, spawned from it, goes back to the kernel's 50 us, and so does a process that
    calls background."""
    if priority.timer_slack_ns() is None:
        import pytest

        pytest.skip("no timer slack here (Linux prctl)")
    res = in_new_process(["import os, threading",
                          "from clients.live import start_process",
                          "from schemas.codec import MEAS",
                          "from schemas.component import ComponentConfig",
                          "from service import priority",
                          "from service.logio.ring import RingRecorder",
                          "stop = start_process(ComponentConfig(id='x', timer_slack_ns=2000), 'run')",
                          "seen = []",
                          "t = threading.Thread(target=lambda: seen.append(priority.timer_slack_ns()))",
                          "t.start(); t.join()",
                          f"rec = RingRecorder({str(tmp_path / 'x.mcap')!r}, "
                          "{'m': ('energyctl.Measurement', MEAS)}, {})",
                          "assert rec.wait_ready()",
                          "p = f'/proc/{rec.pid}/timerslack_ns'",
                          "writer = open(p).read().strip() if os.access(p, os.R_OK) else '50000'",
                          "rec.close()",
                          "priority.background(10)",
                          "print(seen[0], writer, priority.timer_slack_ns())"])
    assert res.stdout.split() == ["2000", str(priority.DEFAULT_TIMER_SLACK_NS), str(priority.DEFAULT_TIMER_SLACK_NS)]
    assert res.stderr == ""


def test_a_timer_slack_the_system_refuses_is_one_line_not_an_error():
    from unittest import mock

    with mock.patch.object(priority, "_prctl", return_value=None):
        assert "cannot set timer slack 1000 ns" in priority.set_timer_slack(1000)
        assert priority.timer_slack_ns() is None
    before = priority.timer_slack_ns()
    assert priority.set_timer_slack(None) is None and priority.set_timer_slack(0) is None  # 0: leave it
    assert priority.timer_slack_ns() == before


def test_a_process_kept_to_cpus_keeps_the_threads_and_processes_it_starts_there():
    """set_cpus (a process's `cpus` config, applied first thing): the threads started afterwards, Zenoh's runtime
    included, inherit the affinity (processes it spawns do too: Linux's rule); a CPU the machine does not have is
    refused by the config, naming the field. Needs two CPUs to show anything."""
    import pytest

    from schemas.component import ComponentConfig

    have = sorted(os.sched_getaffinity(0))
    if len(have) < 2:
        pytest.skip("one CPU: nothing to keep to")
    one = have[-1]
    res = in_new_process([
        "import json, os, threading",
        "from service.priority import set_cpus",
        f"assert set_cpus([{one}]) is None",
        "seen = []",
        "t = threading.Thread(target=lambda: seen.append(sorted(os.sched_getaffinity(0)))); t.start(); t.join()",
        "import zenoh",
        "cfg = zenoh.Config(); cfg.insert_json5('scouting/multicast/enabled', 'false')",
        "s = zenoh.open(cfg)",
        "tasks = [int(x) for x in os.listdir('/proc/self/task')]",
        "print(json.dumps({'thread': seen[0], 'tasks': [sorted(os.sched_getaffinity(x)) for x in tasks]}))",
        "s.close()",
    ])
    import json

    out = json.loads(res.stdout)
    assert out["thread"] == [one]
    assert len(out["tasks"]) > 3  # Zenoh's runtime threads exist ...
    assert all(t == [one] for t in out["tasks"])  # ... and every one of them is on that CPU
    with pytest.raises(ValueError, match="cpus"):
        ComponentConfig.model_validate({"id": "a", "cpus": [max(have) + 64]})


def test_realtime_stacks_take_cpus_per_role():
    from clients.live import configs_from_scenario
    from clients.options import role_cpus

    cpus = role_cpus("controller=1,plant=0+1")
    assert cpus == {"controller": [1], "plant": [0, 1]}
    if not {0, 1} <= os.sched_getaffinity(0):
        return
    comp, plant, load = configs_from_scenario(load_scenario(SCENARIOS / "paper-varying-load.toml"),
                                              "tcp/127.0.0.1:1", False, 1000.0, cpus=cpus)
    assert comp["cpus"] == [1] and plant["cpus"] == [0, 1] and "cpus" not in load


MMAP_PROBE = """
import ctypes, sys
from service.priority import set_mmap_threshold

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
print(set_mmap_threshold(int(sys.argv[1])))
big = libc.malloc(4 << 20)
libc.free(big)  # glibc's dynamic threshold rises to 4 MiB here
before = libc.mallinfo2().hblks
block = libc.malloc(1 << 20)
print(libc.mallinfo2().hblks - before)  # 1: the block has its own mapping; 0: it came from an arena
libc.free(block)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_a_fixed_mmap_threshold_keeps_large_blocks_out_of_the_arenas():
    """glibc raises its mmap threshold to the size of each mapped block freed; after a 4 MiB block, a 1 MiB one comes
    from an arena (and its pages stay resident). Fixed at 128 KiB, the 1 MiB block gets its own mapping, returned to
    the system when freed. 0 leaves glibc's behaviour."""
    def probe(nbytes: int) -> list[str]:
        out = subprocess.run([sys.executable, "-c", MMAP_PROBE, str(nbytes)], capture_output=True, text=True,
                             timeout=30, cwd=ROOT, check=True)
        return out.stdout.split()

    assert probe(128 * 1024) == ["None", "1"]
    assert probe(0) == ["None", "0"]


TUPLE_PROBE = """
import sys
from service.priority import TUPLE_FREE_LIST_SIZES, fill_tuple_free_lists
if sys.argv[1] == "fill":
    fill_tuple_free_lists()
def burst():
    # more tuples of every length alive at once than ever before, then all freed: CPython keeps the freed ones (up
    # to 2000 a length) in its free lists, allocated, as the daemon's forecast windows did a few a second
    held = [[tuple(range(n)) for _ in range(2500)] for n in TUPLE_FREE_LIST_SIZES]
    del held
before = sys.getallocatedblocks()
burst()
print(sys.getallocatedblocks() - before)
"""


@pytest.mark.skipif(platform.python_implementation() != "CPython", reason="CPython's tuple free lists")
def test_filled_tuple_free_lists_keep_the_allocated_blocks_from_growing():
    """A fresh interpreter's tuple free lists are nearly empty and fill as tuples are freed: a burst leaves ~2000
    tuples of each length allocated. After fill_tuple_free_lists (what the daemon does before its loop) the same
    burst leaves nothing: the free lists were full already."""
    def grown(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", TUPLE_PROBE, mode], capture_output=True, text=True, timeout=60,
                             cwd=ROOT, check=True)
        return int(out.stdout.split()[-1])

    lengths = len(priority.TUPLE_FREE_LIST_SIZES)
    assert grown("no") > 0.9 * lengths * priority.TUPLE_FREE_LIST_MAX  # the growth the fill takes up front
    assert abs(grown("fill")) < 100


def test_a_background_process_started_from_a_realtime_one_starts_and_stays_off_sched_fifo():
    """A daemon run under chrt -f starts its forecast worker: a child inherits its forking thread's SCHED_FIFO,
    which nice does not lower (across hosts a worker importing for a second at FIFO starved its daemon's Zenoh
    threads until the daemon's liveliness token lapsed). Spawned from in_normal_thread it starts at SCHED_OTHER;
    spawned directly it starts at FIFO (what this guards against); background() leaves FIFO too. Needs the right to
    set SCHED_FIFO; skips without."""
    child = "import os; print(os.sched_getscheduler(0))"
    res = in_new_process(["import os, subprocess, sys",
                          "from service.priority import background, in_normal_thread",
                          "try:",
                          "    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))",
                          "except PermissionError:",
                          "    print('no-rt'); raise SystemExit(0)",
                          f"run = lambda: subprocess.run([sys.executable, '-c', {child!r}], capture_output=True, "
                          "text=True).stdout.strip()",
                          "print(run(), in_normal_thread(run), os.sched_getscheduler(0))",
                          "background(10)",
                          "print(os.sched_getscheduler(0) == os.SCHED_OTHER, os.getpriority(os.PRIO_PROCESS, 0))"])
    if res.stdout.strip() == "no-rt":
        pytest.skip("no permission to set SCHED_FIFO here")
    direct, normal, caller, *after = res.stdout.split()
    assert (int(direct), int(normal), int(caller)) == (os.SCHED_FIFO, os.SCHED_OTHER, os.SCHED_FIFO), res.stdout
    assert after == ["True", "10"], res.stdout
