"""Every process ours start ends with it, SIGKILL included: a SIGKILLed daemon left its forecast worker (46 MB) and
the multiprocessing resource tracker (13 MB) running for more than 9 minutes, and a SIGKILLed `energyctl demo` its
plant and load peers. The children now die with their parent (service.priority.die_with_parent)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest
from conftest import ROOT, SCENARIOS
from proc_tree import alive, below, command

from clients.live import child_env, wait_until
from service.daemon.bus import free_tcp_port

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and prctl: Linux")


def _kill(pids) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def test_a_sigkilled_daemons_forecast_worker_recorder_and_resource_tracker_end(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    argv = [sys.executable, "-m", "clients.cli", "run", "--config", str(SCENARIOS / "live" / "component.toml"),
            "--set", f'zenoh.listen=["{ep}"]', "--set", f'log_dir="{tmp_path}"']
    daemon = subprocess.Popen(argv, cwd=tmp_path, env=child_env(), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    kids: list[int] = []
    try:
        def started() -> bool:
            kids[:] = below(daemon.pid)
            cmds = [command(p) for p in kids]
            return (any("resource_tracker" in c for c in cmds)
                    and sum("spawn_main" in c for c in cmds) >= 2)  # the recorder's writer and the forecast worker

        assert wait_until(started, 60.0, every_s=0.1), [command(p) for p in kids]
        daemon.kill()
        daemon.wait(10.0)
        assert wait_until(lambda: not any(alive(p) for p in kids), 15.0, every_s=0.1), \
            [command(p) for p in kids if alive(p)]
    finally:
        _kill([daemon.pid, *kids])
        daemon.wait(10.0)


def test_a_sigkilled_energyctl_takes_the_energyctl_it_started_with_it(tmp_path):
    """clients.live.Processes (demo, the live rigs, the benches) starts each peer as a child energyctl that asks for
    SIGTERM when its parent dies; the parent here is SIGKILLed, so nothing of its own can stop them."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(f"""
        import sys, threading, time
        from clients.live import Processes
        procs = Processes()
        args = ["load", "--config", {str(SCENARIOS / "live" / "load.toml")!r}, "--set", 'pacing="realtime"',
                "--set", 'zenoh.connect=["{ep}"]', "--set", "duration_s=600"]
        procs.start("main-thread", args)
        t = threading.Thread(target=procs.start, args=("other-thread", args))  # a thread that ends at once
        t.start(); t.join()
        print(" ".join(str(p.pid) for _, p in procs.procs), flush=True)
        time.sleep(600)
    """))
    parent = subprocess.Popen([sys.executable, str(script)], cwd=ROOT, env=child_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, text=True)
    kids: list[int] = []
    try:
        kids = [int(p) for p in parent.stdout.readline().split()]
        assert len(kids) == 2
        assert wait_until(lambda: all(alive(p) for p in kids) and all("load" in command(p) for p in kids), 10.0)
        # the one started from a thread that ended is still there: it watches its parent, not that thread
        parent.kill()
        parent.wait(10.0)
        assert wait_until(lambda: not any(alive(p) for p in kids), 20.0, every_s=0.1), \
            [command(p) for p in kids if alive(p)]
    finally:
        _kill([parent.pid, *kids])
        parent.wait(10.0)
        parent.stdout.close()
