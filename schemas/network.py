"""Network scenarios: several controllable sources on a DC network, each with its own controller, lines and loads
as their neighbours, and the interconnection layer that shares the load between the sources.

Elements are tables keyed by name (``[sources.S1]``, ``[lines.L1]``, ``[buses.B1]``, ``[loads.P1]``), so that an
override names them: ``--set sources.S1.controller.K_per_s=800``. Every name is unique across all kinds; a line
joins two nodes, each a bus or a source's terminal. A source is the paper's Sigma_1 (a controllable voltage u
behind R, L into its terminal capacitor C); a line is R, L between two nodes; a bus is a capacitor; a load draws
constant power (resistive below ``v_min_V``) or is a resistor.

Sign conventions (docs/control.md): a line's current is positive from its ``a`` end to its ``b`` end; a source's
terminal current ``i_out`` is what leaves its terminal into its lines, and its incoming interaction variable
P^{r,in} is the power its lines draw at its terminal, oriented out of the source.
"""

from __future__ import annotations

import re
from collections import deque
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from schemas.scenario import (
    AcceptanceConfig,
    CircuitParams,
    CommandDisturbances,
    ControllerConfig,
    Farad,
    Henry,
    Ohm,
    ProfileConfig,
    ScenarioError,
    Secs,
    SecsPos,
    Seed,
    SensorConfig,
    SourceLimits,
    Strict,
    Volt,
    VoltNonNeg,
    Watt,
    WattNonNeg,
    _bounded,
    apply_overrides,
    format_validation_error,
    read_toml,
)

NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")


Share = _bounded(0, 1e6, open_lo=True)  # a source's share of the load, relative to the others'
OhmPos = _bounded(0, 1e6, open_lo=True)

NETWORK_CONTROLLER_DEFAULTS = {"load_power": "reference", "nested_K_E_per_s": 200.0}  # see SourceConfig.controller


class ModelError(Strict):
    """The controller's model of its own source, relative to the true circuit: model = true x (1 + error)."""

    R: Annotated[float, Field(gt=-1, lt=10)] = Field(default=0.0, description="relative error of R (-0.1: 10 % low)")
    L: Annotated[float, Field(gt=-1, lt=10)] = Field(default=0.0, description="relative error of L")
    C: Annotated[float, Field(gt=-1, lt=10)] = Field(default=0.0, description="relative error of C")


class SourceConfig(CircuitParams):
    """One controllable source: its true circuit (R_ohm, L_H, C_F), its actuator's limits, its controller."""

    limits: SourceLimits = SourceLimits()
    model_error: ModelError = ModelError()
    controller: ControllerConfig = Field(
        default=ControllerConfig(**NETWORK_CONTROLLER_DEFAULTS),
        description="its controller; on a network two defaults differ: load_power = 'reference' (the law's "
                    "feed-forward is the layer's allocation -P^{r,in}, its share of the load, not its own lines' "
                    "power) and nested_K_E_per_s = 200 /s (the layer sets the voltage once per window; a stiff "
                    "terminal-energy loop, 1 500 /s, held each terminal where the lines put it and left the sharing "
                    "2.3 pp off)")
    share: Share = Field(default=1.0, description="its share of the network's load under the interconnection layer "
                                                "(relative to the other sources' shares)")
    connected: bool = Field(default=True, description="its line breakers start closed; false: it starts idle, "
                                                      "disconnected, until a connect event")
    v0_V: Volt | None = Field(default=None, description="initial terminal voltage with start = \"rest\", V; "
                                                       "default: the network's nominal_v_V (a steady start "
                                                       "computes it)")

    @model_validator(mode="before")
    @classmethod
    def _allocation_is_the_load(cls, data):
        """controller.load_power: 'reference' unless the scenario names it (see the controller field)."""
        if isinstance(data, dict) and isinstance(data.get("controller"), dict):
            data = {**data, "controller": {**NETWORK_CONTROLLER_DEFAULTS, **data["controller"]}}
        return data

    def model_params(self) -> CircuitParams:
        """The controller's (wrong) model of this source."""
        e = self.model_error
        return CircuitParams(R_ohm=self.R_ohm * (1 + e.R), L_H=self.L_H * (1 + e.L), C_F=self.C_F * (1 + e.C))


class BusConfig(Strict):
    """A junction of lines and loads, with its capacitance."""

    C_F: Farad = Field(description="bus capacitance, F (a bus without capacitance is refused: the node needs a "
                                 "state)")
    v0_V: Volt | None = Field(default=None, description="initial voltage with start = \"rest\", V; default: the "
                                                       "network's nominal_v_V (a steady start computes it)")


class LineConfig(Strict):
    """A series R-L line between two nodes (a bus or a source's terminal), behind a breaker."""

    a: str = Field(description="the node at its a end (a bus or a source); current is positive from a to b")
    b: str = Field(description="the node at its b end (a bus or a source)")
    R_ohm: Ohm = Field(description="series resistance, Ω")
    L_H: Henry = Field(description="series inductance, H")
    closed: bool = Field(default=True, description="the breaker's initial state (a source's connected flag opens "
                                                   "its lines)")

    @model_validator(mode="after")
    def _ends(self) -> LineConfig:
        if self.a == self.b:
            raise ValueError(f"a line must join two different nodes (a = b = {self.a!r})")
        return self


class LoadAtBus(ProfileConfig):
    """A load at a bus: constant power following its profile (W), or a resistor."""

    bus: str = Field(description="the bus it draws from")
    type: Literal["cpl", "resistive"] = Field(default="cpl", description="cpl: constant power P(t) from the "
                                                                          "profile; resistive: R_ohm")
    value: Watt = Field(default=1200.0, description="the load power, or the base of steps "
                                                                           "and sines, W")
    R_ohm: OhmPos | None = Field(default=None, description="resistive: its resistance, Ω")
    v_min_V: Volt = Field(default=5.0, description="cpl: below this voltage it draws as a resistor, V")
    active_from_s: Secs = Field(default=0.0,
                                 description="the load draws nothing before this time, s (a load switched in)")

    @model_validator(mode="after")
    def _resistor(self) -> LoadAtBus:
        if self.type == "resistive" and self.R_ohm is None:
            raise ValueError("a resistive load needs R_ohm")
        if self.type == "resistive" and (self.ou is not None or self.off_at_s or self.on_at_s):
            raise ValueError("a resistive load has no profile: ou, off_at_s and on_at_s go with type 'cpl' "
                             "(active_from_s switches a resistor in)")
        return self


class EventConfig(Strict):
    """A timed event: a breaker trips or closes, or a source asks to connect (the layer decides)."""

    t_s: Secs = Field(description="when, s")
    kind: Literal["trip", "close", "connect"] = Field(
        description="trip: open the breakers (of a line, or of every line at a source); close: close them; "
                    "connect: the source asks the interconnection layer to connect it (closed only if feasible)")
    target: str = Field(description="a line's name, or a source's name (all its lines)")


class LinkConfig(Strict):
    """How the interaction variables reach the controllers: delay and loss (per receiving source, or all)."""

    delay_s: Secs = Field(default=0.0, description="extra delay of each interaction message, s (whole control "
                                                     "periods: rounded to the nearest)")
    loss: Annotated[float, Field(ge=0, lt=1)] = Field(default=0.0, description="probability a message is lost, "
                                                                               "seeded")
    silent_from_s: Secs | None = Field(default=None, description="from this time on no message arrives, s")
    silent_until_s: Secs | None = Field(default=None, description="the silence ends here, s (None: it lasts): a "
                                                                     "coordinator that goes away and comes back")


class LayerConfig(Strict):
    """The interconnection layer: shares the incoming interaction among the sources and restores the bus voltage."""

    mode: Literal["none", "live-sum"] = Field(
        default="live-sum", description="none: each source follows the power its own lines draw; live-sum: each "
                                        "sample, source s follows share_s x the sum of all connected sources' line "
                                        "powers")
    window_s: SecsPos = Field(default=0.05, description="the layer's window: v_ref moves and feasibility is checked "
                                                    "once per window, s")
    v_ref_gain: Annotated[float, Field(ge=0, le=1)] = Field(
        default=0.5, description="per window, every source's v_ref moves by this x (nominal - the mean bus "
                                 "voltage over the window); 0: off")
    v_ref_mode: Literal["common", "per-source"] = Field(
        default="per-source", description="common: one v_ref offset for all; per-source: each source's v_ref moves "
                                          "to its own terminal's window mean plus that correction, which removes "
                                          "the sharing error a common v_ref leaves (P at a terminal = P^{r,in} "
                                          "v_ref / v at steady state)")
    v_ref_max_offset_V: VoltNonNeg = Field(default=8.0, description="bound of that v_ref offset, V")
    extrapolate_s: Secs = Field(default=0.0, description="a late P^{r,in} is carried forward along its rate by its "
                                                             "age, at most this long, s; 0: used as it came. The "
                                                             "nested law follows its allocation fast enough that "
                                                             "carrying it forward closes a loop through the live sum: "
                                                             "with 5 ms late messages the sharing was 8-39 pp off "
                                                             "and the bus 6 % high; at 0 they keep the figures. The "
                                                             "paper's fblc wants 0.002 (1 ms late messages keep the "
                                                             "two-source figures; 10 ms diverged 5 ms late ones)")
    idle_power_W: WattNonNeg = Field(default=0.0, description="below this |power| a source's lines count as idle "
                                                          "(excluded from the live sum; its controller idles), W. 0: "
                                                          "only a disconnected source idles (the nested law holds "
                                                          "zero and reversed power); the paper's fblc needs about "
                                                          "30 W, its output y_z losing control of u at zero current")
    idle_tau_s: SecsPos = Field(default=0.005, description="an idle source moves u to v_ref - 0.4 ohm x i with this "
                                                           "time constant, s")
    plug_in_ramp_s: Secs = Field(default=0.0, description="live-sum: a source that connects takes its share "
                                                            "linearly over this long, s (0: at once)")
    fallback_idle_power_W: WattNonNeg | None = Field(
        default=None, description="in fallback (P^{r,in} stale) a source idles below this |own terminal power| "
                                  "instead of idle_power_W, W (None: idle_power_W). At 1 kHz a source left in "
                                  "fallback near zero current rang up the mapping's fast mode u/(i L) and diverged")
    fallback: Literal["last-allocation", "own-terminal"] | None = Field(
        default=None, description="a source whose P^{r,in} is stale keeps the last P^{r,in} it was allocated (its "
                                  "share; a change of its own terminal's power since is followed on top), or follows "
                                  "its own terminal's power alone (the sources then split by their lines and v_refs: "
                                  "a just plugged-in one kept what its v_ref gave it, 228 of its 600 W). None: "
                                  "last-allocation for the nested law, own-terminal for the others (the paper's law "
                                  "regulates its power to P^{r,in}, so a kept gap grows without bound)")
    resume_ramp_s: Secs = Field(default=0.0, description="a source whose P^{r,in} is fresh again after a fallback "
                                                           "moves from its own terminal's power to it linearly over "
                                                           "this long, s (0: at once; a returning coordinator then "
                                                           "stepped the sources back to their shares)")
    open_v_ref: Literal["common", "bus"] = Field(
        default="bus", description="the v_ref a disconnected source gets each window: the common one, or the "
                                      "buses' mean voltage (it waits at the voltage it will close onto)")
    open_idle: Literal["droop", "hold"] = Field(
        default="droop", description="what a disconnected source does: 'droop' as an idle one (u -> v_ref - 0.4 ohm x "
                                     "i), 'hold' u (du/dt = 0). At 1 kHz with 2-4 ms of loop delay the droop law rang "
                                     "the open terminal's L-C resonance (57 Hz) up until it diverged; hold does not")


class NetworkAcceptance(AcceptanceConfig):
    """What a network run must meet for ``energyctl sim`` and ``sweep`` to exit 0 (else 1, naming the run and the
    criterion): no node a source supplies leaves +-diverge_dev_pct of nominal_v_V, and every bus stays inside the
    band where the band must hold (a bus no source reaches, a blackout, fails the band)."""

    hold_from_s: Secs | None = Field(
        default=0.2, description="from this time on every bus must stay inside the band, s (the layer restores the "
                                 "buses over a few of its windows after the start); unset: the band is not required "
                                 "(only divergence is checked)")
    recover_s: Secs = Field(
        default=0.2, description="after each event (a breaker, a connect request, a load's step or on/off switch) "
                                 "the buses need not be inside the band for this long, s (the layer restores them "
                                 "over a few of its windows)")


class NetworkTiming(CommandDisturbances):
    """The network's timing; the command disturbances act on every source's commands, each its own seeded draw."""

    control_rate_hz: Annotated[float, Field(ge=100, le=100_000)] = Field(
        default=10_000.0, description="sampling and control rate of every source, Hz")
    plant_step_s: Annotated[float, Field(gt=0, le=1e-3)] = Field(default=1e-5, description="integration step, s")
    delay_samples: Annotated[int, Field(ge=0, le=200)] = Field(
        default=2, description="loop delay of every source: the command answering sample k acts from k + this")
    duration_s: Annotated[float, Field(gt=0, le=3600)] = Field(default=1.0, description="simulated time, s")


class NetworkScenario(Strict):
    """A DC network of controllable sources, lines, buses and loads (see the module docstring)."""

    kind: Literal["network"] = Field(description="'network': tells a network scenario from a one-source one")
    name: str = Field(default="network", description="name of the scenario")
    description: str = Field(default="", description="free text")
    seed: Seed = Field(default=1, description="seed of the sensor noise and the interaction-message losses")
    nominal_v_V: Volt = Field(default=80.0, description="the network's nominal voltage, V")
    start: Literal["steady", "rest"] = Field(
        default="steady", description="steady: the network starts at the DC operating point of its loads at t = 0, "
                                      "shared as configured; rest: every current zero, every voltage nominal")
    timing: NetworkTiming = NetworkTiming()
    sensor: SensorConfig = SensorConfig()
    sources: dict[str, SourceConfig] = Field(description="the controllable sources, by name")
    buses: dict[str, BusConfig] = Field(default={}, description="the buses, by name")
    lines: dict[str, LineConfig] = Field(default={}, description="the lines, by name")
    loads: dict[str, LoadAtBus] = Field(default={}, description="the loads, by name")
    events: list[EventConfig] = Field(default=[], description="timed breaker and connect events")
    load_scale: Annotated[float, Field(gt=0, le=100)] = Field(
        default=1.0, description="every load's power (and a resistive load's conductance) times this (a sweep's "
                                 "load axis)")
    layer: LayerConfig = LayerConfig()
    acceptance: NetworkAcceptance = NetworkAcceptance()
    links: dict[str, LinkConfig] = Field(default={}, description="interaction-message delay and loss, by receiving "
                                                                 "source name, or '*' for all (a source's own entry "
                                                                 "sets its keys on top of '*')")
    base_dir: str = Field(default=".", description="directory for relative csv paths (set by the loader)")

    @field_validator("sources")
    @classmethod
    def _some_source(cls, v: dict) -> dict:
        if not v:
            raise ValueError("a network needs at least one source")
        return v

    @model_validator(mode="after")
    def _topology(self) -> NetworkScenario:
        errors = topology_errors(self)
        if errors:
            raise ValueError("; ".join(errors))
        return self

    def fallback_of(self, source: str) -> str:
        """The source's fallback (layer.fallback, or by its law when that is None)."""
        if self.layer.fallback is not None:
            return self.layer.fallback
        return "last-allocation" if self.sources[source].controller.kind == "nested" else "own-terminal"

    def nodes(self) -> list[str]:
        """Every node: the sources' terminals, then the buses, in file order."""
        return [*self.sources, *self.buses]


def topology_errors(n: NetworkScenario) -> list[str]:
    """What makes the network unusable: bad or repeated names, references to nothing, a part not connected."""
    out = []
    kinds = {"source": n.sources, "bus": n.buses, "line": n.lines, "load": n.loads}
    seen: dict[str, str] = {}
    for kind, items in kinds.items():
        for name in items:
            if name == "layer":
                out.append(f"{kind} name 'layer': reserved for the interconnection layer's channels")
            if not NAME.match(name):
                out.append(f"{kind} name {name!r}: letters, digits, '_' and '-', starting with a letter")
            if name in seen:
                out.append(f"name {name!r} is both a {seen[name]} and a {kind}")
            seen.setdefault(name, kind)
    nodes = set(n.sources) | set(n.buses)
    for name, ln in n.lines.items():
        for end in (ln.a, ln.b):
            if end not in nodes:
                out.append(f"lines.{name}: {end!r} is not a bus or a source")
    for name, ld in n.loads.items():
        if ld.bus not in n.buses:
            out.append(f"loads.{name}.bus: {ld.bus!r} is not a bus")
    for k, ev in enumerate(n.events):
        if ev.kind == "connect" and ev.target not in n.sources:
            out.append(f"events.{k}.target: {ev.target!r} is not a source (connect names a source)")
        elif ev.target not in n.lines and ev.target not in n.sources:
            out.append(f"events.{k}.target: {ev.target!r} is not a line or a source")
    for name in n.links:
        if name != "*" and name not in n.sources:
            out.append(f"links.{name}: not a source (or '*')")
    if n.layer.fallback == "last-allocation":
        for name, src in n.sources.items():
            if src.controller.kind != "nested":
                out.append(f"layer.fallback: 'last-allocation' needs the nested law; sources.{name} has "
                           f"{src.controller.kind!r} (its power follows P^{{r,in}}: a kept gap grows), use "
                           "'own-terminal'")
    if out:
        return out
    # every node reachable from the first source over the lines (whatever their breakers' state)
    adj: dict[str, set[str]] = {v: set() for v in nodes}
    for ln in n.lines.values():
        adj[ln.a].add(ln.b)
        adj[ln.b].add(ln.a)
    start = next(iter(n.sources))
    reached, todo = {start}, deque([start])
    while todo:
        for w in adj[todo.popleft()] - reached:
            reached.add(w)
            todo.append(w)
    missing = [v for v in n.nodes() if v not in reached]
    if missing:
        out.append(f"not connected to {start}: {', '.join(missing)}")
    return out


def network_from_dict(data: dict, overrides: list[str] | None = None, source: str = "") -> NetworkScenario:
    data = apply_overrides(data, overrides or [])
    try:
        return NetworkScenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(format_validation_error(err, source, "network scenario")) from None


def is_network(data: dict) -> bool:
    """A scenario file's table is a network scenario (kind = "network")."""
    return data.get("kind") == "network"


def load_network(path: str | Path, overrides: list[str] | None = None) -> NetworkScenario:
    """Read a TOML network scenario, apply ``dotted.key=value`` overrides, validate."""
    p = Path(path)
    data = read_toml(p, "scenario")
    data.setdefault("base_dir", str(p.parent.resolve()))
    return network_from_dict(data, overrides, str(p))
