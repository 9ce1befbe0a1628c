"""A stop signal ends a process whose interpreter cannot run Python code (issue 28, item 2: a wedged bridge ignored
SIGINT and SIGTERM, because its 5 s alarm was armed by a Python handler that never ran); and what held it up is
on its stderr (every thread's stack, printed from C when the alarm fires)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from conftest import ROOT

from clients.live import SHUTDOWN_GRACE_S

WEDGED = """
import ctypes, signal, sys, threading
sys.setswitchinterval(1000.0)  # the GIL's holder keeps it until it blocks
from clients.live import install_stop_handlers

stop = threading.Event()
install_stop_handlers(stop)
libc = ctypes.PyDLL(None)  # a PyDLL call keeps the GIL: no other thread runs Python meanwhile


def hold_the_gil():
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM, signal.SIGALRM})
    print("holding", flush=True)
    libc.sleep(60)


threading.Thread(target=hold_the_gil, daemon=True).start()
stop.wait()
"""


def _sleeping_in_c(pid: int) -> bool:
    """One of the process's threads is in clock_nanosleep (x86-64 syscall 230; glibc's sleep) or nanosleep (35)."""
    from pathlib import Path

    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            if (task / "syscall").read_text().split()[0] in ("230", "35"):
                return True
        except (OSError, IndexError):
            pass
    return False


def test_sigterm_ends_a_process_whose_gil_is_held():
    pytest.importorskip("service._stopsignal")
    import platform

    if platform.machine() != "x86_64" or not os.path.exists("/proc/self/syscall"):
        pytest.skip("reads the syscall numbers of x86-64 Linux")
    from clients.live import wait_until

    p = subprocess.Popen([sys.executable, "-c", WEDGED], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert p.stdout.readline().strip() == "holding"
        assert wait_until(lambda: _sleeping_in_c(p.pid), 10.0)  # in libc's sleep, holding the GIL
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(SHUTDOWN_GRACE_S + 10)
        except subprocess.TimeoutExpired:
            pytest.fail("SIGTERM did not end a process whose GIL is held")
        assert p.returncode == -signal.SIGALRM  # the alarm armed in C at the SIGTERM, its default action
    finally:
        if p.poll() is None:
            p.kill()
        _, err = p.communicate()
    assert "in hold_the_gil" in err, err[-2000:]  # the stack of the thread that held the GIL


EXTENDED = """
import signal, sys, threading, time
from clients.live import SHUTDOWN_GRACE_S, install_stop_handlers
from service.priority import extend_stop_grace

extend_stop_grace()  # no stop yet: arms nothing
assert signal.alarm(0) == 0
stop = threading.Event()
install_stop_handlers(stop)
signal.raise_signal(signal.SIGTERM)
assert stop.wait(5.0)
t0 = time.monotonic()
extend_stop_grace(SHUTDOWN_GRACE_S + 2)  # as the recorder does while its writer makes progress
time.sleep(SHUTDOWN_GRACE_S + 1 - (time.monotonic() - t0))
print("alive past the grace", flush=True)
time.sleep(60)
"""


def test_a_stop_making_progress_outlives_the_grace_and_still_ends():
    """service.priority.extend_stop_grace (the recorder's writer still writing at a stop) moves a pending alarm on;
    the process still ends by it once nothing moves it any more."""
    p = subprocess.run([sys.executable, "-c", EXTENDED], capture_output=True, text=True, cwd=ROOT, timeout=60,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert "alive past the grace" in p.stdout, p.stderr[-2000:]
    assert p.returncode == -signal.SIGALRM, (p.returncode, p.stderr[-2000:])
