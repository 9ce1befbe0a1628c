"""A stop signal ends a process whose interpreter cannot run Python code (issue 28, item 2: a wedged bridge ignored
SIGINT and SIGTERM, because its 5 s alarm was armed by a Python handler that never ran)."""

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

    p = subprocess.Popen([sys.executable, "-c", WEDGED], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
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
        p.communicate()
