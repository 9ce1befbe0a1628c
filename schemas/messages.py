"""Message models (SI units). The JSON Schemas in MCAP files and in schemas/json/ come from these."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

# The admissible range of the fields every message shares, here and only here: the codecs (schemas.codec) check
# every decoded frame against its model's bounds, and the JSON Schemas state them (docs/protocol.md, "Admissible
# ranges"). A u64 on the wire holds up to 2^64 - 1, more than what reads it can hold: the compiled tick and the core
# carry seq as an int64, but the logs' JSON records (read by Foxglove as JavaScript doubles) and a replay's double
# columns are exact only below 2^53; so a sequence number or a window index is below 2^53 (docs/decisions/0039).
# A time stamp t is a sample time on the plant's clock, s: not negative, and below 2^32 s (136 years), where its
# nanoseconds still fit the u64 log time of an MCAP record and t still resolves 2^-20 s (1 us, 1 % of a period at
# 10 kHz); a window index t / T_s then stays below 2^53 for any window above 0.5 us.
SEQ_LIMIT = 2**53
T_LIMIT_S = 2.0**32
Index = Annotated[int, Field(ge=0, lt=SEQ_LIMIT)]
SampleTime = Annotated[float, Field(ge=0.0, lt=T_LIMIT_S)]


class Msg(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Measurement(Msg):
    """One sample from the plant (topic ``.../meas``)."""

    seq: Index = Field(description="sample sequence number: 0 at the plant's start (0 again: it restarted), "
                                       "then one more per sampling period")
    t: SampleTime = Field(description="sample time, s")
    i: float = Field(description="source-branch current, A")
    v: float = Field(description="terminal voltage, V")
    u: float = Field(description="source voltage, V")
    i_load: float = Field(description="load current i_2, A")


class Command(Msg):
    """Voltage-rate command answering one measurement (topic ``.../cmd``)."""

    seq: Index = Field(description="sequence number of the measurement it answers")
    t: SampleTime = Field(description="time of the measurement it answers, s")
    du_dt: float = Field(description="commanded source voltage rate, V/s")
    du_dt_next: float = Field(default=0.0, description="du/dt planned for the period after this command's, V/s: "
                                                       "what the plant applies there if the next command is missing "
                                                       "or late (0: hold u)")
    limited: bool = Field(default=False, description="the command was clipped by actuator limits")


class Interaction(Msg):
    """A component's outgoing interaction variable and its forecast range for a window (topic ``.../z``).

    A neighbour forms its incoming variable as P^{r,in} = -sum_j P_j^{r,out} (paper Eqn PsiMap).
    """

    seq: Index = Field(description="lockstep pacing: seq of the measurement the message answers (a lockstep "
                                       "controller waits for it); otherwise a count of the sender's messages")
    t: SampleTime = Field(description="time the rates refer to, s")
    P_r_out: float = Field(description="outgoing instantaneous power P^{r,out}, W")
    P_r_out_dot: float = Field(description="its rate dP^{r,out}/dt, W/s")
    Qdot_r_out: float = Field(description="outgoing reactive power rate Qdot^{r,out}, W/s")
    z_out0: float = Field(description="integral of P^{r,out}, J")
    z_out1: float = Field(description="integral of Qdot^{r,out}, W")
    window: Index = Field(description="index k of the window [k T_s, (k+1) T_s) the range is for: the current "
                                          "one during its first half, the next one during its second half")
    P_min: float = Field(description="lower end of the forecast range of P^{r,out} over the window, W")
    P_max: float = Field(description="upper end of that range, W")
    P_dot_min: float = Field(description="lower end of the forecast range of dP^{r,out}/dt over the window, W/s")
    P_dot_max: float = Field(description="upper end of that range, W/s")


class Estimate(Msg):
    """Estimator internals and energy-space signals (topic ``.../est``)."""

    t: SampleTime = Field(description="sample time of the tick, s")
    E: float = Field(description="stored energy, J")
    p: float = Field(description="dE/dt, W")
    E_t: float = Field(description="stored energy in tangent space, J/s^2")
    y_z: float = Field(description="output of interest R i^2 - u i, W")
    y_z_balance: float = Field(description="R-free output -(P_l + p), W")
    y_ref: float = Field(description="reference P^{r,in} v_ref / v, W")
    eta: float = Field(description="nonlinear term 4E_t + 2(R i - u) di/dt, W/s")
    u_z: float = Field(description="energy-space control Qdot^u, W/s")
    P_r_out: float = Field(description="outgoing interaction rate P^{r,out}, W")
    Qdot_r_out: float = Field(description="outgoing interaction rate Qdot^{r,out}, W/s")
    z_out0: float = Field(description="integral of P^{r,out}, J")
    z_out1: float = Field(description="integral of Qdot^{r,out}, W")


class TickInput(Msg):
    """What the core was given besides the measurement on one tick (topic ``.../z_in``): enough to replay it."""

    seq: Index = Field(description="measurement seq of the tick")
    t: SampleTime = Field(description="sample time of the tick, s")
    P_r_in: float = Field(description="incoming interaction P^{r,in} = -sum_j P_j^{r,out}, W")
    P_r_in_dot: float = Field(description="its rate, W/s")
    stepped: bool = Field(description="false: the core was not stepped (inactive or no fresh reference), du/dt = 0")


class LoopRecord(Msg):
    """Loop counters every N ticks (topic ``.../loop``); percentiles are in the status query."""

    t: SampleTime = Field(description="sample time of the tick, s")
    ticks: int = Field(ge=0, description="ticks since the start")
    overruns: int = Field(ge=0, description="whole periods skipped (clock trigger), since the start")
    no_new_sample: int = Field(ge=0, description="clock ticks that found no new measurement, since the start")
    missing_samples: int = Field(ge=0, description="gaps in the measurement sequence (samples never ticked on), "
                                                   "since the start")
    exec_max_ns: int = Field(ge=0, description="longest tick since the previous record, ns")
    period_max_ns: int = Field(ge=0, description="longest tick-to-tick interval since the previous record, ns")


class Event(Msg):
    """Diagnostics and events (topic ``.../events``): config changes, lifecycle, rejections, recorder drops."""

    t: float = Field(description="s (sample time of the tick it belongs to, or monotonic time)")
    seq: Index = Field(description="measurement seq the event precedes (config changes apply before it)")
    kind: str = Field(description="what happened, e.g. config, config_refused, reject, degraded, plant_restart, "
                                  "neighbour_alive, neighbour_gone, forecast, recorder_drops, failed")
    detail: str = Field(description="JSON text (config, forecast, plant_restart, recorder_drops) or plain text "
                                    "(reject, degraded, failed: the reason; config_refused: the key and the error "
                                    "answered; neighbour_alive, neighbour_gone: its id)")


class Plant(Msg):
    """True plant state in simulation (topic ``.../plant``); not available on real hardware."""

    t: SampleTime = Field(description="sample time, s")
    i: float = Field(description="true source-branch current, A")
    v: float = Field(description="true terminal voltage, V")
    u: float = Field(description="true source voltage, V")
    P_l: float = Field(description="load power, W")


class Allocation(Msg):
    """No longer sent (decision 0042: LayerWindow, the source forming its share itself); older runs' logs carry it.
    The interconnection layer's word to one network source for one sample (topic ``.../<source>/alloc``, from the
    coordinator): what it is to deliver, its voltage reference, its breaker as the rig reported it, and its
    feasibility range Z^{r,in} for the window."""

    seq: Index = Field(description="seq of the network sample it answers (a lockstep source waits for it)")
    t: SampleTime = Field(description="time of that sample, s (a source judges its age against its own sample's t)")
    P_r_in: float = Field(description="P^{r,in} the source is to follow, W (negative: it delivers)")
    P_r_in_dot: float = Field(description="its filtered rate, W/s (a late message is carried forward along it)")
    v_ref_V: float = Field(description="the source's voltage reference, as the layer last moved it, V")
    connected: bool = Field(description="its breaker was closed at that sample")
    window: Index = Field(description="the layer's window the range is for")
    has_range: bool = Field(description="a range is set for the window (false: the source is not connected)")
    Z_P_min: float = Field(description="Z^{r,in}: lower end of the incoming power range, W")
    Z_P_max: float = Field(description="upper end of the incoming power range, W")
    Z_Qdot_min: float = Field(description="lower end of the incoming reactive-power-rate range, W/s")
    Z_Qdot_max: float = Field(description="upper end of that range, W/s")


class LayerWindow(Msg):
    """The interconnection layer's word to one network source for a window (topic ``.../<source>/window``, from the
    coordinator): sent at the first grid sample it takes, at each window's end (for the next window) and when a
    breaker changes. The source forms P^{r,in} = -alpha_s sum_k P_k itself every sample from the rig's grid sample
    (service.network.layer.Sharing); this carries what changes per window: its v_ref, its range Z^{r,in}, the
    breaker as the coordinator saw it and its share alpha_s then. A source without it keeps the last one."""

    seq: Index = Field(description="the first sample it applies to (a lockstep source waits for it at a window's "
                                   "start, at a breaker change and at its first sample)")
    t: SampleTime = Field(description="the time of the sample it was made after, s")
    window: Index = Field(description="the layer's window it is for")
    alpha: Annotated[float, Field(ge=0.0, le=1.0)] = Field(
        description="alpha_s: the source's share of the load among the sources connected then (0: not connected)")
    v_ref_V: float = Field(description="the source's voltage reference, as the layer last moved it, V")
    connected: bool = Field(description="its breaker was closed at that sample")
    has_range: bool = Field(description="a range is set for the window (false: the source is not connected)")
    Z_P_min: float = Field(description="Z^{r,in}: lower end of the incoming power range, W")
    Z_P_max: float = Field(description="upper end of the incoming power range, W")
    Z_Qdot_min: float = Field(description="lower end of the incoming reactive-power-rate range, W/s")
    Z_Qdot_max: float = Field(description="upper end of that range, W/s")


class GridSample(Msg):
    """The network rig's sample for the interconnection layer (topic ``.../<rig>/grid``), in scenario order. Its wire
    form is not fixed-size: magic 0x47, version, seq (u64), t (f64), then u16 counts of sources, buses and loads, then
    f64 arrays: each source's measured v and i_out and 1.0/0.0 for its breaker, the buses' measured voltages, the
    loads' true powers (schemas.codec.GRID)."""

    seq: Index = Field(description="network sample seq")
    t: SampleTime = Field(description="sample time, s")
    v: list[float] = Field(description="each source's measured terminal voltage, V")
    i_out: list[float] = Field(description="each source's measured current into its lines, A")
    connected: list[bool] = Field(description="each source's breaker closed")
    bus_v: list[float] = Field(description="each bus's measured voltage, V")
    load_P: list[float] = Field(description="each load's power, W")


class LayerSource(Msg):
    """What the coordinator saw of one source and answered it, per sample (recorded only, ``.../layer/<source>``):
    enough to replay its allocations."""

    seq: Index = Field(description="network sample seq")
    t: SampleTime = Field(description="sample time, s")
    v: float = Field(description="the source's measured terminal voltage, V")
    i_out: float = Field(description="its measured current into its lines, A")
    connected: bool = Field(description="its breaker closed")
    P_r_in: float = Field(description="the P^{r,in} allocated, W")
    P_r_in_dot: float = Field(description="its filtered rate, W/s")
    v_ref_V: float = Field(description="the v_ref sent, V")


class LayerTick(Msg):
    """The coordinator's per-sample window inputs (recorded only, ``.../layer/tick``)."""

    seq: Index = Field(description="network sample seq")
    t: SampleTime = Field(description="sample time, s")
    bus_v_mean: float = Field(description="the buses' mean measured voltage, V (0 without buses)")
    load_W: float = Field(description="the loads' total power, W")
    has_buses: bool = Field(description="the network has buses (the window's voltage mean counts this sample)")


MESSAGE_MODELS: dict[str, type[Msg]] = {
    "energyctl.Measurement": Measurement,
    "energyctl.Command": Command,
    "energyctl.Estimate": Estimate,
    "energyctl.Interaction": Interaction,
    "energyctl.TickInput": TickInput,
    "energyctl.Allocation": Allocation,
    "energyctl.LayerWindow": LayerWindow,
    "energyctl.GridSample": GridSample,
    "energyctl.LayerSource": LayerSource,
    "energyctl.LayerTick": LayerTick,
    "energyctl.Event": Event,
    "energyctl.LoopRecord": LoopRecord,
    "energyctl.Plant": Plant,
}


def json_schema(model: type[BaseModel]) -> dict:
    """The model's plain JSON Schema: what recordings carry for their JSON-encoded channels. The files in
    schemas/json add the binary wire layout (schemas.generate)."""
    return model.model_json_schema()
