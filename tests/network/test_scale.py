"""Many source daemons across hosts (issue 29, item 3): the radial network of 16 sources on 4 network-namespace hosts
through the secure profile's routers, in lockstep, equal to ``energyctl sim`` in every v, i, u and command
(clients.nethosts, as ``energyctl demo --network --hosts 4 --sources 16``); every namespace and process removed
after a run that fails; and, without root, the pieces: the scenario builder, the placement, the rig's command log
and the identity check.

The 32-source run (``energyctl demo --network --hosts 4 --sources 32``, under a minute and 2.7 GB here) and the
scaling figures (``energyctl bench network-scale``) are in docs/benchmarks.md; CI runs the 16-source one, 0.05 s of
sample time (500 samples at 10 kHz), about 25 s here."""

from __future__ import annotations

import math
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from clients.bench.network import radial
from clients.nethosts import identity, placement, run_hosted, write_radial
from clients.netns import unavailable_reason
from clients.secure import LOCKSTEP_WAIT_BEFORE_DROP_US
from schemas.network import load_network, network_from_dict


def _namespaces() -> set[str]:
    r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
    return {line.split()[0] for line in r.stdout.splitlines() if line.strip()}


def _processes_under(path: Path) -> list[int]:
    """Processes whose command line names path (the run's work directory: every process of the run does)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if str(path).encode() in (d / "cmdline").read_bytes():
                    out.append(int(d.name))
            except OSError:
                pass
    return out


@pytest.fixture
def root():
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(f"network namespaces: {reason}")


# ---------------------------------------------------------------------------------------------- with root

def test_16_sources_on_4_hosts_in_lockstep_equal_sim(root, tmp_path):
    """16 daemons in blocks on 3 hosts, the rig and the coordinator on the hub, one router per host with the secure
    profile: every lockstep sample answered by every source (no timeout), the network equal to the offline run bit
    for bit in every v, i, u and command, every process stopped cleanly, every namespace gone."""
    before = _namespaces()
    scn = write_radial(tmp_path / "radial-16.toml", 16, 0.05)
    res = run_hosted(scn, tmp_path / "run", 4, wait_before_drop_us=LOCKSTEP_WAIT_BEFORE_DROP_US)
    assert res["ok"], res["why"]
    assert res["hosts"] == 4 and [len(ids) for ids in res["place"].values()] == [2, 6, 5, 5]
    assert res["rig"]["samples"] == 500 and res["rig"]["counters"]["timeouts"] == 0
    assert res["rig"]["counters"]["commands"] == 16 * 500
    ident = res["identity"]
    assert ident["equal"] and ident["compared"] == 16 * 5 + 4 and ident["samples"] == 500, ident
    # each stopped on SIGTERM: exit 0, or (under load from other work) ended by its 5 s shutdown grace
    assert set(res["exit_codes"]) == set(res["ended_by_shutdown_grace"]), res["exit_codes"]
    # every daemon's CPU was measured, and it did work while sampling
    assert all(res["cpu_s"][f"S{j}"] > 0 for j in range(1, 17)), res["cpu_s"]
    assert _namespaces() <= before and not _processes_under(tmp_path)


def test_a_failed_run_leaves_no_namespace_and_no_process(root, tmp_path):
    """A daemon that dies while the others wait: run_hosted raises naming it, and every process it started (the
    routers, the rig, the coordinator, the other daemons) and every namespace it made is gone afterwards."""
    before = _namespaces()
    # S2's daemon exits 3 at once; every other process is the real one
    fake = [sys.executable, "-c", "import sys\nif 'S2' in sys.argv: sys.exit(3)\n"
            "from clients.cli import main\nsys.exit(main(sys.argv[1:]))"]
    scn = write_radial(tmp_path / "radial-4.toml", 4, 0.05)
    with pytest.raises(RuntimeError, match=r"S2 exited \(3\)"):
        run_hosted(scn, tmp_path / "run", 3, energyctl=fake)
    assert _namespaces() <= before, _namespaces() - before
    assert not _processes_under(tmp_path)


def test_the_demo_interrupted_exits_130_and_leaves_nothing(root, tmp_path):
    """energyctl demo --network --hosts: SIGINT while its processes start (progress on stderr says so): exit 130,
    every namespace and process gone."""
    import signal

    from clients.live import child_env

    before = _namespaces()
    p = subprocess.Popen([sys.executable, "-m", "clients.cli", "demo", "--network", "--hosts", "3", "--sources", "4",
                          "--logs", str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=child_env(),
                         # SIGINT as a terminal gives it: a suite started in the background (`cmd &` in a script)
                         # inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        for line in p.stderr:  # progress
            if "waiting for them to connect" in line:
                break
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, (out, err)
    assert "interrupted" in err and _namespaces() <= before and not _processes_under(tmp_path)


# ---------------------------------------------------------------------------------------------- without root

@pytest.mark.parametrize("n", [1, 4, 5, 16, 32, 64])
def test_the_radial_builder(n, tmp_path):
    """radial(n): ceil(n / 4) buses in a chain, each source behind its own line to a bus (round robin), 300 W of load
    per source; written as a scenario file, it loads back to the same network."""
    net = network_from_dict(radial(n, 0.1))
    n_bus = math.ceil(n / 4)
    assert list(net.sources) == [f"S{j + 1}" for j in range(n)] and len(net.buses) == n_bus
    feeders = [ln for ln in net.lines.values() if ln.a in net.buses]
    assert len(feeders) == n_bus - 1 and all(ln.b in net.buses for ln in feeders)
    for j, s in enumerate(net.sources):
        (ln,) = [ln for ln in net.lines.values() if s in (ln.a, ln.b)]
        assert ln.b == f"B{j % n_bus + 1}"
    assert sum(ld.value for ld in net.loads.values()) == pytest.approx(300.0 * n)
    assert net.timing.duration_s == 0.1 and net.timing.control_rate_hz == 10000.0
    path = write_radial(tmp_path / f"radial-{n}.toml", n, 0.1)
    back = load_network(path)
    assert back.model_dump(exclude={"base_dir"}) == net.model_dump(exclude={"base_dir"})
    assert tomllib.loads(path.read_text())["name"] == f"radial-{n}"


def test_the_builder_refuses_a_network_without_sources(tmp_path):
    with pytest.raises(Exception, match="sources"):
        write_radial(tmp_path / "radial-0.toml", 0)
    assert not (tmp_path / "radial-0.toml").exists()


def test_placement_puts_the_sources_in_blocks_on_the_spokes():
    s = [f"S{j}" for j in range(1, 33)]
    p = placement(s, 4)
    assert list(p) == ["rig", "h1", "h2", "h3"] and p["rig"] == ["rig", "coordinator"]
    assert [len(p[h]) for h in ("h1", "h2", "h3")] == [11, 11, 10]
    assert [x for h in ("h1", "h2", "h3") for x in p[h]] == s  # in order, each once
    assert placement(["S1", "S2"], 4) == {"rig": ["rig", "coordinator"], "h1": ["S1"], "h2": ["S2"]}
    assert placement(["S1", "S2"], 1) == {"rig": ["rig", "coordinator", "S1", "S2"]}
    with pytest.raises(ValueError, match="at least 1"):
        placement(s, 0)


def _offline_as_rig_log(path: Path, n: int = 4):
    """An offline run of radial(n) written as a lockstep rig's log (its answers under SOURCE/cmd)."""
    from clients.peers.netrig import write_rig_log
    from service.network.netsim import run_network

    net = network_from_dict(radial(n, 0.01))
    off = run_network(net)
    write_rig_log(str(path), off, "energyctl", {})
    return net, off


def test_the_rig_log_carries_each_source_s_answers_and_the_identity_check_reads_them(tmp_path):
    """A lockstep rig log holds each source's du/dt and planned du/dt per sample (before: only the plant's state,
    so no check could cover the commands); the identity check finds a log equal to sim, and names the first
    sample of a command one ulp off."""
    from clients.peers.netrig import read_rig_log

    net, off = _offline_as_rig_log(tmp_path / "rig.mcap")
    back = read_rig_log(str(tmp_path / "rig.mcap"))
    for s in net.sources:
        assert np.array_equal(back.sources[s]["cmd_du"], off.sources[s]["cmd_du"])
        assert np.array_equal(back.sources[s]["cmd_du_next"], off.sources[s]["cmd_du_next"])
    ok = identity(tmp_path / "rig.mcap", net)
    assert ok["equal"] and ok["compared"] == 4 * 5 + 1 and ok["samples"] == 100, ok
    off.sources["S3"]["cmd_du"][57] = np.nextafter(off.sources["S3"]["cmd_du"][57], np.inf)
    from clients.peers.netrig import write_rig_log

    write_rig_log(str(tmp_path / "bad.mcap"), off, "energyctl", {})
    bad = identity(tmp_path / "bad.mcap", net)
    assert not bad["equal"] and bad["differing"] == 1 and bad["first"][0][:3] == ("S3", "cmd du/dt", 57), bad


def test_a_sample_a_source_did_not_answer_is_missing_from_the_log_and_fails_the_check(tmp_path):
    from clients.peers.netrig import read_rig_log, write_rig_log

    net, off = _offline_as_rig_log(tmp_path / "rig.mcap")
    off.sources["S2"]["cmd_du"][10] = np.nan  # the rig's mark for "no answer came"
    write_rig_log(str(tmp_path / "gap.mcap"), off, "energyctl", {})
    back = read_rig_log(str(tmp_path / "gap.mcap"))
    assert np.isnan(back.sources["S2"]["cmd_du"][10]) and np.isnan(back.sources["S2"]["cmd_du_next"][10])
    bad = identity(tmp_path / "gap.mcap", net)
    assert not bad["equal"] and ("S2", "cmd du/dt", 10) in [f[:3] for f in bad["first"]]


def test_a_realtime_rig_log_without_commands_is_not_taken_for_identical(tmp_path):
    """A log with no command channel (a realtime rig's, or one from before) cannot pass the identity check."""
    from clients.peers.netrig import write_rig_log

    net, off = _offline_as_rig_log(tmp_path / "rig.mcap")
    for row in off.sources.values():
        del row["cmd_du"], row["cmd_du_next"]
    write_rig_log(str(tmp_path / "nocmd.mcap"), off, "energyctl", {})
    bad = identity(tmp_path / "nocmd.mcap", net)
    assert not bad["equal"] and bad["first"][0][3] == "not logged"


def test_the_profile_s_wait_before_drop_reaches_every_router_and_process(tmp_path):
    import json

    from clients.secure import write_network_profile

    net = network_from_dict(radial(4, 0.01))
    place = placement(list(net.sources), 3)
    paths = write_network_profile(tmp_path, net, hosts=place, hub="rig", hub_endpoints=["tcp/10.9.0.1:7448"],
                                  wait_before_drop_us=20_000)
    for name in ["client", *(f"router-{h}" for h in place)]:
        text = paths[name].read_text()
        cfg = json.loads(text[text.index("{"):])
        q = cfg["transport"]["link"]["tx"]["queue"]
        assert q["congestion_control"]["drop"]["wait_before_drop"] == 20_000 and q["size"]["data"] == 16, name
    plain = write_network_profile(tmp_path / "plain", net)
    assert "congestion_control" not in plain["client"].read_text()  # unset: Zenoh's


def test_secure_profile_bounds_the_wait_before_drop(tmp_path):
    from conftest import SCENARIOS

    r = subprocess.run([sys.executable, "-m", "clients.cli", "secure-profile", "--out", str(tmp_path / "p"),
                        "--network", str(SCENARIOS / "network" / "two-source.toml"), "--wait-before-drop-us",
                        "2000000"], capture_output=True, text=True)
    assert r.returncode != 0 and "--wait-before-drop-us: 0 to 1000000" in r.stderr, r.stderr


def test_demo_hosts_and_sources_refuse_what_they_cannot_do(tmp_path, capsys):
    from clients.cli import main

    for argv, said in ((["--hosts", "4"], "--hosts and --sources go with --network"),
                       (["--network", "--hosts", "4", "--sources", "4", "--realtime"], "lockstep"),
                       (["--network", "--hosts", "0"], "--hosts: 1 to 64"),
                       (["--network", "--hosts", "2", "--sources", "65"], "--sources: 1 to 64")):
        assert main(["demo", *argv, "--logs", str(tmp_path)]) == 2, argv
        assert said in capsys.readouterr().err, argv
