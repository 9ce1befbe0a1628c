"""Replay: a log's inputs through a rebuilt core reproduce its commands bit for bit, or the first divergence."""

from __future__ import annotations

from conftest import SCENARIOS

from clients.cli import main
from clients.replay import replay
from schemas.scenario import load_scenario
from service.recorder import write_sim_mcap
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
