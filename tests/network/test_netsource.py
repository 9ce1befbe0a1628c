"""A network source's daemon driven by hand (a loopback session, no rig and no coordinator: the grid samples and the
window messages handed to its subscribers, the measurements to its tick): it forms its share from the grid sample and
steps through the same daemon tick as a single source, the compiled one included."""

from __future__ import annotations

import pytest
from conftest import SCENARIOS, RingStub

from schemas.codec import GRID, MEAS, WINDOW
from schemas.component import ZenohConfig
from schemas.netlive import source_component
from schemas.network import load_network
from service.daemon.bus import free_tcp_port
from service.network.netsim import run_network


@pytest.fixture
def offline():
    net = load_network(SCENARIOS / "network" / "realtime.toml", ["events=[]", "timing.duration_s=0.3"])
    return net, run_network(net)


def _daemon(net, core: str):
    from service.daemon.netsource import NetworkSourceDaemon

    z = ZenohConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_tcp_port()}"])
    d = NetworkSourceDaemon(source_component(net, "S1", zenoh=z, lockstep=False, core=core))
    d.open()
    return d


@pytest.mark.parametrize("core", ["c", "python"])
def test_a_network_source_steps_through_the_daemon_s_tick_and_sends_the_offline_commands(offline, core):
    """Each sample: the rig's grid sample (every source's measured v, i_out and breaker, from the offline run), the
    window message where the offline layer moved v_ref, then S1's measurement. Its commands are the offline
    controller's to the bit, and with the compiled core they go through the compiled tick (TickWriter). Before, the
    network daemon replaced the tick wholesale and dropped the compiled path (and took its P^{r,in} from the
    coordinator's per-sample allocation)."""
    net, res = offline
    names = list(net.sources)
    T = 1.0 / net.timing.control_rate_hz
    moves = {seq: v_ref for _t, seq, v_ref in res.config_events["S1"]}
    S = {s: res.sources[s] for s in names}
    connected = [net.sources[s].connected for s in names]  # (no event: S3 open throughout)
    d = _daemon(net, core)
    try:
        assert (d._fast is not None) == (core == "c")
        for k in range(len(res.t)):
            t = k * T
            d.grid.sub = RingStub([GRID.encode(k, t, [float(S[s]["meas_v"][k]) for s in names],
                                               [float(S[s]["meas_i_load"][k]) for s in names], connected, [80.0],
                                               [0.0])])
            d.win.sub = RingStub([WINDOW.encode(k, t, k // d.per_window, 2 / 3, moves[k], True, False, 0.0, 0.0,
                                                0.0, 0.0)] if k in moves else [])
            m = S["S1"]
            d._tick(MEAS.encode(k, t, float(m["meas_i"][k]), float(m["meas_v"][k]), float(m["meas_u"][k]),
                                float(m["meas_i_load"][k])), 1 + k)
            assert d.last_cmd[0] == k, d.last_reject
            assert d.last_cmd[2] == m["cmd_du"][k] and d.last_cmd[3] == m["cmd_du_next"][k], k
        st = d.status()
        assert st["reference"] == "sharing" and st["network"]["fallback_ticks"] == 0 and st["rejected"] == {}
        assert st["network"]["v_ref_moves"] == len([k for k in moves if k < len(res.t)]) > 0
    finally:
        d.close()
