from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.scenario import load_scenario, scenario_from_dict
from service.core.energy import RLCEnergy

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "scenarios"
DATA = ROOT / "tests" / "data"  # files the tests read (a log recorded by an earlier release)

# an ideal setting: no noise, no delay, exact model; the paper's law (fblc), whose claims most tests check; a test
# of the default law says controller={"kind": "nested", ...}
IDEAL = {"timing": {"control_rate_hz": 10000.0, "plant_step_s": 1e-5, "duration_s": 0.1},
         "controller": {"kind": "fblc"}}


def scenario(**sections):
    """Scenario from nested keyword sections on top of IDEAL, e.g. scenario(load={'value': 900.0})."""
    data = {k: dict(v) for k, v in IDEAL.items()}
    for k, v in sections.items():
        if isinstance(v, dict) and isinstance(data.get(k), dict):
            data[k].update(v)
        else:
            data[k] = v
    return scenario_from_dict(data)


def exact_energy_along(trace: dict, R: float, L: float, C: float, Pdot: np.ndarray | None = None):
    """RLCEnergy quantities along a simulated trace, with exact derivatives from the circuit equations."""
    n = len(trace["t"])
    Pdot = np.zeros(n) if Pdot is None else Pdot
    cols = {k: np.zeros(n) for k in RLCEnergy.__slots__}
    cols["di"] = np.zeros(n)
    cols["dv"] = np.zeros(n)
    e = RLCEnergy()
    for k in range(n):
        i, v, u, i2 = trace["i"][k], trace["v"][k], trace["u"][k], trace["i_load"][k]
        P = trace["P_l"][k]
        r = trace["du_dt_applied"][k]
        di = (u - R * i - v) / L
        dv = (i - i2) / C
        di2 = Pdot[k] / v - P * dv / (v * v)
        e.update(R, L, C, i, v, u, i2, di, dv, r, di2)
        for key in RLCEnergy.__slots__:
            cols[key][k] = getattr(e, key)
        cols["di"][k], cols["dv"][k] = di, dv
    return cols


@pytest.fixture
def paper_files():
    return sorted(SCENARIOS.glob("paper-*.toml"))


@pytest.fixture
def daemon_by_hand():
    """An opened daemon (loopback session, no peers) whose loop we drive by hand through _tick."""
    from clients.live import configs_from_scenario
    from schemas.component import ComponentConfig, config_from_dict
    from service.daemon.bus import free_tcp_port
    from service.daemon.daemon import Daemon

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=10000.0)
    comp["neighbour_stale_s"] = 10.0
    comp["loop"]["trigger"] = "clock"
    comp["forecast"] = {"enabled": False}  # no worker process: these tests feed samples, not windows
    comp.pop("local_reference_W")  # the daemon's own default (hold), not the realtime stacks' "measured"
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    nb = d.neighbours[0]
    nb.count, nb.P, nb.rx_ns = 1, 1200.0, 0
    try:
        yield d
    finally:
        d.close()


class RingStub:
    """A Zenoh ring channel's stand-in (a neighbour's subscriber, polled by the loop with try_recv): hands out the
    given payloads one per call, oldest first, then None."""

    def __init__(self, payloads):
        self.items = list(payloads)

    def try_recv(self):
        if not self.items:
            return None
        b = self.items.pop(0)
        return type("Sample", (), {"payload": type("Payload", (), {"to_bytes": lambda self: b})()})()


class QueryStub:
    """A Zenoh query's stand-in for code that answers queries: keeps the one answer (("ok" | "err", JSON body)),
    the key it was given on, and whether it was dropped; ``n`` tells stubs apart."""

    def __init__(self, n: int = 0):
        self.n, self.got, self.key, self.dropped = n, None, None, False

    def reply(self, key, body):
        import json

        self.got, self.key = ("ok", json.loads(body)), str(key)

    def reply_err(self, body):
        import json

        self.got = ("err", json.loads(body))

    def drop(self):
        self.dropped = True


class PumpingClient:
    """A blocking WebSocket test client (the Foxglove tests'): ``pump`` reads messages into ``_take`` until a
    condition holds; subclasses set ``ws`` and ``_take``, and ``PUMP_TIMEOUT_S``."""

    PUMP_TIMEOUT_S = 5.0

    def pump(self, pred, timeout_s: float | None = None) -> bool:
        """Reads messages until pred() holds or timeout_s (default PUMP_TIMEOUT_S) passes."""
        import time

        deadline = time.monotonic() + (self.PUMP_TIMEOUT_S if timeout_s is None else timeout_s)
        while not pred():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                self._take(self.ws.recv(timeout=left))
            except TimeoutError:
                return pred()
        return True


# ---- a hung test must fail the run with its stacks, not hold CI until its time limit ----------------------------
# CI once ran out of its 90 minutes with nothing printed after the 40th test (pytest's output to a pipe is
# block-buffered, so the rest was lost with the process). Now:
# - every test gets TEST_TIMEOUT_S: past it the stacks of every thread and the processes the run started are
#   printed, those processes killed, and pytest exits 3; progress is flushed after each test;
# - the same EXIT_TIMEOUT_S after the summary if the interpreter's exit hangs (leftover threads, pools, queues);
# - where the hung call holds the GIL (the watchdog threads then never run), faulthandler prints the stacks from C
#   30 s later and exits 1, and a guard process started with the session kills what pytest leaves behind (a child
#   left running would hold CI's output pipe open).
# 0 or inf turns a timeout off.

TEST_TIMEOUT_S = float(__import__("os").environ.get("ENERGYCTL_TEST_TIMEOUT_S", "600"))
EXIT_TIMEOUT_S = float(__import__("os").environ.get("ENERGYCTL_TEST_EXIT_TIMEOUT_S", "120"))
BACKSTOP_S = 30.0  # faulthandler's dump and exit, after a watchdog thread that did not get to run

def _on(timeout_s: float) -> bool:
    import math

    return 0 < timeout_s < math.inf


def _descendants() -> list[tuple[int, str]]:
    """(pid, command line) of every live process below this one, the guard excepted."""
    import os

    from proc_tree import below, command

    return [(pid, command(pid)) for pid in below(os.getpid(), tuple(_GUARD_PID))]


_STDERR_FD: list[int] = []  # a dup of the terminal's stderr, taken before any test captures fd 2
_GUARD_PID: list[int] = []


def pytest_configure(config):
    import os
    import subprocess
    import sys

    _STDERR_FD.append(os.dup(2))
    if os.path.isdir("/proc"):
        g = subprocess.Popen([sys.executable, str(Path(__file__).with_name("proc_tree.py")), str(os.getpid())],
                             stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        _GUARD_PID.append(g.pid)


def _say(text: str) -> None:
    import os

    os.write(_STDERR_FD[0] if _STDERR_FD else 2, text.encode(errors="replace"))


def _report_and_kill(what: str) -> None:
    """Stacks of every thread and the process tree below this one to the terminal's stderr; those processes
    killed (one left running would hold CI's output pipe open after pytest is gone)."""
    import faulthandler
    import os
    import signal

    _say(f"\n\n===== {what}: stacks of every thread =====\n")
    faulthandler.dump_traceback(file=_STDERR_FD[0] if _STDERR_FD else 2, all_threads=True)
    procs = _descendants()
    _say(f"===== processes this run started and left running: {len(procs)} =====\n")
    for pid, cmd in procs:
        _say(f"  {pid}: {cmd[:300]}\n")
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


def _watchdog(timeout_s: float, what: str, flush):
    """A daemon thread that, unless the returned event is set within timeout_s, reports, kills and exits 3; and
    faulthandler's dump-and-exit BACKSTOP_S later for a hang that holds the GIL. Returns the event (None: off)."""
    import faulthandler
    import os
    import threading

    if not _on(timeout_s):
        return None
    done = threading.Event()

    def watch() -> None:
        if done.wait(timeout_s):
            return
        _report_and_kill(f"{what} after {timeout_s:g} s")
        try:
            flush()
        finally:
            os._exit(3)

    threading.Thread(target=watch, name="test-watchdog", daemon=True).start()
    faulthandler.dump_traceback_later(timeout_s + BACKSTOP_S, exit=True, file=_STDERR_FD[0] if _STDERR_FD else 2)
    return done


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    import faulthandler

    tw = item.config.get_terminal_writer()
    done = _watchdog(TEST_TIMEOUT_S, f"{item.nodeid} still running", tw.flush)
    try:
        yield
    finally:
        if done is not None:
            done.set()
            faulthandler.cancel_dump_traceback_later()
        tw.flush()


def pytest_unconfigure(config):
    """After the summary: say what is still running (it would hold the interpreter's exit), and arm the exit's
    watchdog."""
    import sys
    import threading

    alive = [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    procs = [(p, c) for p, c in _descendants() if "resource_tracker" not in c]  # that one ends with us
    if alive or procs:
        _say("\nleft running at the end of the tests (the exit waits for them): "
             f"threads {[t.name for t in alive]}, processes {[(p, c[:120]) for p, c in procs]}\n")
    sys.stdout.flush()
    _watchdog(EXIT_TIMEOUT_S, "the interpreter has not exited", sys.stdout.flush)
