"""service.plant.rig.RigModel: the single-source plant side shared by the offline loop (service.sim) and the stand-in
plant (clients.peers.plant). It equals, to the bit, the loop service.sim ran before it existed (plant, sensor, delay
line, command disturbances, schedule inline), and the stand-in built from a scenario is the same rig as sim's."""

from __future__ import annotations

import threading
from collections import deque
from pathlib import Path

import numpy as np
import pytest

from schemas.component import PlantPeerConfig
from schemas.scenario import load_scenario
from service.core import make_core
from service.core.types import Incoming
from service.plant.profiles import Profile
from service.plant.rig import RigModel, substeps
from service.plant.rlc import CommandChannel, CommandSchedule, RLCPlant, Sensor, load_current

ROOT = Path(__file__).resolve().parents[2]


def _s(s) -> tuple:
    return s.seq, s.t, s.i, s.v, s.u, s.i_load
SCN = ROOT / "scenarios" / "paper-varying-load.toml"


def _old_sim_loop(scn, N: int) -> list[tuple]:
    """service.sim.run's plant side as it was written inline before RigModel: (t, i, v, u, sample, rate) per tick."""
    tm = scn.timing
    T = 1.0 / tm.control_rate_hz
    n_sub = substeps(T, tm.plant_step_s)
    load = Profile(scn.load, scn.base_dir)
    dist = Profile(scn.disturbance, scn.base_dir) if scn.disturbance is not None else None
    plant = RLCPlant(scn.plant, load, dist, "auto")
    sensor = Sensor(scn.sensor, scn.seed)
    core = make_core(scn.controller, scn.model, T, tm.delay_samples)
    delay = deque([(0.0, 0.0)] * tm.delay_samples)
    sched = CommandSchedule(0)
    channel = CommandChannel(tm, [scn.seed])
    inc = Incoming(0.0, 0.0)
    out_rows = []
    for k in range(N):
        t = plant.t
        P_l = load.value(t)
        i2 = load_current(P_l, plant.v, plant.v_min)
        s = sensor.measure(k, t, plant.i, plant.v, plant.u, i2)
        inc.P_r_in, inc.P_r_in_dot = -P_l, -load.rate(t)
        out = core.step(s, inc)
        if tm.delay_samples:
            delay.append((out.du_dt, out.du_dt_next))
            cmd = delay.popleft()
        else:
            cmd = (out.du_dt, out.du_dt_next)
        r = channel.deliver(sched, k, t, cmd)
        out_rows.append((t, plant.i, plant.v, plant.u, P_l, i2, _s(s), r))
        plant.advance(r, T, n_sub)
    return out_rows


def _rig_loop(scn, N: int) -> list[tuple]:
    tm = scn.timing
    rig = RigModel.of_scenario(scn)
    core = make_core(scn.controller, scn.model, 1.0 / tm.control_rate_hz, tm.delay_samples)
    inc = Incoming(0.0, 0.0)
    p = rig.plant
    out_rows = []
    for k in range(N):
        t = p.t
        s = rig.sample(k)
        inc.P_r_in, inc.P_r_in_dot = -rig.P_l, -rig.load.rate(t)
        out = core.step(s, inc)
        r = rig.command(k, out.du_dt, out.du_dt_next)
        out_rows.append((t, p.i, p.v, p.u, rig.P_l, rig.i_load, _s(s), r))
        rig.advance()
    return out_rows


@pytest.mark.parametrize("sets", [
    [],  # the paper's varying load, noise, 3 samples of delay
    ["timing.delay_samples=0"],
    # the command disturbances between the delay line and the schedule: losses, lateness, an outage
    ["timing.command_loss=0.1", "timing.command_late=0.1", "timing.command_outages=[[0.05, 0.01]]"],
])
def test_the_rig_equals_the_loop_sim_ran_inline(sets):
    scn = load_scenario(SCN, [*sets, "timing.duration_s=0.1"])
    N = int(round(scn.timing.duration_s * scn.timing.control_rate_hz))
    old, new = _old_sim_loop(scn, N), _rig_loop(scn, N)
    assert len(old) == len(new) == N
    assert old == new  # every state, sample and applied rate, to the bit


def test_sim_runs_on_the_rig():
    """service.sim.run's trace is the rig loop's (it drives a RigModel, nothing of its own)."""
    from service.sim import run

    scn = load_scenario(SCN, ["timing.duration_s=0.05", "timing.command_loss=0.05"])
    tr = run(scn).trace
    rows = _rig_loop(scn, len(tr["t"]))
    assert tr["v"].tolist() == [r[2] for r in rows]
    assert tr["du_dt_applied"].tolist() == [r[7] for r in rows]
    assert tr["v_meas"].tolist() == [r[6][3] for r in rows]


def _old_peer_lockstep(answers, d: int) -> list[float]:
    """The stand-in's lockstep command path as written before RigModel: the schedule first (each answer, or a
    timeout, at its own sample), then a delay line of the rates."""
    sched = CommandSchedule(0)
    delay = deque([0.0] * d)
    rates = []
    for k, a in enumerate(answers):
        if a is not None:
            sched.arrive(k, *a)
        r, _ = sched.take(k)
        if d:
            delay.append(r)
            r = delay.popleft()
        rates.append(r)
    return rates


def test_the_lockstep_stand_in_applies_what_it_did_before_with_timeouts():
    """Answers and timeouts (None) in any pattern: the rig's lockstep path (delay line, then the schedule, as
    offline) applies the same rate each period as the stand-in's old order (schedule, then a delay of rates): a
    timeout's period gets its predecessor's plan, else a hold, either way."""
    rng = np.random.default_rng(7)
    scn = load_scenario(SCN, [])
    for d in (0, 1, 3):
        for _ in range(30):
            answers = [None if rng.random() < 0.3 else (float(rng.normal()), float(rng.normal())) for _ in range(40)]
            rig = RigModel(scn.plant, scn.load, None, scn.sensor, 1, scn.base_dir, 1e-4, 1e-5, d)
            got = [rig.command(k, *(a if a is not None else (None,))) for k, a in enumerate(answers)]
            assert got == _old_peer_lockstep(answers, d)


def _old_peer_realtime(arrivals, apply_d: int, d: int, N: int) -> list[tuple]:
    sched = CommandSchedule(apply_d)
    delay = deque([0.0] * d)
    out = []
    for k in range(N):
        for seq, du, dn in arrivals.get(k, ()):
            sched.arrive(seq, du, dn)
        r, fresh = sched.take(k)
        latest = r
        if d:
            delay.append(r)
            r = delay.popleft()
        out.append((r, latest, fresh))
    return out


def test_the_realtime_stand_in_schedule_is_unchanged():
    rng = np.random.default_rng(3)
    scn = load_scenario(SCN, [])
    for apply_d, d in ((1, 0), (2, 0), (2, 1)):
        arrivals: dict[int, list] = {}
        for j in range(50):
            if rng.random() < 0.8:
                arrivals.setdefault(j + int(rng.integers(0, 4)), []).append((j, float(rng.normal()), 1.0 + j))
        rig = RigModel(scn.plant, scn.load, None, scn.sensor, 1, scn.base_dir, 1e-4, 1e-5, d, realtime=True,
                       apply_delay_samples=apply_d)
        got = []
        for k in range(55):
            for a in arrivals.get(k, ()):
                rig.arrive(*a)
            got.append(rig.take(k))
        assert got == _old_peer_realtime(arrivals, apply_d, d, 55)


def test_the_stand_in_plant_built_from_a_scenario_is_sims_rig():
    """energyctl demo's lockstep stand-in (clients.live's configs) holds a RigModel with sim's period, substeps,
    delay, schedule, sensor stream and plant state; driven by the same answers both apply the same rates and
    reach the same states."""
    from clients.live import configs_from_scenario
    from clients.peers.plant import PlantRig
    from schemas.component import config_from_dict

    scn = load_scenario(SCN, [])
    _, plant_cfg, _ = configs_from_scenario(scn, "tcp/127.0.0.1:7447", lockstep=True)
    peer = PlantRig(config_from_dict(PlantPeerConfig, plant_cfg), threading.Event())
    a, b = peer.rig, RigModel.of_scenario(scn)
    assert isinstance(a, RigModel)
    assert (a.T, a.n_sub, a.d, a.sched.d, a.realtime) == (b.T, b.n_sub, b.d, b.sched.d, False)
    rng = np.random.default_rng(5)
    for k in range(300):
        sa, sb = a.sample(k), b.sample(k)
        assert _s(sa) == _s(sb)
        du, dn = float(rng.normal(0, 1e3)), float(rng.normal(0, 1e3))
        assert a.command(k, du, dn) == b.command(k, du, dn)
        a.advance()
        b.advance()
    assert (a.plant.i, a.plant.v, a.plant.u) == (b.plant.i, b.plant.v, b.plant.u)


def test_the_network_rig_puts_each_sources_commands_through_the_same_path():
    """NetworkRigModel holds one CommandPath per source: with losses, lateness and an outage, the rates equal those
    of its old inline lists (a delay line, a CommandChannel seeded [seed, j] and a CommandSchedule per source)."""
    from schemas.network import load_network
    from service.network.netrig import NetworkRigModel

    net = load_network(ROOT / "scenarios" / "network" / "two-source.toml",
                       ["timing.command_loss=0.2", "timing.command_late=0.1", "timing.command_outages=[[0.01, 0.005]]"])
    rig = NetworkRigModel(net)
    tm, d, ns = net.timing, rig.d, len(rig.names)
    assert d > 0
    delays = [deque([(0.0, 0.0)] * d) for _ in range(ns)]
    scheds = [CommandSchedule(0) for _ in range(ns)]
    channels = [CommandChannel(tm, [net.seed, j]) for j in range(ns)]
    rng = np.random.default_rng(11)
    for k in range(300):
        rig.plant.t = k * rig.T
        for j in range(ns):
            du = None if rng.random() < 0.1 else float(rng.normal(0, 1e3))
            dn = float(rng.normal(0, 1e3))
            delays[j].append(None if du is None else (du, dn))
            old = channels[j].deliver(scheds[j], k, rig.plant.t, delays[j].popleft())
            assert rig.command(j, k, du, dn) == old
            assert rig.r[j] == old
    assert [s.counts for s in rig.scheds] == [s.counts for s in scheds]
