"""The JSON the controller daemon answers queries with (Zenoh queryables under ``<prefix>/<id>/``).

* ``status``: :class:`StatusReply`;
* ``config``: :class:`ConfigReply` (read only: a payload, or a ``set`` parameter, gets an error);
* ``config/set``: a :class:`ConfigSetRequest` payload, answered by :class:`ConfigSetReply`.

Each answer is one reply on the queryable's own key: JSON text (UTF-8) in an ordinary (ok) reply, or an
:class:`ErrorReply` in a Zenoh error reply. The body is Python's ``json.dumps``, which writes a non-finite float
as the bare token ``NaN``, ``Infinity`` or ``-Infinity``, outside strict JSON: a reader should accept those.
Objects with fixed keys list every key the daemon writes and forbid others; maps keyed by an id, a reason or a
topic are ``additionalProperties`` of one type.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, RootModel

from schemas.messages import Command, Measurement
from schemas.scenario import ControllerConfig

State = Literal["configured", "active", "inactive", "degraded", "failed", "shutdown"]


class Reply(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _no_default(schema: dict) -> None:
    schema.pop("default", None)


def _absent(description: str):
    """A key the daemon leaves out (rather than sending null) until it has a value: optional, not nullable."""
    return Field(default=None, description=description, json_schema_extra=_no_default)


class TimeDistribution(Reply):
    """A loop-time distribution over the newest ``loop.stats_window`` ticks (nearest-rank percentiles)."""

    mean: float = Field(description="mean, µs")
    p50: float = Field(description="median, µs")
    p99: float = Field(description="99th percentile, µs")
    max: float = Field(description="largest, µs")


class LoopStatus(Reply):
    """The loop thread's counters and time distributions."""

    rate_hz: float = Field(description="configured control rate (loop.rate_hz), Hz")
    trigger: Literal["clock", "sample"] = Field(description="what starts a tick (loop.trigger)")
    ticks: int = Field(ge=0, description="ticks since the start (clock trigger: every period, sample or not)")
    overruns: int = Field(ge=0, description="whole periods skipped because a tick ran late (clock trigger)")
    no_new_sample: int = Field(ge=0, description="clock ticks that found no new measurement")
    missing_samples: int = Field(ge=0, description="gaps in the measurement sequence (samples never ticked on)")
    lockstep_timeouts: int = Field(ge=0, description="sample trigger with lockstep: waits for the neighbours' "
                                                     "messages that timed out")
    overrun_pct: float = Field(description="overruns / (ticks + overruns), %")
    cpu_pct: float | None = Field(description="the process's CPU time (all its threads) as a share of one CPU "
                                              "since the first tick, %: 100 is a whole CPU; null before 1025 ticks")
    period_us: TimeDistribution = _absent("tick-to-tick interval, µs; absent until a tick has a predecessor")
    exec_us: TimeDistribution = _absent("a whole tick, µs; absent before the first tick")
    publish_us: TimeDistribution = _absent("of exec_us: the command's put (Zenoh's work on the loop thread), µs; "
                                           "absent before the first tick")
    compute_us: TimeDistribution = _absent("exec_us - publish_us: reading, checks, core, recording, µs; absent "
                                           "before the first tick")
    control_us: TimeDistribution = _absent("of compute_us: the control computation alone, over the ticks that "
                                           "computed a command, µs; absent until one did")
    meas_queue_dropped: int = Field(ge=0, description="sample trigger (wait=block): measurements the full queue "
                                                      "dropped while the loop thread was held up; else 0")
    meas_skipped: int = Field(ge=0, description="sample trigger (wait=block): frames the loop passed over, unchecked, "
                                                "to answer the newest loop.catch_up after a wait or a stall (counted, "
                                                "not rejected); else 0")


class StatusEstimate(Reply):
    """The estimator's energy-space quantities at the last stepped sample."""

    E: float = Field(description="stored energy, J")
    E_t: float = Field(description="stored energy in tangent space, J/s^2")
    p: float = Field(description="dE/dt, W")
    y_z: float = Field(description="output of interest R i^2 - u i, W")
    y_z_balance: float = Field(description="R-free output -(P_l + p), W")
    eta: float = Field(description="nonlinear term 4E_t + 2(R i - u) di/dt, W/s")
    P_r_out_port: float = Field(description="outgoing interaction P^{r,out} at the load port (-v i_load), W")
    Qdot_r_out_port: float = Field(description="outgoing reactive rate Qdot^{r,out} at the load port, W/s")


class NeighbourStatus(Reply):
    """What this controller last heard from one neighbour (ComponentConfig.neighbours)."""

    messages: int = Field(ge=0, description="interaction messages received from it")
    age_s: float | None = Field(description="time since its last message, s; null before the first")
    fresh: bool = Field(description="heard from within neighbour_stale_s and its liveliness token not gone")
    alive: bool | None = Field(description="its liveliness token: present (true), gone (false), not seen yet (null)")
    lagging: bool = Field(description="lockstep: it timed out once and is not waited for until it catches up")
    P_r_out: float = Field(description="its last outgoing interaction P^{r,out}, W")


class Violation(Reply):
    """One excursion of this component's outgoing rates outside the window's incoming range."""

    t: float = Field(description="start of the excursion, s")
    element: Literal["P", "Qdot"] = Field(description="which rate left its range")
    value: float = Field(description="its value there: P^{r,out} in W, Qdot^{r,out} in W/s")
    lo: float = Field(description="lower end of its incoming range, W or W/s as value")
    hi: float = Field(description="upper end of its incoming range, W or W/s as value")


class ForecastZOut(Reply):
    """The forecast range Z^{r,out} of this component's outgoing rates over the window."""

    P: tuple[float, float] = Field(description="[lowest, highest] P^{r,out}, W")
    P_dot: tuple[float, float] = Field(description="[lowest, highest] dP^{r,out}/dt, W/s")
    Qdot: tuple[float, float] = Field(description="[lowest, highest] Qdot^{r,out}, W/s")


class ForecastZIn(Reply):
    """The incoming range Z^{r,in} the neighbours' announced boxes give for the window."""

    P: tuple[float, float] = Field(description="[lowest, highest] P^{r,in}, W")
    Qdot: tuple[float, float] = Field(description="[lowest, highest] Qdot^{r,in}, W/s")


class ForecastStatus(Reply):
    """The forecast worker (forecast.enabled with neighbours): counters, and its newest window's result."""

    computed: int = Field(ge=0, description="forecasts run")
    cache_hits: int = Field(ge=0, description="windows answered from the forecast cache")
    infeasible_windows: int = Field(ge=0, description="windows forecast infeasible")
    errors: int = Field(ge=0, description="forecasts that failed (the worker process broke)")
    last_error: str = Field(description="the last failure, '' if none")
    last_compute_ms: float = Field(description="duration of the last forecast run, ms")
    window: int = _absent("index k of the window [k T_s, (k+1) T_s) of the newest result; absent (as are the keys "
                          "below) before the first result")
    feasible: bool = _absent("Z^{r,out} inside Z^{r,in} and no local saturation met")
    reason: str = _absent("'' when feasible, else what failed first")
    Z_out: ForecastZOut = _absent("forecast range of the outgoing rates")
    Z_in: ForecastZIn = _absent("incoming range from the neighbours' boxes")
    v_range: tuple[float, float] = _absent("[lowest, highest] terminal voltage over the forecast runs, V")
    u_range: tuple[float, float] = _absent("[lowest, highest] source voltage over the forecast runs, V")
    limited_ticks: int = _absent("forecast ticks at the du/dt or u limit")


class FeasibilityStatus(Reply):
    """Run-time check of the outgoing rates against each window's incoming range."""

    violations: int = Field(ge=0, description="excursions outside the incoming range since the start")
    tau_prime_s: float = Field(description="tau' = min(10 L/R, 1/K) of the incoming Qdot range, s")
    recent: list[Violation] = Field(description="the newest excursions (up to 5), oldest first")
    forecast: ForecastStatus | None = Field(description="null without a forecast worker (forecast.enabled false or "
                                                        "no neighbours)")


class LoopDelayStatus(Reply):
    """The loop delay measured from the newest ticks (which past command moved the measured u)."""

    measured_samples: int | None = Field(description="measured loop delay, samples; null when the commands were "
                                                     "too steady to tell or too few ticks")
    compensated_samples: int = Field(ge=0, description="the loop delay the core compensates, samples")
    mismatch: bool = Field(description="measured and not equal to compensated")
    window: int = Field(ge=0, description="ticks the measurement used (0 before the first sample)")
    explained: float | None = _absent("share of the measured du/dt the delayed commands explain (1 = all); null "
                                      "when undefined; absent before the first sample")
    contrast: float | None = _absent("how much better the best delay fits than the next best (0..1); null when "
                                     "undefined; absent before the first sample")


class LoggingStatus(Reply):
    """The recorder (log_dir set)."""

    path: str = Field(description="the MCAP file being written (the first of a rotated series)")
    written: int = Field(ge=0, description="messages written")
    drops: dict[str, int] = Field(description="messages dropped because the recorder's ring was full, by topic")
    state: Literal["ok", "degraded"] = Field(description="degraded: the recorder failed or could not start")
    error: str | None = Field(description="what failed, null if nothing (the recorder could not start: its "
                                          "reason, with written 0)")


class StatusReply(Reply):
    """The controller daemon's answer on ``<prefix>/<id>/status``."""

    id: str = Field(description="component id")
    version: str = Field(description="energyctl version")
    state: State = Field(description="lifecycle state; degraded: stale measurements, du/dt = 0 held until fresh "
                                     "ones return; failed: the loop ended by an unexpected exception (failure), u "
                                     "held, nothing more published, the process exits 1")
    failure: str = Field(description="why the state is failed: the thread, the exception and where it was raised; '' "
                                     "otherwise")
    config_version: int = Field(ge=0, description="run-time config changes applied (config/set)")
    loop: LoopStatus
    last_sample: Measurement | None = Field(description="the last accepted measurement; null before the first")
    last_command: Command | None = Field(description="the last command sent; null before the first")
    estimate: StatusEstimate | None = Field(description="null before the first estimate")
    z_out: tuple[float, float] = Field(description="[integral of P^{r,out} (J), integral of Qdot^{r,out} (W)]")
    y_ref: float = Field(description="the last reference y_ref, W")
    u_z: float = Field(description="the last energy-space control Qdot^u, W/s")
    neighbours: dict[str, NeighbourStatus] = Field(description="by neighbour id (ComponentConfig.neighbours)")
    feasibility: FeasibilityStatus
    rejected: dict[str, int] = Field(description="rejected or held measurements and neighbour messages, by reason "
                                                 "(e.g. 'meas.v: out of range', 'load.t: invalid'), those refused on "
                                                 "receipt included")
    last_reject: str = Field(description="the last rejection's reason and detail, '' if none")
    config_refused: int = Field(default=0, ge=0, description="config requests answered with an error: a config/set "
                                                             "that was malformed, invalid or not applied, and a set "
                                                             "sent to the read-only config key (each also logged: a "
                                                             "stderr line and a config_refused event, at most one "
                                                             "per second)")
    last_config_refused: str = Field(default="", description="the last refused config request: the key, then the "
                                                             "error it was answered with; '' if none")
    reference: Literal["neighbours", "none", "local"] = Field(
        description="where the last tick's P^{r,in} came from: the neighbours, none (du/dt = 0), or "
                    "local_reference_W")
    degraded_reason: str = Field(description="why the state is degraded (e.g. 'meas: stale'), '' otherwise")
    plant_restarts: int = Field(ge=0, description="times the plant's seq went back to 0 (the core was reset)")
    recovery_ticks: int = Field(default=0, ge=0, description="measurements with v out of range answered with the "
                                                            "recovery command (u ramped toward v_ref; recovery_ramp_s)")
    clock_resyncs: int = Field(default=0, ge=0, description="times samples off the clock the daemon held became its "
                                                          "new clock (meas_resync_frames after the stale time; the "
                                                          "core was reset)")
    refused_requests: int = Field(default=0, ge=0, description="config/set requests refused unread: above "
                                                             "query_max_bytes")
    late_command_ticks: int = Field(ge=0, description="ticks at which commands were seen not acting in time "
                                                      "(controller.late_detect_V)")
    current_limited_ticks: int = Field(default=0, ge=0, description="ticks whose command the nested law shaped at "
                                                                    "controller.limits.i_max_A (the source at its "
                                                                    "current limit)")
    loop_delay: LoopDelayStatus
    logging: LoggingStatus | None = Field(description="null without log_dir")


class ConfigReply(Reply):
    """The answer on ``<prefix>/<id>/config`` (a get without payload)."""

    controller: ControllerConfig = Field(description="the controller config in force")
    state: State = Field(description="lifecycle state")
    config_version: int = Field(ge=0, description="run-time config changes applied")


class ConfigSetRequest(BaseModel):
    """The payload of a get on ``<prefix>/<id>/config/set``. Only ``controller.*`` (not kind or mapping) and
    ``lifecycle`` can be set; the controller changes apply together between two ticks (the answer comes after), a
    lifecycle change at the loop's next pass."""

    model_config = ConfigDict(extra="allow")  # the daemon reads "set" and ignores any other key

    set: list[str] = Field(
        min_length=1, description="'key=value' strings: 'controller.<field>[.<field>]=<TOML value>' (a value that "
                                  "is not TOML is taken as a string), or 'lifecycle=active' / 'lifecycle=inactive'",
        json_schema_extra={"items": {"type": "string", "pattern": r"^(lifecycle=|controller\.[^=]+=)"}})


class ConfigSetApplied(Reply):
    """Accepted (an ok reply): the controller changes are in force; a lifecycle change is handed to the loop, which
    makes it at its next pass (status shows it)."""

    applied: list[str] = Field(description="the request's set strings, as given")
    config_version: int = Field(ge=0, description="run-time controller changes applied, this one included (a "
                                                  "lifecycle-only set does not count)")
    controller: ControllerConfig = Field(description="the controller config now in force")


class ErrorReply(Reply):
    """Any refusal, in a Zenoh error reply: a malformed request, a key that cannot be set, a validation error
    (``invalid config set (N errors):`` then one line per field, named relative to ``controller``), a change the
    loop did not take within 2 s, a set sent to ``config``, or an exception while answering."""

    error: str = Field(description="what was wrong")


class ConfigSetReply(RootModel[ConfigSetApplied | ErrorReply]):
    """The answer on ``<prefix>/<id>/config/set``: ConfigSetApplied in an ok reply, ErrorReply in an error reply."""


REPLY_MODELS: dict[str, type[BaseModel]] = {
    "energyctl.StatusReply": StatusReply,
    "energyctl.ConfigReply": ConfigReply,
    "energyctl.ConfigSetRequest": ConfigSetRequest,
    "energyctl.ConfigSetReply": ConfigSetReply,
    "energyctl.ErrorReply": ErrorReply,
}
