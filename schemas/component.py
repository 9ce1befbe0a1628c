"""Configuration of the live processes: controller daemon, HIL plant peer, neighbour load peer."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, Field, ValidationError, field_validator, model_validator

from schemas.scenario import (
    AcceptanceConfig,
    Amp,
    CircuitParams,
    ControllerConfig,
    LoadConfig,
    Margin,
    OutgoingForecastConfig,
    PlantConfig,
    ProfileConfig,
    ScenarioError,
    Secs,
    SecsPos,
    Seed,
    SensorConfig,
    Strict,
    Volt,
    Watt,
    WattNonNeg,
    WattPos,
    apply_overrides,
    format_validation_error,
    read_toml,
)

_ID = re.compile(r"^[A-Za-z0-9_\-]+$")


class ZenohConfig(Strict):
    """How to open the Zenoh session. ``config_file`` (Zenoh JSON5) is passed through unchanged, as
    Zenoh's own tools take ``-c``; the other fields are applied on top of it only when given."""

    mode: Literal["peer", "client", "router"] = Field(default="peer", description="Zenoh session mode")
    listen: list[str] = Field(default=[], description="Zenoh endpoints to listen on, e.g. tcp/0.0.0.0:7447; a peer "
                                                       "given none, no config_file, no multicast scouting and only "
                                                       "loopback connect endpoints listens on tcp/127.0.0.1:0, so "
                                                       "that Zenoh's gossip links this host's peers over loopback; "
                                                       "any other peer given none listens where Zenoh's default "
                                                       "says (every interface)")
    connect: list[str] = Field(default=[], description="Zenoh endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    config_file: str | None = Field(default=None, description="Zenoh JSON5 config file, used as it is (relative "
                                                              "paths: from the config file's directory)")
    multicast_scouting: bool = Field(default=False, description="find peers by UDP multicast")
    user: str | None = Field(default=None, description="user/password authentication (transport/auth/usrpwd): "
                                                       "this session's user name, its identity in the router's ACL")
    password_file: str | None = Field(default=None, description="file holding the password (first line); relative "
                                                                "paths are taken from the config file's directory")

    tx_queue_batches: Annotated[int, Field(ge=1, le=256)] | None = Field(
        default=None, description="Zenoh's transport/link/tx/queue/size/data: how many batches a link's send queue "
                                  "holds for data-priority messages (every measurement, command and interaction "
                                  "message is one express batch). A publisher that finds it full waits up to 1 ms "
                                  "and then drops the message (congestion control DROP). Zenoh's own default, 2, "
                                  "dropped samples and commands whenever its send thread stalled for a millisecond "
                                  "on this 2-vCPU machine; unset: 16, or the config_file's value when one is given")
    shared_memory: bool | None = Field(
        default=None, description="Zenoh's transport/shared_memory/enabled: with it, Zenoh puts every message over "
                                  "3 KiB (here: the status replies, once a diverged run's rejects make them longer) "
                                  "through a 16 MiB shared-memory pool it creates at that moment, and the pool's "
                                  "pages become resident as its chunks go round: a 10 kHz soak's daemon grew 26 MB "
                                  "in one minute. Our hot-path messages are under 100 B and never use it. Unset: "
                                  "off, or the config_file's value when one is given")
    open_timeout_s: Annotated[float, Field(ge=0.1, le=60.0)] | None = Field(
        default=None, description="Zenoh's transport/unicast/open_timeout: how long a link's Zenoh handshake may take "
                                  "(s). It also bounds a session's close: a peer that stopped reading (SIGSTOP) "
                                  "accepts the TCP connection its gossip makes a new session dial but never answers "
                                  "the handshake, and the close waits for that dial (9.5 s at Zenoh's 10 s). Unset: "
                                  "10, or the config_file's value; `energyctl query` uses 2 unless it is set")
    tls_root_ca: str | None = Field(default=None, description="TLS (tls/ endpoints): the CA certificate that signed "
                                                             "the router's certificate (PEM file)")
    tls_certificate: str | None = Field(default=None, description="mutual TLS: this session's certificate (PEM), "
                                                                 "its common name the identity in the router's ACL")
    tls_private_key: str | None = Field(default=None, description="mutual TLS: its private key (PEM file, not "
                                                                 "readable by group or others)")

    @model_validator(mode="after")
    def _credentials(self):
        if (self.user is None) != (self.password_file is None):
            raise ValueError("zenoh.user and zenoh.password_file go together")
        if (self.tls_certificate is None) != (self.tls_private_key is None):
            raise ValueError("zenoh.tls_certificate and zenoh.tls_private_key go together")
        return self


def cpus_exist(v: list[int] | None) -> list[int] | None:
    """A CPU list for sched_setaffinity: None (any), or CPUs this machine has (not only those the validating process
    may use: a bench kept to CPU 0 starts a daemon for CPU 1)."""
    import os

    if v is not None:
        if not v:
            raise ValueError("no CPU given: name at least one, or leave it unset for any")
        n = os.cpu_count() or 1
        missing = sorted(c for c in set(v) if c >= n)
        if missing:
            raise ValueError(f"CPUs {missing} are not on this machine (it has CPUs 0-{n - 1})")
    return v


# a CPU list for sched_setaffinity (None: any CPU)
CpuList = Annotated[list[Annotated[int, Field(ge=0, le=1023)]] | None, AfterValidator(cpus_exist)]


class Named(Strict):
    id: str = Field(description="component id: letters, digits, '_' and '-'")
    prefix: str = Field(default="energyctl", description="key-expression prefix")
    zenoh: ZenohConfig = ZenohConfig()
    nice: Annotated[int, Field(ge=-20, le=19)] | None = Field(
        default=None, description="scheduling priority (Unix nice value) of the whole process, Zenoh's threads "
                                  "included, set before anything starts; below 0 needs CAP_SYS_NICE (refused: one "
                                  "line on stderr, and it runs at the priority it was started with). Its recorder "
                                  "and forecast processes always run below it (service.priority)")
    timer_slack_ns: Annotated[int, Field(ge=0, le=1_000_000_000)] = Field(
        default=1000, description="how late the kernel may end this process's timed waits (sleeps, queue timeouts) "
                                  "on purpose, ns; Linux's default is 50 000, half a period at 10 kHz. Set like nice, "
                                  "before anything starts; 0 leaves the inherited value. Its recorder and forecast "
                                  "processes go back to 50 000 (service.priority)")
    malloc_mmap_threshold_bytes: Annotated[int, Field(ge=0, le=1 << 30)] = Field(
        default=131072, description="glibc: blocks of this size (bytes) or more get their own mapping, returned to the "
                                    "system when freed, and the threshold stays fixed (glibc raises it to each such "
                                    "block freed, up to 32 MiB, after which large temporaries stay resident in "
                                    "thread arenas); 0 leaves glibc's dynamic threshold. Set before anything starts")
    cpus: CpuList = Field(
        default=None, description="CPUs the whole process may run on (sched_setaffinity), Zenoh's threads included, "
                                  "set before anything starts; None = any. A process kept on one CPU hands work "
                                  "between its own threads without waking another CPU (on a 2-vCPU VM that "
                                  "took Zenoh's put from 90-100 us to 27-32 us)")

    @field_validator("id")
    @classmethod
    def _id(cls, v: str) -> str:
        if not _ID.match(v):
            raise ValueError("must match [A-Za-z0-9_-]+")
        return v

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, v: str) -> str:
        if not v or any(not _ID.match(p) for p in v.split("/")):
            raise ValueError("must be '/'-separated [A-Za-z0-9_-]+ chunks")
        return v


class LoopConfig(Strict):
    rate_hz: Annotated[float, Field(ge=1000, le=20000)] = Field(
        default=10000.0, description="control rate, Hz: the clock trigger's tick rate, and the period the core "
                                     "plans with (the plant's sample rate)")
    trigger: Literal["clock", "sample"] = Field(
        default="clock", description="clock: own absolute-time schedule; sample: each new measurement ticks")
    lockstep: bool = Field(default=False, description="sample trigger also waits for each neighbour's "
                                                       "interaction variable stamped with the sample's seq")
    lockstep_timeout_s: Annotated[float, Field(gt=0, le=60)] = Field(
        default=2.0, description="lockstep: longest wait for the neighbours' messages for a sample, s (then the "
                                 "tick goes ahead and the late neighbour is not waited for until it catches up)")
    spin_margin_s: Annotated[float, Field(ge=0, le=0.01)] = Field(
        default=2e-4, description="clock trigger: sleep until this long before each tick, then spin, s")
    wait: Literal["block", "spin"] = Field(
        default="block", description="sample trigger: block on the queue (frees the core), or spin on it (lower "
                                     "wake-up latency on an idle machine, but it costs a whole core, which the "
                                     "plant and Zenoh's threads then lack on a small one)")
    catch_up: Annotated[int, Field(ge=1, le=256)] = Field(
        default=1, description="sample trigger: when several samples queued up, answer up to this many of the "
                               "newest, oldest first (each gets its command; older ones count as missing); 1 = only "
                               "the newest")
    stats_window: Annotated[int, Field(ge=100, le=10_000_000)] = Field(
        default=100_000, description="ticks the status query's loop-time distributions cover (the newest)")


class NetworkRole(Strict):
    """A source daemon's part in a live network (``energyctl run --network``): what it forms its share from (the
    rig's grid sample, the network's shares), where its window messages come from, the line ends at its terminal it
    shows as neighbours, and when it asks to connect."""

    network: str = Field(description="the network scenario's name")
    coordinator: str = Field(default="coordinator", description="the coordinator's id: its window messages come "
                                                                "on PREFIX/ID/window, connect requests go to "
                                                                "PREFIX/COORDINATOR/connect")
    lines: list[str] = Field(default=[], description="the lines at its terminal: neighbours on PREFIX/LINE/z/ID")
    idle_power_W: WattNonNeg = Field(default=30.0, description="below this |P^{r,in}| (and "
                                                                                  "whenever disconnected) it holds "
                                                                                  "its voltage (idle mode), W")
    idle_tau_s: SecsPos = Field(default=0.005, description="idle mode's time constant, s")
    open_idle: Literal["droop", "hold"] = Field(default="droop", description="disconnected: the idle droop law, or "
                                                                             "hold u")
    fallback_idle_power_W: WattNonNeg | None = Field(
        default=None, description="in fallback it idles below this |own terminal power| instead, W (None: "
                                  "idle_power_W)")
    fallback: Literal["last-allocation", "own-terminal"] = Field(
        default="last-allocation", description="a stale grid sample: keep its last P^{r,in} (plus the change of its "
                                               "own terminal's power since; the nested law), or follow its own "
                                               "terminal's power alone")
    resume_ramp_s: Secs = Field(default=0.0, description="after a fallback, from its own "
                                                                                  "terminal's power to its share "
                                                                                  "linearly over this long, s")
    stale_s: SecsPos = Field(default=0.01, description="a grid sample older than this (sample "
                                                                             "time) is stale: the source falls back "
                                                                             "(its last share, or its own terminal), s")
    extrapolate_s: Secs = Field(default=0.002, description="a late P^{r,in} is carried "
                                                                                    "forward along its rate by at "
                                                                                    "most this, s")
    connect_at_s: Secs | None = Field(
        default=None, description="from this sample time on (s), while its breaker is open, it asks the coordinator to "
                                  "connect (the plug-in handshake; again after connect_retry_s when refused or "
                                  "tripped); none: it never asks")
    connected_at_start: bool = Field(default=False, description="the scenario has it connected from the start: a "
                                     "daemon whose first grid sample shows its breaker open (restarted after a "
                                     "trip) asks to connect by itself, connect_at_s unset")
    connect_retry_s: SecsPos = Field(default=0.5, description="sample time between two "
                                                                                    "connect requests, s")
    v_ref_min_V: Volt | None = Field(default=None, description="a window message whose v_ref "
                                                                                      "is below this is refused "
                                                                                      "(counted), V")
    v_ref_max_V: Volt | None = Field(default=None, description="a window message whose v_ref "
                                                                                      "is above this is refused, V")
    P_max_W: WattPos = Field(default=1e6, description="a grid sample whose power at a terminal |v i_out| is above "
                                                      "this is refused (counted), W")
    # what it shares with (service.network.layer.Sharing): it forms P^{r,in} = -alpha_s sum_k P_k itself each sample
    # from the rig's grid sample (PREFIX/RIG/grid); the coordinator sends v_ref and Z^{r,in} per window
    rig: str = Field(default="rig", description="the rig's id: its grid sample PREFIX/RIG/grid is what the sharing is "
                                                "formed from")
    index: Annotated[int, Field(ge=0, le=65535)] = Field(
        default=0, description="its position among the network's sources (the grid sample's order)")
    shares: list[Annotated[float, Field(gt=0, le=1e6)]] = Field(
        default=[1.0], description="every source's share of the load, in the network's order (layer: the sources' "
                                   "share)")
    sources_connected: list[bool] = Field(default=[True], description="which sources start connected, in the "
                                                                      "network's order")
    sharing: Literal["none", "live-sum"] = Field(
        default="live-sum", description="the layer's mode: none: its own lines' power; live-sum: its share of all "
                                        "connected sources' line powers")
    carry_power_W: WattNonNeg = Field(default=0.0, description="a source whose lines draw less than this |power| is "
                                                               "left out of the live sum (layer.idle_power_W), W")
    plug_in_ramp_s: Secs = Field(default=0.0, description="a source that connects takes its share linearly over this "
                                                          "long (layer.plug_in_ramp_s), s")
    window_s: SecsPos = Field(default=0.05, description="the layer's window (layer.window_s): a lockstep source waits "
                                                        "for the coordinator's window message at each window's "
                                                        "start, s")

    @model_validator(mode="after")
    def _index_in_shares(self):
        if len(self.sources_connected) != len(self.shares):
            raise ValueError(f"sources_connected: {len(self.sources_connected)} entries for {len(self.shares)} shares")
        if self.index >= len(self.shares):
            raise ValueError(f"index: {self.index} is not below the {len(self.shares)} sources")
        return self


class ComponentConfig(Named):
    """``energyctl run --config``: the controller daemon for one component."""

    model: CircuitParams = CircuitParams()
    controller: ControllerConfig = ControllerConfig()
    loop: LoopConfig = LoopConfig()
    delay_samples: Annotated[int, Field(ge=0, le=200)] = Field(
        default=2, description="loop delay the core predicts over unless controller.delay_compensation_samples "
                               "(samples)")
    neighbours: list[str] = Field(default=[], description="ids whose interaction variables form P^{r,in}")
    network: NetworkRole | None = Field(default=None, description="a source on a live network: its P^{r,in} is its "
                                                                  "share formed from the rig's grid sample, not "
                                                                  "from neighbours (energyctl run --network)")
    core: Literal["auto", "c", "python"] = Field(
        default="auto", description="the control core's implementation: 'c' the compiled twin (the daemon refuses "
                                    "to start without it), 'python' the reference (the same bits, about 25x the CPU "
                                    "per step), 'auto' c if it was built at install")
    interaction_rate_hz: Annotated[float, Field(gt=0, le=20000)] = Field(
        default=1000.0, description="rate of this component's interaction messages on .../z, Hz (every "
                                    "round(loop.rate_hz / this) ticks)")
    forecast_window_s: SecsPos = Field(
        default=1.0, description="length T_s of the windows the interaction ranges and forecasts are for, s")
    forecast: OutgoingForecastConfig = Field(
        default=OutgoingForecastConfig(enabled=True),
        description="forecast this component's Z^{r,out} for each window the neighbours announce, publish it on "
                    ".../z and check it against Z^{r,in} ahead of the window (in a worker process)")
    neighbour_stale_s: SecsPos = Field(
        default=0.05, description="a neighbour not heard from for this long is not fresh (no reference from it), s")
    neighbour_extrapolate_s: Secs = Field(
        default=0.01, description="how far a neighbour's rate carries its last P to the sample's time (s), forward "
                                  "or back (a sample answered after a stall is older than the message): P_j + dP_j/dt "
                                  "age, |age| clamped to this; 0: its last value as it is. Beyond a message period "
                                  "or two a rate is a guess: a 200 Hz load silent for 32 ms was carried 560 W off and "
                                  "the realtime loop left the band")
    plant_id: str | None = Field(default=None, description="id whose .../meas this controller reads (default: id)")
    meas_v_min_V: Volt = Field(
        default=1.0, description="reject measurements with v below, V (answered with du/dt = 0)")
    meas_v_max_V: Volt = Field(
        default=1000.0, description="reject measurements with v above, V (answered with du/dt = 0)")
    meas_i_max_A: Amp = Field(
        default=1000.0, description="reject measurements with |i| or |i_load| above, A (answered with du/dt = 0)")
    meas_u_max_V: Volt = Field(
        default=1000.0, description="hold measurements with |u| above, V (answered with du/dt = 0)")
    recovery_ramp_s: SecsPos | None = Field(
        default=0.1, description="while measurements are held for v out of [meas_v_min_V, meas_v_max_V] and none was "
                                 "stepped on for the stale time (stale_periods, at least 50 ms), the daemon answers "
                                 "them with a recovery command that moves the source voltage u toward v_ref at "
                                 "v_ref / recovery_ramp_s (at most the slew limit), landing on it (a soft start), "
                                 "s; None: hold du/dt = 0 for as long as v is out of range")
    meas_max_gap_s: Annotated[float, Field(gt=0, le=60)] = Field(
        default=0.1, description="a measurement whose seq is more than this many seconds of samples after the last "
                                 "one stepped on is not taken as the next sample (rejected, no answer): a lone frame "
                                 "is not the plant's new clock (docs/protocol.md, \"The plant's clock\")")
    meas_clock_tolerance_s: Annotated[float, Field(gt=0, le=1)] | None = Field(
        default=None, description="a measurement whose t differs from the last stepped one's t + (seq gap) x period by "
                                  "more than this is not taken as the next sample (rejected, no answer), s; None: half "
                                  "a period")
    meas_resync_frames: Annotated[int, Field(ge=2, le=1000)] = Field(
        default=3, description="after no sample was stepped on for the stale time (stale_periods, at least 50 ms), "
                               "this many measurements in a row that agree with each other (seq and t as above) "
                               "become the new clock: the core is re-initialised, as at a plant restart")
    neighbour_P_max_W: WattPos | None = Field(
        default=None, description="a neighbour's interaction message with |P_r_out|, |P_min| or |P_max| above this is "
                                  "rejected (counted by field), its rates (P_r_out_dot, Qdot_r_out, P_dot_min, "
                                  "P_dot_max) above this x loop.rate_hz too, W; None: meas_v_max_V x meas_i_max_A")
    log_live_hz: Annotated[float, Field(ge=0, le=1000)] = Field(
        default=0.0, description="the recorder's process also publishes the estimates (est), the tick's inputs (z_in) "
                                 "and every event (events) on PREFIX/ID/est, z_in and events, as the JSON the log "
                                 "holds, est and z_in at most this often per second of sample time, for live views "
                                 "(energyctl foxglove); dropped under congestion, background priority; needs logging "
                                 "on; 0: off, Hz")
    query_max_bytes: Annotated[int, Field(ge=1024, le=16 << 20)] = Field(
        default=65536, description="a config/set request larger than this is refused before it is read (not parsed, "
                                   "not echoed), bytes")
    stale_periods: Annotated[int, Field(ge=1, le=100000)] = Field(
        default=10, description="this many periods without a measurement -> degraded, du/dt = 0 "
                                "(sample trigger: at least 50 ms)")
    local_reference_W: Watt | Literal["measured"] | None = Field(
        default=None, description="while a neighbour is silent or gone: a load power to assume (W), or 'measured' "
                                  "(v * i_load at this component's port); None: hold du/dt = 0")
    log_dir: str | None = Field(default=None, description="record to <log_dir>/<id>-<UTC time>.mcap (off the loop)")
    log_est_every: Annotated[int, Field(ge=1, le=100000)] = Field(default=10, description="estimator record decimation")
    log_rotate_bytes: Annotated[int, Field(ge=1 << 20, le=1 << 40)] | None = Field(
        default=None, description="start a new file (<name>-1.mcap, -2, ...) after about this many bytes of JSON")
    log_rotate_s: SecsPos | None = Field(
        default=None, description="start a new file after this much log time (s)")
    log_queue: Annotated[int, Field(ge=1024, le=4_194_304)] = Field(
        default=131_072, description="recorder ring slots (128 B each); full = counted drop, never a wait")
    log_writer_cpus: CpuList = Field(
        default=None, description="CPUs the recorder's writer process may run on (sched_setaffinity); None = any. "
                                  "Keep it off the CPU the loop runs on: on 2 vCPUs, [1] halved the loop overruns "
                                  "the writer adds")


class PlantPeerConfig(Named):
    """``energyctl plant --config``: the hardware-in-the-loop stand-in."""

    controller_id: str = Field(description="id whose .../cmd the plant applies (its measurements go there too)")
    wait_for: list[str] = Field(default=[], description="other ids whose liveliness token must be up before starting")
    plant: PlantConfig = PlantConfig()
    load: LoadConfig = LoadConfig()
    disturbance: ProfileConfig | None = Field(default=None, description="matched disturbance voltage profile (V); "
                                                                       "None: none")
    sensor: SensorConfig = SensorConfig()
    sample_rate_hz: Annotated[float, Field(ge=100, le=100_000)] = Field(
        default=10000.0, description="rate of the measurements on .../meas, Hz")
    plant_step_s: Annotated[float, Field(gt=0, le=1e-3)] = Field(
        default=1e-5, description="the plant's integration step, s")
    delay_samples: Annotated[int, Field(ge=0, le=200)] = Field(
        default=0, description="extra actuation delay the plant adds (lockstep: the whole loop delay), samples")
    pacing: Literal["lockstep", "realtime"] = Field(
        default="realtime", description="lockstep: after each sample the plant waits for the command answering "
                                        "it (simulated time); realtime: samples on the wall clock's schedule")
    realtime_apply_delay_samples: Annotated[int, Field(ge=1, le=200)] = Field(
        default=1, description="realtime: the command answering sample k acts from sampling instant k + this "
                               "(samples)")
    lockstep_timeout_s: Annotated[float, Field(gt=0, le=60)] = Field(
        default=2.0, description="lockstep: longest wait for a command, s")
    realtime_spin_us: Annotated[float, Field(ge=0, le=1000)] = Field(
        default=60.0, description="realtime: the plant sleeps until this long before each "
                                  "sampling instant and spins the rest (µs): a timed wait here ends 17 µs late "
                                  "p50, 87 µs p99 (energyctl bench wake), and the spin costs this much CPU per "
                                  "period")
    duration_s: Annotated[float, Field(gt=0, le=86400)] = Field(default=2.0, description="length of the run, s")
    start_delay_s: Annotated[float, Field(ge=0, le=60)] = Field(
        default=0.0, description="wait this long after the peers in wait_for are up before the first sample, s")
    seed: Seed = Field(default=1, description="seed of the sensor noise")
    v_ref_V: Volt = Field(default=80.0, description="the voltage reference the run's metrics are judged "
                                                     "against, V")
    acceptance: AcceptanceConfig = Field(default=AcceptanceConfig(), description="the criteria the run's metrics "
                                         "are judged by (a scenario's [acceptance]): divergence, the band and where "
                                         "it must hold")
    out: str | None = Field(default=None, description="write the run's trace and metrics here (.mcap, .json)")
    base_dir: str = Field(default=".", description="directory for relative csv paths (set by the loader)")


class LoadPeerConfig(Named):
    """``energyctl load --config``: the neighbour Sigma_2, a constant-power load."""

    load: LoadConfig = LoadConfig()
    rate_hz: Annotated[float, Field(gt=0, le=20000)] = Field(
        default=1000.0, description="realtime: rate of the interaction messages on .../z, Hz")
    window_s: SecsPos = Field(
        default=1.0, description="length T_s of the windows the announced load ranges are for, s")
    forecast_margin: Margin = Field(
        default=0.05, description="relative widening of the announced load range (fraction of its largest "
                                  "magnitude, each side)")
    pacing: Literal["lockstep", "realtime"] = Field(
        default="realtime", description="lockstep: one message per sample of plant_id, stamped with its seq and "
                                        "time; realtime: rate_hz on the wall clock, stamped with the plant's time")
    plant_id: str | None = Field(default=None, description="lockstep: answer each sample of this id's .../meas")
    duration_s: Annotated[float, Field(gt=0, le=86400)] = Field(default=3600.0, description="length of the run, s")
    log_dir: str | None = Field(default=None, description="record published messages to <log_dir>/<id>-<time>.mcap")
    base_dir: str = Field(default=".", description="directory for relative csv paths (set by the loader)")


def load_config(kind: type[BaseModel], path: str | Path, overrides: list[str] | None = None):
    """Read and validate a TOML config of the given model; errors name the field.

    ``extends = "OTHER.toml"`` (relative to this file) starts from another config: tables merge key by
    key, anything else in this file replaces the other's value."""
    p = Path(path)
    data = _read_toml(p, kind, [])
    return config_from_dict(kind, data, overrides, str(p))


MAX_EXTENDS = 8  # files in an 'extends' chain after the first (the longest here: 1)


def _read_toml(p: Path, kind: type[BaseModel], seen: list[Path]) -> dict:
    if p.resolve() in seen:
        raise ScenarioError(f"config {p}: 'extends' loops back to itself ({' -> '.join(map(str, seen))})")
    if len(seen) > MAX_EXTENDS:
        raise ScenarioError(f"config {seen[0]}: 'extends' chains more than {MAX_EXTENDS} files (stopped at {p})")
    data = read_toml(p, "config")
    own_base_dir = "base_dir" in data
    if "base_dir" in kind.model_fields:
        data.setdefault("base_dir", str(p.parent.resolve()))
    z = data.get("zenoh")
    if isinstance(z, dict):  # Zenoh file paths in a config file are relative to that file
        for f in ("password_file", "config_file", "tls_root_ca", "tls_certificate", "tls_private_key"):
            if isinstance(z.get(f), str) and not Path(z[f]).is_absolute():
                z[f] = str((p.parent / z[f]).resolve())
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ScenarioError(f"config {p}: extends: expected a file name")
    parent = _read_toml(p.parent / base, kind, [*seen, p.resolve()])
    if not own_base_dir and "base_dir" in parent:  # relative data paths stay those of the file that has them
        data["base_dir"] = parent["base_dir"]
    return merge_tables(parent, data)


def merge_tables(base: dict, over: dict) -> dict:
    """``over`` on top of ``base``, as a new dict: tables merge key by key, anything else replaces."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge_tables(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def config_from_dict(kind: type[BaseModel], data: dict, overrides: list[str] | None = None, source: str = ""):
    data = apply_overrides(data, overrides or [])
    try:
        return kind.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(format_validation_error(err, source, what="config")) from None
