"""Wire fuzzing of a live network's coordinator and rig (issue 30): bad grid samples on the rig's key, bad commands on
a source's key (tests/wire_fuzz.py: valid frames with bit flips, fields at their boundaries, NaN and ±inf, cuts),
put with Zenoh's own put while the network runs in lockstep. The coordinator counts every bad grid sample and no
window message follows one; the source daemons, which form their shares from the same grid samples, refuse them too
(by field, counted) and follow none; the rig counts every bad command and applies none; all keep going, and the
network does not diverge. Every process is stopped (LiveNetwork.close)."""

from __future__ import annotations

import json
import signal
from collections import Counter

import zenoh
from conftest import SCENARIOS
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from wire_fuzz import bad_fixed, bad_grid

from clients.netlive import LiveNetwork
from schemas.codec import WINDOW
from schemas.network import load_network

SEQ_MAX = 100  # the fuzz frames' seqs: samples the network has passed before fuzzing starts
SCENARIO = SCENARIOS / "network" / "two-source.toml"
LIVE = settings(max_examples=25, deadline=None, phases=[Phase.explicit, Phase.generate],
                suppress_health_check=list(HealthCheck))
NET = load_network(SCENARIO)
SIZES = (len(NET.sources), len(NET.buses), len(NET.loads))
T = 1.0 / NET.timing.control_rate_hz


def test_the_coordinator_and_the_rig_count_every_bad_frame_and_follow_none(tmp_path):
    with LiveNetwork(SCENARIO, tmp_path / "run", sets=["timing.duration_s=600"]) as live:
        live.start()
        with live.session() as z:
            co = live.wait_until(z, "coordinator", lambda s: s["seq"] > 2 * SEQ_MAX, 60)
            assert co["counters"]["rejected"] == 0 and co["state"] == "active"
            windows: list[int] = []
            sub = z.declare_subscriber("energyctl/S1/window", lambda m: windows.append(WINDOW.decode(
                m.payload.to_bytes())[0]))
            grid = z.declare_publisher("energyctl/rig/grid", congestion_control=zenoh.CongestionControl.BLOCK)
            sent = Counter()

            @LIVE
            @given(frames=st.lists(bad_grid(SIZES, T, NET.nominal_v_V, SEQ_MAX), min_size=1, max_size=40))
            def grid_samples(frames):
                seq0 = live.query(z, "coordinator")["seq"]
                for f in frames:
                    grid.put(f)
                sent["grid"] += len(frames)
                now = live.wait_until(z, "coordinator", lambda s: s["counters"]["rejected"] >= sent["grid"], 20)
                assert now["counters"]["rejected"] == sent["grid"], now["last_reject"]
                assert now["state"] == "active"
                live.wait_until(z, "coordinator", lambda s: s["seq"] > seq0, 20)  # still taking samples
                assert not [s for s in windows if s <= SEQ_MAX]  # no window message answered a bad sample
                assert len(windows) == len(set(windows))  # and each window was sent once

            grid_samples()
            cmd = z.declare_publisher("energyctl/S1/cmd", congestion_control=zenoh.CongestionControl.BLOCK)

            @LIVE
            @given(frames=st.lists(bad_fixed("cmd", "cmd"), min_size=1, max_size=40))
            def commands(frames):
                seq0 = live.query(z, "coordinator")["seq"]
                for f, _ in frames:
                    cmd.put(f)
                sent["cmd"] += len(frames)
                # the rig reads S1's commands in order at every sample: a few samples later it has read these
                live.wait_until(z, "coordinator", lambda s: s["seq"] > seq0 + 3, 20)

            commands()
            sub.undeclare()
            for name in ("S1", "S2"):  # the bad grid samples they saw refused by field; nothing else
                now = live.query(z, name)
                assert now["state"] == "active" and all(k.startswith("grid.") for k in now["rejected"]), (
                    name, now["rejected"])
                assert now["reference"] == "sharing" and now["loop"]["lockstep_timeouts"] == 0, name
        live.kill("rig", signal.SIGTERM)
        res = live.wait_rig(60)
        assert res["state"] == "done" and res["failure"] == ""
        assert res["counters"]["rejected"] == sent["cmd"] and res["counters"]["late"] == 0
        assert res["counters"]["timeouts"] == 0 and not res["metrics"]["diverged"]
        out = live.close()
    for name, (rc, _so, se) in out.items():
        assert "Traceback" not in se, (name, se[-2000:])
        assert rc == 0 or name == "rig", (name, rc, se[-2000:])
    assert json.loads((tmp_path / "run" / "coordinator.out").read_text().splitlines()[-1])["state"] == "active"
