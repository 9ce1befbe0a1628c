"""A bus left out of the measurement range is brought back, not held there for good. A stall (the controller stopped,
a 10 MB request parsed under the GIL) left the plant at 0 V, and every later sample was held as `meas.v: out of
range` with du/dt = 0: the source voltage never moved again. Now, once no sample was stepped on for the stale time,
such samples are answered by the recovery command (u toward v_ref at v_ref / recovery_ramp_s; it reads u, never the
implausible v), and the law takes over at the first sample in range. The same brings up a bus that starts
discharged.

Closed loop by hand: the daemon's own _tick on each sample of an RLC plant (the paper's circuit, a 300 W
constant-power load, resistive below 5 V), its answer applied over the next period. (The paper's 1.2 kW is, below
5 V, a 21 mOhm resistor: no source without pre-charge brings a bus up through that; docs/limits.md.)"""

from __future__ import annotations

import pytest
from conftest import ROOT

from schemas.codec import MEAS
from schemas.scenario import PlantConfig, ProfileConfig, load_scenario
from service.plant.profiles import Profile
from service.plant.rlc import RLCPlant

T = 1e-4  # the daemon runs at 10 kHz
V_REF = 80.0
LOAD_W = 300.0


@pytest.fixture
def nested_daemon():
    """An opened daemon (loopback session, no neighbours' traffic) running the default law (the demo's scenario)."""
    from clients.live import configs_from_scenario
    from schemas.component import ComponentConfig, config_from_dict
    from service.daemon.bus import free_tcp_port
    from service.daemon.daemon import Daemon

    scn = load_scenario(ROOT / "clients" / "embedded" / "demo.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=1 / T)
    comp["loop"]["trigger"] = "clock"  # we call _tick ourselves
    comp["forecast"] = {"enabled": False}
    comp["local_reference_W"] = "measured"  # no neighbour in this test: the law's reference from the terminal
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    try:
        yield d
    finally:
        d.close()


def run_from(d, v0: float, u0: float, seconds: float) -> tuple[list[float], list[float]]:
    """The plant from (i = 0, v = v0, u = u0) under the daemon's answers; v (V) and du/dt (V/s) per period."""
    plant = RLCPlant(PlantConfig(initial={"i_A": 0.0, "v_V": v0, "u_V": u0}),
                     Profile(ProfileConfig(kind="constant", value=LOAD_W)))
    vs, dus = [], []
    for k in range(int(seconds / T)):
        i_load = plant.load.value(plant.t) / max(plant.v, plant.v_min)
        d._tick(MEAS.encode(k, plant.t, plant.i, plant.v, plant.u, i_load), int(k * T * 1e9))
        cmd = d.last_cmd
        du = cmd[2] if cmd is not None and cmd[0] == k else 0.0  # no answer: the plant holds u
        vs.append(plant.v)
        dus.append(du)
        plant.advance(du, T, 10)
    return vs, dus


def test_a_bus_left_at_zero_volts_is_brought_back_and_regulated(nested_daemon):
    d = nested_daemon
    stale = d._resync_ns / 1e9
    vs, dus = run_from(d, v0=0.2, u0=0.0, seconds=0.8)
    held = int(stale / T)  # a glitch shorter than the stale time is held (du/dt = 0)
    assert all(du == 0.0 for du in dus[:held - 1])
    ramp = V_REF / d.cfg.recovery_ramp_s
    assert 0 < dus[held + 1] <= ramp  # then u moves toward v_ref, at most at the recovery ramp
    assert d.recovery_ticks > 0 and d.rejected.get("meas.v: out of range", 0) >= held
    first_in = next(k for k, v in enumerate(vs) if v >= d.cfg.meas_v_min_V)
    assert d.recovery_ticks <= first_in  # only samples out of range were answered so
    # then the law regulates: within +-2 % of v_ref for the last 0.2 s, and never far above it on the way
    tail = vs[-int(0.2 / T):]
    assert max(abs(v - V_REF) for v in tail) <= 0.02 * V_REF, (min(tail), max(tail))
    assert max(vs) <= 1.25 * V_REF


def test_without_the_recovery_command_such_a_bus_stays_held_at_zero(nested_daemon):
    """The behaviour before (recovery_ramp_s = None: hold): every sample held, u never moves, v stays out of range."""
    d = nested_daemon
    d.cfg = d.cfg.model_copy(update={"recovery_ramp_s": None})
    vs, dus = run_from(d, v0=0.2, u0=0.0, seconds=0.2)
    assert all(du == 0.0 for du in dus) and max(vs) < d.cfg.meas_v_min_V and d.recovery_ticks == 0


def test_no_recovery_command_while_inactive_or_with_an_implausible_u(nested_daemon):
    """The recovery command moves the actuator: not while the operator has the daemon inactive, and not on a u it
    cannot trust (beyond meas_u_max_V): both held at du/dt = 0."""
    d = nested_daemon
    d.state = "inactive"
    _vs, dus = run_from(d, v0=0.2, u0=0.0, seconds=0.1)
    assert all(du == 0.0 for du in dus) and d.recovery_ticks == 0
    d.state = "active"
    later = int(1.0e9)  # well past the stale time
    d._tick(MEAS.encode(10_000, 1.0, 0.0, 0.2, 2 * d.cfg.meas_u_max_V, 0.0), later)
    assert d.last_cmd[2] == 0.0 and d.recovery_ticks == 0
    d._tick(MEAS.encode(10_001, 1.0 + T, 0.0, 0.2, 0.0, 0.0), later + int(T * 1e9))
    assert d.last_cmd[2] > 0.0 and d.recovery_ticks == 1  # the same sample with a plausible u: recovered
