"""Replay: a log's inputs through a rebuilt core reproduce its commands bit for bit, or the first divergence."""

from __future__ import annotations

from conftest import DATA, SCENARIOS

from clients.cli import main
from schemas.scenario import load_scenario
from service.logio.mcapfile import write_sim_mcap
from service.replay import replay
from service.sim import run


def test_replay_of_a_sim_log_is_identical_and_a_changed_command_is_found(tmp_path, capsys):
    res = run(load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.05"]))
    good = tmp_path / "good.mcap"
    write_sim_mcap(good, res)
    assert main(["replay", str(good)]) == 0
    assert "identical: 500 commands" in capsys.readouterr().out
    res.trace["du_dt"][123] = res.trace["du_dt"][123] * (1 + 1e-15) + 1e-300  # one ulp-scale change
    bad = tmp_path / "bad.mcap"
    write_sim_mcap(bad, res)
    assert main(["replay", str(bad)]) == 1
    out = capsys.readouterr().out
    assert "diverged" in out and "seq 123" in out


def test_what_if_writes_a_new_log_that_itself_replays(tmp_path):
    res = run(load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.03"]))
    log = tmp_path / "log.mcap"
    write_sim_mcap(log, res)
    what_if = tmp_path / "k500.mcap"
    r = replay(log, ["controller.K_per_s=500.0"], out=str(what_if), progress=False)
    assert r["ticks"] == 300
    again = replay(what_if, progress=False)
    assert again["identical"] and again["compared"] == 300
    assert main(["replay", str(log), "--set", "controller.K_per_s=500.0"]) == 2  # a what-if needs --out


WRITER = """
import sys, time
from schemas.codec import TICK_IN
from service.logio.ring import RingRecorder
if __name__ == "__main__":  # the recorder process is spawned: it re-imports this module
    path, n = sys.argv[1], int(sys.argv[2])
    rec = RingRecorder(path, {"x/z_in": ("energyctl.TickInput", TICK_IN)}, {"core": {"json": "{}"}},
                       chunk_size=65536)
    for k in range(n):
        rec.offer("x/z_in", k * 1e-4, (k, k * 1e-4, -1200.0 - k * 1e-3, 0.5 * k, True))
    deadline = time.monotonic() + 30
    while rec.written < n and time.monotonic() < deadline:
        time.sleep(0.005)
    print(rec.pid, rec.written, flush=True)
    time.sleep(60)  # the test kills the writer process before close()
"""


def test_a_killed_writer_loses_at_most_its_last_chunk_and_recover_completes_the_file(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    from conftest import ROOT

    from clients.logtools import info, recover

    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    log = tmp_path / "killed.mcap"
    n = 20_000
    p = subprocess.Popen([sys.executable, str(script), str(log), str(n)], stdout=subprocess.PIPE, text=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    try:
        writer_pid, taken = map(int, p.stdout.readline().split())
        assert taken == n
        os.kill(writer_pid, signal.SIGKILL)  # the process writing the MCAP dies mid-file
        time.sleep(0.2)
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    got = info(log)
    assert not got["complete"]
    kept = got["messages"]
    per_message = got["channels"]["x/z_in"]["bytes"] / kept + 31  # payload + message record overhead
    assert n - kept <= 65536 / per_message + 1  # at most the last (unfinished) chunk is lost
    assert kept > n / 2
    fixed = tmp_path / "fixed.mcap"
    assert recover(log, fixed)["messages"] == kept
    again = info(fixed)
    assert again["complete"] and again["messages"] == kept


def test_logs_open_in_the_typescript_mcap_reader(tmp_path):
    """Foxglove's MCAP library (npm @mcap/core) reads our files: indexed, and as a CRC-checked stream."""
    import json
    import shutil
    import subprocess

    from conftest import ROOT

    js = ROOT / "tests" / "js"
    node = shutil.which("node")
    assert node and (js / "node_modules" / "@mcap" / "core").exists(), \
        "run the README test command: it installs tests/js (npm install --prefix tests/js)"
    res = run(load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.duration_s=0.02"]))
    log = tmp_path / "sim.mcap"
    write_sim_mcap(log, res)
    out = subprocess.run([node, str(js / "check_mcap.mjs"), str(log)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["messages"] == 5 * 200 and got["streamDone"] and got["schemaEncodings"] == ["jsonschema"]
    assert "core" in got["metadata"] and got["sample"]["seq"] == 0
    # a daemon log, with its tick-index attachments: still a valid file for the other reader
    from clients.bench.tick import _trace, drive_daemon

    scn, tr = _trace(str(SCENARIOS / "paper-varying-load.toml"), 1000)
    _t, st = drive_daemon(scn, tr, str(tmp_path))
    out = subprocess.run([node, str(js / "check_mcap.mjs"), st["log_path"]], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["streamDone"] and got["counts"]["energyctl/source/meas"] == 1000 and "tick_index" in got["metadata"]


def test_foxglove_layout_plots_only_channels_the_daemon_writes(tmp_path):
    """Every topic the shipped layout plots is a channel of a real daemon log (component id 'source')."""
    import json
    import re

    from conftest import ROOT

    from clients.live import run_live
    from clients.logtools import info

    layout = json.loads((ROOT / "foxglove" / "energyctl-daemon.layout.json").read_text())
    text = json.dumps(layout["configById"])
    wanted = set(re.findall(r'\\"(energyctl/source/[a-z_]+)\\"', text))
    assert {"energyctl/source/meas", "energyctl/source/cmd", "energyctl/source/est"} <= wanted

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.duration_s=0.02"])
    res = run_live(scn, lockstep=True, rate_hz=None, out=str(tmp_path / "plant.mcap"), duration_s=None,
                   workdir=str(tmp_path))
    channels = set(info(res["daemon_log"])["channels"])
    channels.add("energyctl/source/events")  # written only when something happens
    assert wanted <= channels, wanted - channels
    # and every plotted field is a field of that channel's schema (the JSON Schema Foxglove reads)
    schema_of = {"meas": "Measurement", "cmd": "Command", "est": "Estimate", "z_in": "TickInput", "z": "Interaction",
                 "z_out": "Interaction"}
    plotted = re.findall(r'\\"energyctl/source/([a-z_]+)\\"\.([A-Za-z_0-9]+)', text)
    assert ("cmd", "du_dt_next") in plotted
    for topic, fld in plotted:
        props = json.loads((ROOT / "schemas" / "json" / f"energyctl.{schema_of[topic]}.json").read_text())["properties"]
        assert fld in props, (topic, fld)


def test_rotated_daemon_log_replays_across_its_parts_and_records_neighbours_and_loop(tmp_path):
    from clients.live import configs_from_scenario
    from clients.logtools import info
    from schemas.component import ComponentConfig

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.duration_s=0.1"])
    # rotate every 0.03 s of log time: four parts for 1000 ticks
    orig = configs_from_scenario

    def rotating(*a, **k):
        comp, plant, load = orig(*a, **k)
        comp["log_rotate_s"] = 0.03
        ComponentConfig.model_validate(comp)
        return comp, plant, load

    import clients.live as live

    live.configs_from_scenario = rotating
    try:
        res = live.run_live(scn, lockstep=True, rate_hz=None, out=str(tmp_path / "p.mcap"), duration_s=None,
                            workdir=str(tmp_path))
    finally:
        live.configs_from_scenario = orig
    first = res["daemon_log"]
    parts = [first] + sorted(str(p) for p in tmp_path.glob(first.rsplit("/", 1)[-1][:-5] + "-*.mcap"))
    assert len(parts) == 4
    assert replay(parts[0], progress=False)["identical"]  # the first part starts from a fresh core too
    assert not replay(parts[1], progress=False)["identical"]  # a later part alone lacks the core's history
    whole = replay(parts, progress=False)
    assert whole["identical"] and whole["compared"] == 1000
    chans = set()
    for p in parts:
        chans |= set(info(p)["channels"])
    assert "energyctl/source/z_nb/load" in chans and "energyctl/source/loop" in chans


def test_fast_log_reader_gives_the_general_readers_arrays(tmp_path):
    """service/logio/_mcapscan.c (no Python object per message) and mcap + json read the same doubles, also from a
    file cut off mid-chunk (a killed writer); a log not in the recorder's flat JSON falls back to the general
    reader instead of failing."""
    import numpy as np
    import pytest

    from service.logio import reader as rp

    if rp._mcapscan is None:
        pytest.skip("log scanner not built")
    res = run(load_scenario(SCENARIOS / "paper-varying-load.toml", ["timing.duration_s=0.2"]))
    log = tmp_path / "log.mcap"
    write_sim_mcap(log, res)
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * 0.6)])
    for f in (log, cut):
        fast, general = rp._read_fast(f), rp._read_general(f)
        a, b = np.concatenate(fast.rows), np.concatenate(general.rows)
        assert a.shape == b.shape and len(a) > 0 and fast.core == general.core
        needed = np.zeros(b.shape, dtype=bool)  # the columns replay reads (the scanner skips the others)
        needed[:, 0] = True
        for c, ks in enumerate(rp.KEYS):
            for k, name in enumerate(ks):
                needed[b[:, 0] == c, 1 + k] = name in rp.NEEDED[c]
        assert needed[:, 1:].sum() > 3 * len(b)  # (meas 6, z_in 4, cmd 2 per tick)
        assert np.array_equal(a[needed], b[needed])
    assert len(np.concatenate(rp._read_fast(cut).rows)) < len(np.concatenate(rp._read_fast(log).rows))

    from service.logio.mcapfile import McapFile

    odd = tmp_path / "odd.mcap"  # same topics, keys in another order: not the recorder's template
    f = McapFile(odd)
    f.metadata("core", {"json": "{}"})
    f.channel("x/meas", "energyctl.Measurement")
    f.add("x/meas", 0.0, {"t": 0.0, "seq": 0, "i": 1.0, "v": 80.0, "u": 80.0, "i_load": 1.0})
    f.close()
    with pytest.raises(ValueError, match="not the expected flat JSON"):
        rp._read_fast(odd)
    assert np.concatenate(rp.read_log(odd).rows)[0, 1:7].tolist() == [0.0, 0.0, 1.0, 80.0, 80.0, 1.0]


def test_tick_index_gives_the_json_channels_inputs_and_is_used_only_when_complete(tmp_path):
    """A daemon log carries a tick index (zstd attachments of one row per tick) beside its JSON channels.
    Replay from it equals replay from the JSON, row for row and command for command, with a config change
    mid-run; a file cut short (no summary to count against) is read from the JSON instead."""
    import threading

    import numpy as np

    from clients.bench.tick import _trace, drive_daemon
    from service import replay as rp

    scn, tr = _trace(str(SCENARIOS / "paper-varying-load.toml"), 3000)
    faster = scn.controller.model_copy(update={"K_per_s": 900.0})

    def set_gain(d):  # what the loop does with a validated config set, between two ticks
        d._pending = (faster, threading.Event(), faster.model_dump_json())
        d._apply_pending()

    _t, st = drive_daemon(scn, tr, str(tmp_path), hooks={1200: set_gain})
    log = st["log_path"]
    by_index, by_json = rp.collect([log]), rp.collect([log], use_index=False)
    assert by_index.sources == ["index"] and by_json.sources == ["json"]
    assert np.array_equal(by_index.keys, by_json.keys) and len(by_index.keys) == 3000
    assert np.array_equal(by_index.rows[:, :9], by_json.rows[:, :9])
    assert np.array_equal(by_index.logged, by_json.logged) and by_json.has_cmd.all()
    a, b = rp.replay(log, progress=False), rp.replay(log, progress=False, use_index=False)
    assert a["identical"] and b["identical"] and a["compared"] == b["compared"] == 3000
    assert a["read_from"] == "index" and b["read_from"] == "json"
    # the gain change was applied from its event on both paths: without it, replay diverges after tick 1200
    assert len(by_index.cfg_events) == 1

    from clients.logtools import recover

    fixed = tmp_path / "rewritten.mcap"  # log recover keeps the index: still used, still identical
    recover(log, fixed)
    r = rp.replay(fixed, progress=False)
    assert r["read_from"] == "index" and r["identical"] and r["compared"] == 3000

    cut = tmp_path / "cut.mcap"
    data = open(log, "rb").read()
    cut.write_bytes(data[:int(len(data) * 0.7)])
    part = rp.collect([cut])
    assert part.sources == ["json"] and 0 < len(part.keys) < 3000
    assert np.array_equal(part.rows[:, :9], by_json.rows[:len(part.keys), :9])


def test_a_daemon_log_with_the_observer_replays_bit_for_bit_and_without_it_does_not(tmp_path):
    """The observer's estimate is core state carried from tick to tick: the replay rebuilds it from the logged
    samples (held and skipped ones included), and a what-if without it finds the first divergence."""
    from clients.bench.tick import _trace, drive_daemon

    scn, tr = _trace(str(SCENARIOS / "paper-varying-load.toml"), 1500)
    scn = scn.model_copy(update={"controller": scn.controller.model_copy(update={"observer_gain": 0.15})})
    _times, st = drive_daemon(scn, tr, str(tmp_path), skip={400, 401, 900})
    r = replay(st["log_path"], progress=False)
    assert r["identical"] and r["compared"] == 1500 - 3
    off = replay(st["log_path"], ["controller.observer_gain=0.0"], progress=False)
    assert not off["identical"]


def test_a_log_recorded_by_the_previous_release_replays_identical():
    """tests/data holds a 0.05 s lockstep demo log written by release 0.1.0 (commit ea805d8), before the code moved
    into its layers: today's core must reproduce every one of its commands bit for bit."""
    log = DATA / "source-v0.1.0-ea805d8.mcap"
    r = replay(log, progress=False)
    assert r["identical"] and r["compared"] == 500 and r["first_divergence"] is None, r


def test_log_info_reports_a_foreign_log_where_it_stops_making_sense(tmp_path):
    """A log whose /events channel is not JSON (another tool's encoding) is described up to there, with the
    reason, not a traceback; the messages reader returns what came before."""
    from clients.logtools import info
    from service.logio.mcapfile import McapFile
    from service.logio.reader import messages

    path = tmp_path / "foreign.mcap"
    f = McapFile(path)
    f.channel("x/events", "energyctl.Event")
    f.add("x/events", 0.0, {"t": 0.0, "seq": 0, "kind": "config", "detail": "{}"})
    f.add_raw("x/events", 0.001, b"\x00\x01\xff not json")
    f.close()
    res = info(path)
    assert res["truncated_at"] and "Error" in res["truncated_at"]
    assert res["channels"]["x/events"]["messages"] == 2
    assert messages(path, "/events") == [{"t": 0.0, "seq": 0, "kind": "config", "detail": "{}"}]
