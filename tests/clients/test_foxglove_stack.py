"""The Foxglove bridge beside the real stack (daemon, stand-in plant and load as processes, lockstep): what a
WebSocket client receives on the measurement channel is what the daemon logged, sample for sample."""

from __future__ import annotations

import pytest
from conftest import SCENARIOS

pytest.importorskip("foxglove.websocket")
pytest.importorskip("websockets")


def test_the_bridge_serves_what_the_daemon_logged(tmp_path):
    from clients.bench.foxglove import _stack
    from clients.live import run_live
    from schemas.scenario import load_scenario
    from service.daemon.bus import free_tcp_port
    from service.logio.reader import messages

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.duration_s=0.3"])
    watch: dict = {}
    res = run_live(scn, lockstep=True, rate_hz=None, out=str(tmp_path / "plant.mcap"), duration_s=None,
                   workdir=str(tmp_path),
                   extra=_stack(free_tcp_port(), 1000.0, watch, keep_topic="energyctl/source/meas"))
    watch["stop"].set()
    watch["watcher"].join(5.0)
    assert watch["subscribed"] and not res["metrics"]["diverged"]
    got = {m["seq"]: m for m in watch["watcher"].kept}
    logged = {m["seq"]: m for m in messages(res["daemon_log"], "/meas")}
    assert len(got) > 300 and set(got) <= set(logged)  # decimated to 1 kHz of 10 kHz: a part, all logged ones
    for seq, m in got.items():
        assert m == logged[seq], seq
