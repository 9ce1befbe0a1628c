"""A network scenario run live: the rig's and the coordinator's configs, and each source daemon's config derived from
the scenario. Every process of a live network reads the same scenario file (with the same ``--set`` overrides), so
the plant, the layer and each controller agree on it without another config to keep in step.

Keys (PREFIX: ``prefix``, default energyctl):

* the rig publishes each source's measurement on PREFIX/SOURCE/meas, each line end's interaction variable on
  PREFIX/LINE/z/NODE and each load's on PREFIX/LOAD/z, and the layer's sample on PREFIX/RIG/grid; it takes each
  source's command from PREFIX/SOURCE/cmd and breaker commands on PREFIX/RIG/breaker (a query);
* each source's daemon forms its share from the grid sample itself; the coordinator publishes each source's window
  message on PREFIX/SOURCE/window (v_ref, Z^{r,in}, once per window and at a breaker change) and answers
  PREFIX/COORDINATOR/status and PREFIX/COORDINATOR/connect (the plug-in handshake);
* every process holds the liveliness token PREFIX/ID/alive.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from schemas.component import ComponentConfig, LoopConfig, Named, NetworkRole, OutgoingForecastConfig, ZenohConfig
from schemas.network import NetworkScenario
from schemas.scenario import SecsPos


class NetworkRigConfig(Named):
    """``energyctl plant --config NETWORK.toml``: the hardware-in-the-loop stand-in of a whole network."""

    id: str = Field(default="rig", description="the rig's id (its grid and breaker keys, its liveliness token)")
    pacing: Literal["lockstep", "realtime"] = Field(
        default="lockstep", description="lockstep: sample k + 1 after every live source answered sample k (or "
                                        "lockstep_timeout_s passed, counted); realtime: on the wall clock")
    lockstep_timeout_s: Annotated[float, Field(gt=0, le=60)] = Field(default=2.0, description="longest wait for a "
                                                                                              "source's answer, s")
    wait_for: list[str] = Field(default=["coordinator"], description="ids whose liveliness the rig waits for before "
                                                                     "its first sample (the sources connected at the "
                                                                     "start are waited for too)")
    wait_s: SecsPos = Field(default=30.0, description="how long to wait for them, s")
    out: str | None = Field(default=None, description="the rig's MCAP log (true state, events, breakers)")
    interaction_rate_hz: Annotated[float, Field(gt=0, le=100_000)] = Field(
        default=1000.0, description="how often the lines' and loads' interaction variables are published, Hz (for "
                                    "the sources' status and logs; the layer's sample goes every period)")
    realtime_spin_us: Annotated[float, Field(ge=0, le=10_000)] = Field(
        default=60.0, description="realtime: spin this long before each sampling instant instead of sleeping, us")


class CoordinatorConfig(Named):
    """``energyctl coordinator NETWORK.toml``: the interconnection layer as a Zenoh service."""

    id: str = Field(default="coordinator", description="the coordinator's id")
    rig: str = Field(default="rig", description="the rig's id: its grid sample and its breaker query")
    lockstep: bool = Field(default=True, description="answer every grid sample in order (lockstep) rather than "
                                                     "only the newest")
    out: str | None = Field(default=None, description="the coordinator's MCAP log (the shares per sample, windows, "
                                                      "verdicts)")
    resume_timeout_s: SecsPos = Field(default=1.0, description="at start, how long to wait for "
                                                                                     "each source's config (its "
                                                                                     "v_ref) to resume from, s")
    trip_on_loss: bool = Field(default=True, description="a source whose liveliness token disappears is tripped: the "
                                                         "rig opens its breaker and its share is reallocated")


def source_component(net: NetworkScenario, source: str, *, prefix: str = "energyctl", zenoh: ZenohConfig | None = None,
                     lockstep: bool = True, log_dir: str | None = None, coordinator: str = "coordinator",
                     connect_at_s: float | None = None, core: str = "auto", rig: str = "rig") -> ComponentConfig:
    """The daemon config of one source of the network: its controller and its model (with the scenario's model
    error) as the offline run builds them, the network's rate and loop delay, a sample-triggered loop. connect_at_s
    None: the time of its first connect event in the scenario, if any."""
    if source not in net.sources:
        raise ValueError(f"{source!r} is not a source of {net.name!r} (sources: {', '.join(net.sources)})")
    src = net.sources[source]
    if connect_at_s is None:
        connect_at_s = next((e.t_s for e in net.events if e.kind == "connect" and e.target == source), None)
    lines = [name for name, ln in net.lines.items() if source in (ln.a, ln.b)]
    off = net.layer.v_ref_max_offset_V
    role = NetworkRole(network=net.name, coordinator=coordinator, lines=lines, idle_power_W=net.layer.idle_power_W,
                       v_ref_min_V=max(1e-3, src.controller.v_ref_V - off), v_ref_max_V=src.controller.v_ref_V + off,
                       # the most its measurements can show: the current bound at the voltage bound
                       P_max_W=ComponentConfig.model_fields["meas_i_max_A"].default * 2.5 * net.nominal_v_V,
                       idle_tau_s=net.layer.idle_tau_s, open_idle=net.layer.open_idle,
                       resume_ramp_s=net.layer.resume_ramp_s, fallback_idle_power_W=net.layer.fallback_idle_power_W,
                       extrapolate_s=net.layer.extrapolate_s, connect_at_s=connect_at_s,
                       connected_at_start=src.connected, fallback=net.fallback_of(source), rig=rig,
                       index=list(net.sources).index(source), shares=[s.share for s in net.sources.values()],
                       sources_connected=[s.connected for s in net.sources.values()], sharing=net.layer.mode,
                       carry_power_W=net.layer.idle_power_W, plug_in_ramp_s=net.layer.plug_in_ramp_s,
                       window_s=net.layer.window_s)
    v_nom = net.nominal_v_V
    return ComponentConfig(
        id=source, prefix=prefix, zenoh=zenoh or ZenohConfig(), model=src.model_params(), controller=src.controller,
        # realtime: after a stall, answer the queued samples whose commands can still act (within the loop delay)
        # in order, not only the newest (as the single source's realtime stack, clients.live)
        loop=LoopConfig(rate_hz=net.timing.control_rate_hz, trigger="sample", lockstep=lockstep,
                        catch_up=1 if lockstep else max(1, min(256, net.timing.delay_samples))),
        delay_samples=net.timing.delay_samples, core=core, log_dir=log_dir, network=role,
        forecast=OutgoingForecastConfig(enabled=False), forecast_window_s=net.layer.window_s,
        meas_v_min_V=0.25 * v_nom, meas_v_max_V=2.5 * v_nom)
