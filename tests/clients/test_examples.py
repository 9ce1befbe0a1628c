"""The examples/ peers, written only against docs/protocol.md, against the installed daemon, on loopback.

The daemon runs `energyctl run --config examples/component.toml` with its endpoint moved to a free loopback port;
the lockstep plant example drives it for 0.5 s; the status client then asks, sets and is refused. Every process is
stopped whatever happens (SIGTERM, then SIGKILL)."""

from __future__ import annotations

import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def energyctl() -> list[str]:
    """The installed energyctl command (its console-script entry point if the script is not on PATH)."""
    exe = shutil.which("energyctl")
    if exe:
        return [exe]
    code = ("import sys, importlib.metadata as m; "
            "sys.exit([e for e in m.entry_points(group='console_scripts') if e.name == 'energyctl'][0].load()())")
    return [sys.executable, "-c", code]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def wait_until(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)  # a poll interval, not a synchronisation: the condition decides
    return pred()


def stop(p: subprocess.Popen, grace_s: float = 5.0) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(grace_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5.0)


def client(endpoint: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(EXAMPLES / "status_client.py"), "--connect", endpoint, *args],
                          capture_output=True, text=True, timeout=20)


def test_the_examples_regulate_and_query_the_daemon(tmp_path):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cmd = [*energyctl(), "run", "--config", str(EXAMPLES / "component.toml"),
           "--set", f'zenoh.listen=["{endpoint}"]', "--set", "zenoh.multicast_scouting=false"]
    with open(tmp_path / "daemon.out", "w") as so, open(tmp_path / "daemon.err", "w") as se:
        daemon = subprocess.Popen(cmd, stdout=so, stderr=se, cwd=ROOT)
    plant = None

    def daemon_log() -> str:
        return (tmp_path / "daemon.err").read_text(errors="replace")[-2000:]

    try:
        assert wait_until(lambda: listening(port) or daemon.poll() is not None, 15.0), daemon_log()
        assert daemon.poll() is None, f"the daemon exited ({daemon.returncode}): {daemon_log()}"
        plant = subprocess.Popen([sys.executable, str(EXAMPLES / "lockstep_plant.py"), "--connect", endpoint,
                                  "--id", "source", "--neighbour", "load", "--seconds", "0.5"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            out, err = plant.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the plant did not finish within 30 s; daemon: {daemon_log()}")
        assert plant.returncode == 0, f"plant: {err[-2000:]}\n{out[-2000:]}\ndaemon: {daemon_log()}"
        res = json.loads(out.strip().splitlines()[-1])
        assert res["samples"] == res["commands"] == 5000 and res["timeouts"] == 0 and res["rejected"] == 0, res
        assert res["max_dev_after_50ms_pct"] <= 2.0, res  # v within +-2 % of v_ref after 50 ms
        assert 0.5 * 80.0 < res["v_min"] <= res["v_max"] < 1.5 * 80.0, res

        # status: answered, and it saw every sample with nothing rejected
        st = client(endpoint, "status")
        assert st.returncode == 0, st.stderr
        status = json.loads(st.stdout)
        assert status["id"] == "source" and status["loop"]["ticks"] >= 5000, status["loop"]
        assert status["rejected"] == {} and status["loop"]["lockstep_timeouts"] == 0
        assert status["neighbours"]["load"]["messages"] >= 5000
        # a valid set is applied, and config says so
        ok = client(endpoint, "set", "controller.K_per_s=1500")
        assert ok.returncode == 0, ok.stderr
        ans = json.loads(ok.stdout)
        assert ans["controller"]["K_per_s"] == 1500.0 and ans["config_version"] == status["config_version"] + 1
        cfg = client(endpoint, "config")
        assert cfg.returncode == 0 and json.loads(cfg.stdout)["controller"]["K_per_s"] == 1500.0, cfg.stderr
        # an invalid value is refused with an error naming the field, and nothing changes
        bad = client(endpoint, "set", "controller.K_per_s=-1")
        assert bad.returncode == 1 and "K_per_s" in bad.stderr, (bad.returncode, bad.stderr)
        again = client(endpoint, "config")
        assert json.loads(again.stdout)["controller"]["K_per_s"] == 1500.0
    finally:
        if plant is not None and plant.poll() is None:
            plant.kill()
            plant.wait(5.0)
        stop(daemon)


def test_the_example_plant_reaches_a_load_that_is_a_process_of_its_own(tmp_path):
    """Three processes: the daemon, the example plant (--neighbour '') and `energyctl load` as the neighbour, the load a
    peer that listens nowhere, as the example plant was. The daemon does not route between its peers, so the load
    and the plant must link directly: with both listening nowhere the load saw no measurement while the daemon
    reported it alive. The example plant now listens on a free loopback port, and the load reaches it."""
    import os

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    here = [sys.executable, "-m", "clients.cli"]
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    zcfg = tmp_path / "load-zenoh.json5"
    zcfg.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": []}, "connect": {"endpoints": [endpoint]},
                                "scouting": {"multicast": {"enabled": False}}}))
    procs = []

    def start(name, argv):
        with open(tmp_path / f"{name}.out", "w") as so, open(tmp_path / f"{name}.err", "w") as se:
            procs.append(subprocess.Popen(argv, stdout=so, stderr=se, cwd=ROOT, env=env))
        return procs[-1]

    def log(name) -> str:
        return (tmp_path / f"{name}.err").read_text(errors="replace")[-2000:]

    try:
        daemon = start("daemon", [*here, "run", "--config", str(EXAMPLES / "component.toml"),
                                  "--set", f'zenoh.listen=["{endpoint}"]'])
        assert wait_until(lambda: listening(port) or daemon.poll() is not None, 15.0), log("daemon")
        assert daemon.poll() is None, log("daemon")
        load = start("load", [*here, "load", "--config", str(ROOT / "scenarios" / "live" / "load.toml"),
                              "--set", f"zenoh.config_file={json.dumps(str(zcfg))}",
                              "--set", f'zenoh.connect=["{endpoint}"]', "--set", "duration_s=120",
                              "--set", "load.components=[]"])
        st = lambda: client(endpoint, "status")  # noqa: E731
        assert wait_until(lambda: '"load"' in st().stdout and json.loads(st().stdout)["neighbours"]["load"]["alive"],
                          20.0), log("load")
        plant = subprocess.run([sys.executable, str(EXAMPLES / "lockstep_plant.py"), "--connect", endpoint, "--id",
                                "source", "--neighbour", "", "--seconds", "0.2"], capture_output=True, text=True,
                               timeout=120, env=env)
        res = json.loads(plant.stdout.strip().splitlines()[-1])  # (exit 1 on any timeout: the first, see below)
        assert res["samples"] == 2000 and res["timeouts"] <= 1, (res, plant.stderr[-2000:])
        status = json.loads(client(endpoint, "status").stdout)
        # every sample's z came from the load process (the first may come before the plant and the load linked)
        assert status["neighbours"]["load"]["messages"] >= res["samples"] - 1, (status["neighbours"], log("load"))
        assert status["loop"]["lockstep_timeouts"] <= 1, status["loop"]
        assert load.poll() is None, log("load")
    finally:
        for p in procs:
            stop(p)


def test_a_lockstep_load_that_gets_no_measurement_says_so(tmp_path):
    """The load waited silently for measurements that could not reach it; now it says so once, with the likely
    reason."""
    import os

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with open(tmp_path / "load.err", "w") as se:
        load = subprocess.Popen([sys.executable, "-m", "clients.cli", "load", "--config",
                                 str(ROOT / "scenarios" / "live" / "load.toml"), "--set",
                                 f'zenoh.connect=["tcp/127.0.0.1:{free_port()}"]', "--set", "duration_s=60"],
                                stdout=subprocess.DEVNULL, stderr=se, cwd=ROOT, env=env)
    try:
        said = lambda: "no measurement on energyctl/source/meas" in (tmp_path / "load.err").read_text()  # noqa: E731
        assert wait_until(said, 30.0), (tmp_path / "load.err").read_text()
        assert "listens nowhere" in (tmp_path / "load.err").read_text()
    finally:
        stop(load)
