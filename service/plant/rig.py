"""The plant side of one source's closed loop: the RLC plant with its load (and disturbance) profile, its sensor, the
loop delay and the command schedule. Pure: no clocks, no I/O.

The offline loop (``service.sim.run``) and the hardware-in-the-loop stand-in (``energyctl plant``,
``clients.peers.plant``) drive this one class, so that both sample, delay and apply commands the same way to the bit
(as ``service.network.netrig.NetworkRigModel`` does for a network). Per sample k: ``sample(k)`` measures the plant at
t = plant.t (the load's power P_l (W) and current i_load (A) at that instant are kept in ``P_l`` and ``i_load``);
``command(k, du, du_next)`` takes the answer to sample k (du/dt and the planned du/dt of the next period, V/s; None:
none came) through the d-sample loop delay, timing's command disturbances (``channel``) and the command schedule, and
returns the rate the converter applies over period k; ``advance()`` integrates one period at that rate.

Realtime (``realtime=True``), commands come when they come: ``arrive(seq, ...)`` files the answer to sample seq and
``take(k)`` gives the rate over period k: the answer to sample k - apply_delay, else its predecessor's plan, else a
hold (``CommandSchedule``), then the plant's own extra delay of d samples.
"""

from __future__ import annotations

import math
from collections import deque

from service.core.types import Sample
from service.plant.profiles import Profile
from service.plant.rlc import CommandChannel, CommandSchedule, RLCPlant, Sensor, load_current


def substeps(period_s: float, plant_step_s: float) -> int:
    """Plant integration steps per control period: ceil(period_s / plant_step_s), at least 1."""
    return max(1, math.ceil(period_s / plant_step_s - 1e-9))


class CommandPath:
    """One source's commands on their way to its converter: the loop delay, timing's command disturbances and the
    command schedule (pure: no clock, no I/O). RigModel has one, NetworkRigModel one per source.

    Lockstep and offline (``command``): the answer to sample k (None: none came) goes through a d-sample delay line
    first, then the disturbances (``channel``: loss, lateness, outages; None for none), then the schedule takes each
    command for its own period (a lost one never arrives: its predecessor's plan, else a hold). Realtime (``arrive``,
    ``take``): commands come when they come, the schedule's own delay (apply_delay samples) says which acts over a
    period, and a further d-sample delay line of rates follows it (a stand-in plant's extra actuation delay)."""

    def __init__(self, d: int, channel: CommandChannel | None = None, realtime: bool = False, apply_delay: int = 0):
        self.d = d
        self.channel = channel
        self.delay: deque = deque([0.0] * d if realtime else [(0.0, 0.0)] * d)
        self.sched = CommandSchedule(apply_delay if realtime else 0)
        self.r = 0.0  # the rate applied over the current period (V/s)

    def command(self, k: int, t: float, du: float | None, du_next: float = 0.0) -> float:
        """The answer to sample k (du/dt, planned du/dt V/s; None: none came) at plant time t (s): the rate the
        converter applies over period k (V/s)."""
        got = None if du is None else (du, du_next)
        if self.d:
            q = self.delay
            q.append(got)
            got = q.popleft()
        sched = self.sched
        if self.channel is not None:
            self.r = self.channel.deliver(sched, k, t, got)
        else:
            if got is not None:
                sched.arrive(k, *got)
            self.r = sched.take(k)[0]
        return self.r

    def arrive(self, seq: int, du: float, du_next: float) -> None:
        """Realtime: the answer to sample seq came."""
        self.sched.arrive(seq, du, du_next)

    def take(self, k: int) -> tuple[float, float, bool]:
        """Realtime: (the rate applied over period k after the delay line, the schedule's rate for k, whether that
        is the command meant for k rather than a plan or a hold)."""
        r, fresh = self.sched.take(k)
        if self.d:
            q = self.delay
            q.append(r)
            self.r = q.popleft()
        else:
            self.r = r
        return self.r, r, fresh


class RigModel:
    """See the module docstring. ``plant`` is the RLCPlant, ``load`` / ``dist`` its profiles, ``path`` the
    commands' way to the converter (CommandPath) and ``sched`` its schedule."""

    def __init__(self, plant, load, disturbance, sensor, seed: int, base_dir, T: float, plant_step_s: float,
                 delay_samples: int, impl: str = "auto", timing=None, realtime: bool = False,
                 apply_delay_samples: int = 1):
        """plant, load, disturbance, sensor: their configs (PlantConfig, LoadConfig, ProfileConfig or None,
        SensorConfig); seed: the sensor's (and the command disturbances'); base_dir: where relative csv paths are;
        T: the control period (s); delay_samples: the loop delay d (samples); timing: a CommandDisturbances (a
        scenario's timing) whose command loss, lateness and outages apply between the delay line and the schedule,
        None for none; realtime: see the module docstring (apply_delay_samples: the schedule's delay there)."""
        self.load = Profile(load, base_dir)
        self.dist = Profile(disturbance, base_dir) if disturbance is not None else None
        self.plant = RLCPlant(plant, self.load, self.dist, impl)
        self.sensor = Sensor(sensor, seed)
        self.T = T
        self.n_sub = substeps(T, plant_step_s)
        self.d = delay_samples
        self.realtime = realtime
        self.path = CommandPath(delay_samples, CommandChannel(timing, [seed]) if timing is not None else None,
                                realtime, apply_delay_samples)
        self.sched = self.path.sched
        self.arrive, self.take = self.path.arrive, self.path.take
        self.P_l = self.i_load = 0.0

    @classmethod
    def of_scenario(cls, scn, impl: str = "auto") -> RigModel:
        """The rig of a single-source Scenario, as ``energyctl sim`` runs it."""
        tm = scn.timing
        return cls(scn.plant, scn.load, scn.disturbance, scn.sensor, scn.seed, scn.base_dir, 1.0 / tm.control_rate_hz,
                   tm.plant_step_s, tm.delay_samples, impl, timing=tm)

    def sample(self, k: int) -> Sample:
        """The sensor's measurement of sample k at t = plant.t (the load's P_l and i_load kept for the trace)."""
        p = self.plant
        t = p.t
        self.P_l = P_l = self.load.value(t)
        self.i_load = i2 = load_current(P_l, p.v, p.v_min)
        return self.sensor.measure(k, t, p.i, p.v, p.u, i2)

    def command(self, k: int, du: float | None, du_next: float = 0.0) -> float:
        """The answer to sample k (None: none came) through the loop delay, the command disturbances and the
        schedule: the rate the converter applies over period k (V/s)."""
        return self.path.command(k, self.plant.t, du, du_next)

    def advance(self) -> None:
        """Integrate one control period at the rate ``r``."""
        self.plant.advance(self.path.r, self.T, self.n_sub)
