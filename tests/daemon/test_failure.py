"""A loop thread that ends by an unexpected exception fails the daemon visibly and safely (service.daemon.failure):
u held, nothing more published, the token withdrawn, state failed with the reason in status and on stderr, and
``energyctl run`` exits 1. Loopback, free ports, no multicast scouting; every process is stopped."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

from conftest import ROOT, SCENARIOS

from clients.live import _toml, child_env, configs_from_scenario, wait_until
from clients.peers.common import wait_alive
from schemas.codec import CMD, MEAS
from schemas.component import ComponentConfig, ZenohConfig, config_from_dict
from schemas.scenario import load_scenario
from service.daemon.bus import free_tcp_port, open_session
from service.daemon.daemon import Daemon


def component(ep: str) -> dict:
    """A sample-triggered daemon without neighbours (nothing to wait for), listening on ep."""
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, ep, lockstep=False, rate_hz=10000.0)
    comp.update(neighbours=[], forecast={"enabled": False})
    comp.pop("local_reference_W")
    return comp


def meas(k: int) -> bytes:
    return MEAS.encode(k, k * 1e-4, 15.0, 80.0, 80.15, 15.0)


def test_an_exception_in_the_loop_holds_u_publishes_nothing_more_and_says_failed(monkeypatch):
    d = Daemon(config_from_dict(ComponentConfig, component(f"tcp/127.0.0.1:{free_tcp_port()}")))
    d.open()
    loop = None
    try:
        d._fast = None  # the Python tick, whose core step we break
        step = d.core.step_values

        def breaks_at_3(seq, *args):
            if seq == 3:
                raise RuntimeError("injected")
            return step(seq, *args)

        monkeypatch.setattr(d.core, "step_values", breaks_at_3)
        got = []
        sub = d.session.declare_subscriber("energyctl/source/cmd",
                                           lambda m: got.append(CMD.decode(m.payload.to_bytes())))
        pub = d.session.declare_publisher("energyctl/source/meas")
        loop = threading.Thread(target=d.run_loop, daemon=True)
        loop.start()
        assert wait_until(lambda: d.token is not None, 10.0)
        for k in range(3):
            pub.put(meas(k))
            assert wait_until(lambda k=k: len(got) == k + 1, 5.0)
        pub.put(meas(3))
        loop.join(5.0)
        assert not loop.is_alive()  # the loop ended ...
        assert wait_until(lambda: len(got) == 4, 5.0)
        assert [c[0] for c in got] == [0, 1, 2, 3]
        assert got[3] == (3, 3 * 1e-4, 0.0, 0.0, 1)  # ... holding u for the sample it was on
        assert d.token is None  # withdrawn: a plant or a coordinator sees the controller gone
        st = d.status()
        assert st["state"] == "failed"
        assert st["failure"].startswith("loop: RuntimeError: injected (at test_failure.py:")
        ok, body = d.apply_sets(["controller.K_per_s=100"])
        assert not ok and body["error"].startswith("the loop failed")
        pub.put(meas(4))  # nothing answers any more
        assert not wait_until(lambda: len(got) > 4, 0.3)
        sub.undeclare()
    finally:
        d.stop()
        if loop is not None:
            loop.join(5.0)
        d.close()
    assert d.state == "failed"  # closing does not paper over it


FAILING_RUN = """
import sys
from clients.commands.run import run_daemon
from schemas.component import ComponentConfig, load_config
from service.daemon.daemon import Daemon

def tick(self, payload, now):  # the loop's first tick raises: what any bug in it would do
    raise ZeroDivisionError("injected")

Daemon._tick = tick
sys.exit(run_daemon(load_config(ComponentConfig, sys.argv[1], []), sys.argv[2]))
"""


def test_energyctl_run_exits_1_with_the_reason_when_its_loop_fails(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    path = tmp_path / "c.toml"
    path.write_text(_toml(component(ep)))
    stats = tmp_path / "status.json"
    p = subprocess.Popen([sys.executable, "-c", FAILING_RUN, str(path), str(stats)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT, env=child_env())
    try:
        with open_session(ZenohConfig(mode="peer", connect=[ep])) as s:
            assert wait_alive(s, "energyctl/source/alive", 20.0, threading.Event())
            pub = s.declare_publisher("energyctl/source/meas")
            out, err = "", ""
            for _ in range(100):  # until it is routed and taken (the first one that arrives fails the loop)
                pub.put(meas(0))
                try:
                    out, err = p.communicate(timeout=0.2)
                    break
                except subprocess.TimeoutExpired:
                    continue
        assert p.returncode == 1, err[-2000:]
        assert "energyctl[source]: failed: loop: ZeroDivisionError: injected" in err
        assert "Traceback" in err and "energyctl run: source failed, control stopped" in err
        assert json.loads(out.strip().splitlines()[-1])["state"] == "failed"
        status = json.loads(stats.read_text())
        assert status["state"] == "failed" and status["failure"].startswith("loop: ZeroDivisionError: injected")
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()


def test_the_forecast_thread_counts_a_box_it_cannot_forecast_and_fails_the_daemon_on_anything_else():
    """A neighbour's box of finite values can be beyond the forecast's arithmetic (widening 1e308 overflows): an
    error counted in status, the thread goes on. Any other exception out of it is the component's failure, and it
    stops the loop (on_failure), which then takes the safe state."""
    from service.daemon.failure import Failure
    from service.daemon.forecast_worker import ForecastWorker

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    failure, stopped = Failure("test"), threading.Event()
    fw = ForecastWorker(scn.model, 1e-4, 2, ComponentConfig.model_fields["forecast"].default, 0.02,
                        failure=failure, on_failure=stopped.set)
    fw._thread.start()  # no worker process: these requests never reach it
    try:
        fw.request(3, (0.0, 1.7976931348623157e308, -1.0, 1.0), scn.controller)
        assert wait_until(lambda: fw.errors == 1, 5.0)
        assert fw.last_error.startswith("window 3: box") and "OverflowError" in fw.last_error
        assert fw._thread.is_alive() and not failure

        def broken(*args):
            raise KeyError("a bug")

        fw._answer = broken
        fw.request(4, (0.0, 1.0, -1.0, 1.0), scn.controller)
        assert wait_until(stopped.is_set, 5.0)
        assert failure.reason.startswith("forecast: KeyError: 'a bug'") and not fw._thread.is_alive()
    finally:
        fw.close()
