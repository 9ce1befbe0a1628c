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


def _drive(d, net, res, ks, extra=None, window_msgs=True):
    """Steps d (S1's daemon) through samples ks of the offline run res, with extra grid frames (seq -> payloads put
    on the ring before that sample's own); returns the samples whose command differs from the offline one."""
    names = list(net.sources)
    T = 1.0 / net.timing.control_rate_hz
    moves = {seq: v_ref for _t, seq, v_ref in res.config_events["S1"]}
    S = {s: res.sources[s] for s in names}
    connected = [net.sources[s].connected for s in names]
    extra = extra or {}
    bad = []
    for k in ks:
        t = k * T
        d.grid.sub = RingStub([*extra.get(k, []), GRID.encode(k, t, [float(S[s]["meas_v"][k]) for s in names],
                                                              [float(S[s]["meas_i_load"][k]) for s in names],
                                                              connected, [80.0], [0.0])])
        d.win.sub = RingStub([WINDOW.encode(k, t, k // d.per_window, 2 / 3, moves[k], True, False, 0.0, 0.0, 0.0,
                                            0.0)] if window_msgs and k in moves else [])
        m = S["S1"]
        d._tick(MEAS.encode(k, t, float(m["meas_i"][k]), float(m["meas_v"][k]), float(m["meas_u"][k]),
                            float(m["meas_i_load"][k])), 1 + k)
        if not (d.last_cmd[0] == k and d.last_cmd[2] == m["cmd_du"][k] and d.last_cmd[3] == m["cmd_du_next"][k]):
            bad.append(k)
    return bad


def _forged(net, seq: int) -> bytes:
    """A valid grid sample of seq (a stray sender's: every source at 48 V drawing nothing)."""
    ns = len(net.sources)
    return GRID.encode(seq, seq / net.timing.control_rate_hz, [48.0] * ns, [0.0] * ns, [True] * ns, [80.0], [0.0])


def test_two_forged_grid_samples_far_ahead_do_not_cut_a_source_off_the_rig(offline):
    """Review F2 item 1: grid frames 100000 and 100001 (valid, the second following the first) among the rig's. The
    grid seq is judged against the measurements' clock: both are refused by field and the rig's samples are taken
    on, the commands the offline ones to the bit. Before, the second was taken (it followed the first refused) and
    every real grid sample after it was refused as 'not after': the source fell back for the rest of the run."""
    net, res = offline
    d = _daemon(net, "c")
    try:
        bad = _drive(d, net, res, range(len(res.t)), {100: [_forged(net, 100000), _forged(net, 100001)]})
        st = d.status()
        assert bad == [] and st["network"]["fallback_ticks"] == 0, (bad[:5], st["rejected"], d.last_reject)
        assert st["rejected"] == {"grid.seq: invalid": 2}, st["rejected"]
    finally:
        d.close()


def test_grid_samples_before_the_first_measurement_are_judged_when_it_comes(offline):
    """A daemon started mid-run (its first measurement at sample 100) that finds forged grid frames far ahead on the
    key before it: they wait for the measurements' clock and are refused by it; the rig's are taken. Before, there
    was no ahead check before the first measurement: the forged ones were taken and every rig sample refused."""
    net, res = offline
    d = _daemon(net, "c")
    try:
        d.grid.sub = RingStub([_forged(net, 100000), _forged(net, 100001)])
        d._poll_neighbours(0)
        _drive(d, net, res, range(100, len(res.t)))  # (its commands are not the offline run's: it starts at 100)
        st = d.status()
        assert d.grid.seq == len(res.t) - 1 and st["network"]["fallback_ticks"] == 0, (st["rejected"], d.last_reject)
        assert st["rejected"] == {"grid.seq: invalid": 2}, st["rejected"]
    finally:
        d.close()


def test_a_run_of_grid_samples_behind_one_taken_is_a_new_run(offline):
    """Whatever put the newest grid sample taken ahead of the rig's (a forged one the measurements' clock let pass),
    a window of the rig's samples in a row that follow one another are a new run (as the coordinator's rule), not
    refused for ever."""
    net, res = offline
    d = _daemon(net, "c")
    try:
        _drive(d, net, res, range(100))
        d._set_clock(1000, 0)  # (as if the measurements' clock had been moved to 1000: a forged one taken)
        d._judge_grid(GRID.decode(_forged(net, 1000)), 0, counted=False)
        _drive(d, net, res, range(100, len(res.t)))
        st = d.status()
        assert d.grid.seq == len(res.t) - 1 and st["network"]["grid_new_runs"] == 1, st["rejected"]
    finally:
        d.close()


def test_a_stray_grid_sample_of_seq_0_mid_run_does_not_reset_the_sharing(offline):
    """Review F2 item 2: a valid grid sample of seq 0 among the rig's at sample 150 (a stray sender's). It is a
    candidate only (a rig restart shows as the measurement's seq 0 or grid seq 1 after it): refused when the rig's
    151 comes, and the commands stay the offline run's to the bit. Before, it reset the sharing mid-run (its rate
    filter, breaker memory and k_prev) and the commands after it differed."""
    net, res = offline
    d = _daemon(net, "c")
    try:
        bad = _drive(d, net, res, range(len(res.t)), {151: [_forged(net, 0)]})
        st = d.status()
        assert bad == [] and st["rejected"] == {"grid.seq: invalid": 1}, (bad[:5], st["rejected"])
    finally:
        d.close()


def test_a_grid_seq_0_followed_by_seq_1_is_a_rig_restart(offline):
    """The candidate seq 0 is the rig's restart when grid seq 1 follows it (its measurement's seq 0 lost): the
    sharing starts again from it, as at a start."""
    net, res = offline
    d = _daemon(net, "c")
    try:
        _drive(d, net, res, range(200))
        d.grid.sub = RingStub([_forged(net, 0), _forged(net, 1)])
        d._poll_neighbours(0)
        assert d.grid.seq == 1 and d.grid.count == 2 and d.sharing.k_prev == 1, d.last_reject
    finally:
        d.close()


def test_a_daemon_started_mid_run_takes_its_share_at_once(offline):
    """Review F2 item 3: S1's daemon started at sample 1000 of a run in which S3 (open at the scenario's start)
    connected earlier. Its first grid sample's breakers are the ones it starts with: P^{r,in} = -alpha_S1 sum P_k
    at once (2/4 of 2880 W), not with S3 'just connected' and ramping from 0 (2/3: S1 took more than its share)."""
    net, _res = offline
    d = _daemon(net, "c")
    try:
        shares = [s.share for s in net.sources.values()]
        assert not net.sources["S3"].connected and d.sharing.ramp_ticks > 0
        d._set_clock(1000, 0)
        d.grid.sub = RingStub([GRID.encode(1000, 1.0, [48.0] * 3, [20.0] * 3, [True] * 3, [80.0], [0.0])])
        d._poll_neighbours(0)
        assert d.grid.seq == 1000, d.last_reject
        assert d.grid.P == -(shares[0] / sum(shares)) * 3 * 960.0
    finally:
        d.close()


class _Trickle(RingStub):
    """A ring whose payloads come in polls: a None in the list ends a poll (the next message not there yet)."""

    def try_recv(self):
        if self.items and self.items[0] is None:
            self.items.pop(0)
            return None
        return super().try_recv()


def test_lockstep_waits_for_the_breaker_change_message_on_a_window_s_first_sample(offline):
    """Review F2 item 4: a breaker change (S3 closes) shown by the grid sample of a window's first sample (100, with
    50-sample windows). The window-end message made after sample 99 is for 100 too; the breaker change's, made after
    sample 100, comes a poll later. The lockstep wait takes both before the tick (as offline, which applies the
    change's range from 100). Before, the first satisfied it and the tick could go without the second."""
    import time

    net, res = offline
    d = _daemon(net, "c")
    try:
        _drive(d, net, res, range(100))
        assert 100 % d.per_window == 0
        T = d.period_s
        d.grid.sub = RingStub([GRID.encode(100, 100 * T, [48.0] * 3, [20.0] * 3, [True] * 3, [80.0], [0.0])])
        end = WINDOW.encode(100, 99 * T, 2, 2 / 3, 80.0, True, True, -900.0, -100.0, -1e5, 1e5)
        change = WINDOW.encode(100, 100 * T, 2, 2 / 4, 80.0, True, True, -700.0, -50.0, -1e5, 1e5)
        d.win.sub = _Trickle([end, None, None, change])
        d._await_neighbours(100, time.monotonic_ns() + 5_000_000_000)
        assert d._changed_at == 100 and d.stats.lockstep_timeouts == 0, (d.rejected, d.win.seq, d.win.t)
        assert [wv[1] for wv in d._win_pending] == [99 * T, 100 * T]
    finally:
        d.close()


def test_window_messages_with_ranges_out_of_order_are_refused_by_field_and_drops_counted(offline):
    """Review F2 item 5: a window message with Z_P_min > Z_P_max (or Z_Qdot_min > Z_Qdot_max) is refused by field,
    never set on the feasibility monitor; more pending than the queue holds are counted, not dropped silently."""
    net, res = offline
    d = _daemon(net, "c")
    try:
        _drive(d, net, res, range(10))
        w = [WINDOW.encode(10, 0.009, 0, 2 / 3, 80.0, True, True, -100.0, -900.0, -1e5, 1e5),
             WINDOW.encode(10, 0.009, 0, 2 / 3, 80.0, True, True, -900.0, -100.0, 1e5, -1e5)]
        d.win.sub = RingStub(w + [WINDOW.encode(11 + i, 0.009, 0, 2 / 3, 80.0, True, False, 0, 0, 0, 0)
                                  for i in range(10)])
        d._poll_neighbours(0)
        st = d.status()
        assert st["rejected"] == {"window.Z_P_min: invalid": 1, "window.Z_Qdot_min: invalid": 1}, st["rejected"]
        assert st["network"]["window_dropped"] == 2 and len(d._win_pending) == 8
    finally:
        d.close()


def test_a_layer_closes_a_window_whose_last_sample_it_did_not_see():
    """Review F2 item 5: a realtime coordinator that skips a window's last sample (49 with 50-sample windows)
    closes the window at the next sample it takes (the window of k + 1 past the current one), once; offline, which
    sees every sample, closes it at 49 as before. Before, only (k + 1) % per_window == 0 closed one: the window's
    message was never sent."""
    from service.network.layer import InterconnectionLayer

    net = load_network(SCENARIOS / "network" / "realtime.toml", ["events=[]", "timing.duration_s=0.3"])
    ns = len(net.sources)
    args = ([True] * ns, [True] * ns, [True] * ns)
    every = InterconnectionLayer(net, None)
    assert every.per_window == 50
    assert [k for k in range(150) if every.window_end(k, *args)[0] is not None] == [49, 99, 149]
    skips = InterconnectionLayer(net, None)
    closed = [(k, skips.window_end(k, *args)[0]) for k in [*range(49), 51, 52, *range(53, 99), 100, 101]]
    assert [c for c in closed if c[1] is not None] == [(51, 1), (100, 2)]
    late = InterconnectionLayer(net, None)  # started mid-run: its first window closes at that window's end
    assert [(k, late.window_end(k, *args)[0]) for k in (130, 149)] == [(130, None), (149, 3)]


def _step_as_before(sh, k, P, connected):
    """Sharing.step as it was (a new list per quantity per sample): the reference the in-place one must equal."""
    ns = sh.ns
    if sh.mode == "live-sum":
        shares = sh.shares
        if sh.ramp_ticks:
            for j in range(ns):
                if connected[j] and not sh.was_connected[j]:
                    sh.connected_at[j] = k
                sh.was_connected[j] = connected[j]
            shares = [s * min(1.0, (k - sh.connected_at[j]) / sh.ramp_ticks) if sh.connected_at[j] >= 0 else s
                      for j, s in enumerate(shares)]
        carrying = [j for j in range(ns) if connected[j] and abs(P[j]) >= sh.carry_power_W]
        total = sum(P[j] for j in carrying)
        weight = sum(shares[j] for j in carrying) or 1.0
        want = [-(shares[j] / weight) * total if connected[j] else 0.0 for j in range(ns)]
    else:
        want = [-P[j] for j in range(ns)]
    dt = (k - sh.k_prev) * sh.T if sh.k_prev is not None and k > sh.k_prev else 0.0
    for j in range(ns):
        raw = (want[j] - sh.want_prev[j]) / dt if dt else 0.0
        sh.want_rate[j] += sh.rate_alpha * (raw - sh.want_rate[j])
        sh.want_prev[j] = want[j]
    sh.k_prev = k
    return want, list(sh.want_rate)


@pytest.mark.parametrize("mode", ["live-sum", "none"])
def test_sharing_steps_in_place_to_the_same_bits(mode):
    """Review F2 item 6: Sharing.step updates its result lists in place (none allocated per sample on the loop
    thread) and gives the bits it gave with new lists: breakers that open and close (the plug-in ramp), sources
    under the carrying threshold, samples skipped."""
    import random

    from service.network.layer import Sharing

    rng = random.Random(7)
    shares = [2.0, 1.0, 1.0, 0.5]
    new = Sharing(shares, 1e-3, mode, 5.0, 0.05, [True, True, False, True])
    old = Sharing(shares, 1e-3, mode, 5.0, 0.05, [True, True, False, True])
    connected = [True, True, False, True]
    k, lists = 0, None
    for _ in range(3000):
        k += 1 if rng.random() < 0.9 else rng.randint(2, 5)
        if rng.random() < 0.01:
            j = rng.randrange(4)
            connected[j] = not connected[j]
        P = [rng.choice([rng.uniform(-10, 10), rng.uniform(-3000, 3000)]) if c else 0.0 for c in connected]
        want, rate = new.step(k, P, list(connected))
        ref_want, ref_rate = _step_as_before(old, k, P, list(connected))
        bits = [x.hex() for x in (*want, *rate)]
        assert bits == [x.hex() for x in (*ref_want, *ref_rate)], k  # the same bits (-0.0 told from 0.0 too)
        lists = lists or (want, rate)
        assert want is lists[0] and rate is lists[1]
