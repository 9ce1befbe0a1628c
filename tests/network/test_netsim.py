"""Networks of controllable sources offline (service/network/netsim.py): the shipped scenarios reach their figures, the
design notes' hazards are handled (and fail on the naive choice), and a run is deterministic."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from conftest import ROOT, SCENARIOS

from schemas.network import load_network
from schemas.scenario import CircuitParams, ControllerConfig, PlantConfig, SensorConfig
from service.core import make_core
from service.core.source import SourceController
from service.network.netsim import run_network
from service.plant.rlc import RLCPlant, Sensor

NET = SCENARIOS / "network"


def _run(name: str, *overrides: str):
    return run_network(load_network(NET / f"{name}.toml", list(overrides)))


def paper_law(*sources: str) -> list[str]:
    """Overrides that put a network's sources on the paper's law (fblc) with the layer as it was built for it: a
    30 W idle threshold, one common v_ref, each source following its own lines' power in the prediction. The
    hazards of the design notes are the paper law's; these tests show them on it, and the default law beside. (Late
    allocations carried forward 2 ms along their rate.)"""
    return ["layer.idle_power_W=30.0", 'layer.v_ref_mode="common"', "layer.extrapolate_s=0.002",
            *(f"sources.{s}.controller.{kv}" for s in sources for kv in ('kind="fblc"', 'load_power="measured"'))]


def test_two_sources_share_the_load_and_hold_the_bus():
    """2:1 sharing under a 1.2 -> 2.4 kW step and a varying load, with noise, 2 samples of delay and +-10 % model
    error in each source."""
    m = _run("two-source").metrics
    assert not m["diverged"]
    for s in m["sources"].values():
        assert abs(s["sharing_error_pp"]) <= 2.0
    bus = m["buses"]["bus"]
    assert bus["ss_dev_pct"] <= 1.0 and bus["v_min"] >= 75.5
    step = next(e for e in m["events"] if e["kind"] == "load" and e["t_s"] == pytest.approx(0.3))
    assert step["bus_back_in_band_s"]["bus"] <= 0.150
    assert max(step["terminals_back_in_band_s"].values()) <= 0.030
    assert step["sharing_in_band_s"] <= 1.0


def test_after_a_trip_the_other_source_carries_the_load():
    res = _run("two-source-trip")
    m = res.metrics
    assert not m["diverged"]
    after = res.t >= 0.9
    assert res.sources["S1"]["P"][after].mean() >= 0.95 * 2400.0  # S1 delivers the whole load (and the losses)
    assert np.all(res.lines["L2"][after] == 0.0)
    trip = next(e for e in m["events"] if e["kind"] == "trip")
    assert trip["bus_back_in_band_s"]["bus"] <= 0.200 and trip["bus_min_V"]["bus"] >= 74.0


def test_a_line_drawn_towards_the_source_changes_nothing():
    """Hazard 4, signs at junctions: the power a source follows is its lines' power oriented out of it, whatever
    way a line is drawn. Drawing L2 bus -> S2 gives the same run to the bit (a controller that took the line's
    own orientation would lose regulation here)."""
    a = _run("two-source", "timing.duration_s=0.4")
    b = _run("two-source", "timing.duration_s=0.4", 'lines.L2.a="bus"', 'lines.L2.b="S2"')
    assert np.array_equal(a.buses["bus"], b.buses["bus"])
    assert np.array_equal(a.sources["S2"]["P"], b.sources["S2"]["P"])
    assert np.array_equal(a.lines["L2"], -b.lines["L2"])


def test_the_same_scenario_gives_the_same_bits():
    a, b = _run("two-source", "timing.duration_s=0.2"), _run("two-source", "timing.duration_s=0.2")
    for s in a.sources:
        for k in a.sources[s]:
            assert np.array_equal(a.sources[s][k], b.sources[s][k]), (s, k)


class _NoLoad:
    def value(self, t: float) -> float:
        return 0.0

    def rate(self, t: float) -> float:
        return 0.0


def _island(idle_power_W: float, kind: str = "fblc") -> tuple[float, float, float, float]:
    """A connected source whose lines draw nothing (P^{r,in} = 0), 0.5 s at 10 kHz with noise and 2 samples of
    delay: the ranges of its source voltage u and of its terminal voltage v (lo u, hi u, lo v, hi v; V)."""
    plant = RLCPlant(PlantConfig(initial={"i_A": 0.0, "v_V": 80.0}), _NoLoad())
    sensor = Sensor(SensorConfig(noise_v_V=0.05, noise_i_A=0.05), 3)
    ctl = SourceController(make_core(ControllerConfig(kind=kind, K_per_s=1000.0), CircuitParams(), 1e-4, 2), 1e-4,
                           idle_power_W=idle_power_W)
    line = deque([0.0, 0.0])
    us, vs = [plant.u], [plant.v]
    for k in range(5000):
        s = sensor.measure(k, plant.t, plant.i, plant.v, plant.u, 0.0)
        line.append(ctl.step(s, 0.0, 0.0, True, True)[0])
        plant.advance(line.popleft(), 1e-4, 10)
        us.append(plant.u)
        vs.append(plant.v)
    return min(us), max(us), min(vs), max(vs)


def test_a_source_with_nothing_to_deliver_idles_at_its_reference():
    """Hazard 2, no voltage information at zero power: the paper's y_z = y_ref says nothing about v when P = 0. With
    the idle mode u stays at v_ref; without it (idle power 0: the law runs) u wanders by volts (20 V). The nested
    law (the default, which needs no idle mode: layer.idle_power_W = 0) regulates the terminal itself: v within
    0.05 V, u moving by a few volts with the current's noise."""
    lo, hi, _, _ = _island(30.0)
    assert 79.9 < lo and hi < 80.1
    lo, hi, _, _ = _island(0.0)
    assert hi - lo > 10.0
    lo, hi, v_lo, v_hi = _island(0.0, "nested")
    assert 79.95 < v_lo and v_hi < 80.05 and hi - lo < 8.0


def _open_terminal_at_1khz(hold_when_open: bool) -> float:
    """A source of the 1 kHz scenario whose breaker opened while its allocation went stale (its host cut off, then
    tripped): it still believes the breaker closed (connected True, fresh False) and its terminal draws nothing.
    2 s with noise and 4 samples of delay: the largest |v - 80 V| (V)."""
    src = load_network(NET / "realtime.toml").sources["S2"]
    plant = RLCPlant(PlantConfig(**src.model_params().model_dump(), initial={"i_A": 0.0, "v_V": 80.0}), _NoLoad())
    sensor = Sensor(SensorConfig(noise_v_V=0.05, noise_i_A=0.05), 3)
    ctl = SourceController(make_core(src.controller, src.model_params(), 1e-3, 4), 1e-3,
                           hold_when_open=hold_when_open)
    line = deque([0.0] * 4)
    worst = 0.0
    for k in range(2000):
        s = sensor.measure(k, plant.t, plant.i, plant.v, plant.u, 0.0)
        line.append(ctl.step(s, 0.0, 0.0, True, False)[0])
        plant.advance(line.popleft(), 1e-3, 100)
        worst = max(worst, abs(plant.v - 80.0))
        if worst > 40.0:
            break
    return worst


def test_an_open_source_with_a_stale_allocation_holds_its_voltage_at_1_khz():
    """Seen across hosts: S2, tripped while cut off, got samples again before an allocation told it its breaker was
    open; believing it closed, its idle droop law rang the open terminal's L-C (57 Hz) up to divergence within 60 ms.
    With layer.open_idle = "hold" an idle source holds u also while its allocation is stale."""
    assert _open_terminal_at_1khz(True) < 1.0
    assert _open_terminal_at_1khz(False) > 10.0


def test_a_feasible_source_plugs_in_gently_and_an_infeasible_one_is_refused():
    """Plug-in: the layer checks the source's forecast against its share of the window before closing its line.
    A feasible one closes with a small inrush and barely moves the bus, then shares; one whose gain is too slow
    for the load band is refused with the reason, its breaker stays open and nothing moves."""
    m = _run("plug-in").metrics
    plug = next(e for e in m["events"] if e["kind"] == "connect")
    assert plug["accepted"] and plug["inrush_A"] <= 20.0 and plug["bus_move_V"]["bus"] <= 2.0
    assert abs(m["sources"]["S3"]["sharing_error_pp"]) <= 2.0 and m["sources"]["S3"]["final_mode"] == "active"
    res = _run("plug-in", "sources.S3.controller.nested_K_P_per_s=10.0")
    plug = next(e for e in res.metrics["events"] if e["kind"] == "connect")
    assert not plug["accepted"] and plug["reason"]
    assert res.metrics["sources"]["S3"]["final_mode"] == "idle"
    assert np.all(res.lines["L3"] == 0.0)


@pytest.mark.parametrize("link", ["links.*.delay_s=0.001", "links.*.loss=0.1"])
def test_interaction_variables_a_little_late_or_lost_keep_the_figures(link):
    m = _run("two-source", link).metrics
    assert not m["diverged"] and all(abs(s["sharing_error_pp"]) <= 2.0 for s in m["sources"].values())
    assert m["buses"]["bus"]["ss_dev_pct"] <= 1.0 and m["buses"]["bus"]["v_min"] >= 75.5
    step = m["events"][0]
    assert step["bus_back_in_band_s"]["bus"] <= 0.150 and max(step["terminals_back_in_band_s"].values()) <= 0.030


def test_interaction_variables_5_ms_late_keep_the_bus_above_70_v():
    m = _run("two-source", "links.*.delay_s=0.005").metrics
    assert not m["diverged"] and m["buses"]["bus"]["v_min"] >= 70.0


@pytest.mark.parametrize("link", ["links.*.delay_s=0.02", "links.*.silent_from_s=0.4"])
def test_late_or_silent_interaction_variables_make_the_sources_fall_back_without_diverging(link):
    """20 ms late (older than the 10 ms a P^{r,in} stays usable) or silent from 0.4 s: each source follows its
    own terminal, and the metrics say from when."""
    m = _run("two-source", link).metrics
    assert not m["diverged"]
    for s in m["sources"].values():
        assert s["fallback_s"] > 0.3 and s["first_fallback_t_s"] is not None
    if "silent" in link:
        assert all(s["first_fallback_t_s"] == pytest.approx(0.41, abs=1e-3) for s in m["sources"].values())


AGGRESSIVE = [*paper_law("S1", "S2", "S3"), *(f"sources.{s}.controller.{kv}" for s in ("S1", "S2", "S3")
                                               for kv in ("K_per_s=1000", "observer_gain=0", "plan_next_period=true"))]


@pytest.mark.parametrize("disturbance", ["timing.command_late=0.1", "timing.command_loss=0.1",
                                         "timing.command_outages=[[1.0, 0.02], [3.0, 0.02]]"])
def test_the_realtime_network_rides_through_late_lost_and_stalled_commands(disturbance):
    """A realtime stack on a shared machine delivers some commands a period late, loses some, and stalls for
    tens of ms (docs/limits.md). The shipped 1 kHz network (the nested law at its 1 kHz rates, on an observer's
    estimate, a missing command holds u) keeps the bus within 10 % through each; the paper's law with the gain and
    the planned commands the offline figures were first tuned with (K = 1000 /s on the raw sample) diverges under
    the same disturbance: the planned command, predicted four periods ahead through a model that sees the lines as
    a constant-power load, pushes the wrong way, and so did the chatter of the sensor noise at that gain."""
    m = _run("realtime", disturbance).metrics
    assert not m["diverged"], m["diverged_at_s"]
    assert 72.0 <= m["buses"]["bus"]["v_min"] and m["buses"]["bus"]["v_max"] <= 88.0, m["buses"]
    assert _run("realtime", disturbance, *AGGRESSIVE).metrics["diverged"]


def test_the_network_rig_model_applies_the_command_disturbances_per_source():
    """Each source's commands get their own seeded draws (S1's losses are not S2's), the same in every run."""
    from service.network.netrig import NetworkRigModel

    net = load_network(NET / "realtime.toml", ["timing.command_loss=0.5"])
    a, b = NetworkRigModel(net), NetworkRigModel(net)
    applied = np.array([[m.command(j, k, 100.0 + k, -1.0) for k in range(200) for j in range(3)]
                        for m in (a, b)]).reshape(2, 200, 3)
    assert np.array_equal(applied[0], applied[1])
    held = applied[0] != 100.0 + np.arange(200)[:, None] - net.timing.delay_samples  # not its own command: lost
    assert 0.3 < held[10:].mean() < 0.7 and not np.array_equal(held[:, 0], held[:, 1])


def test_a_returning_coordinator_ramps_the_sources_back_to_their_shares():
    """The layer's messages silent over the load step (a coordinator away from 1.99 s to 2.3 s): each source
    follows its own terminal meanwhile, which splits the new load by the lines, not by the shares. When the
    messages come back the sources move to their shares over layer.resume_ramp_s (50 ms in the shipped 1 kHz
    scenario) and the bus stays within +-2 %. The paper's law needed that ramp: at once, the step took the bus out
    (2.4 % offline; 2.3 % across hosts); the nested law stays within the band either way."""
    silence = ["links.*.silent_from_s=1.99", "links.*.silent_until_s=2.3"]

    def worst_after_return_pct(*extra):
        r = _run("realtime", *silence, *extra)
        after = (r.t >= 2.3) & (r.t < 2.6)
        shares = r.sources["S1"]["P"][r.t >= 2.9].mean() / r.sources["S2"]["P"][r.t >= 2.9].mean()
        return np.abs(r.buses["bus"][after] - 80.0).max() / 0.8, shares

    ramped, shares = worst_after_return_pct()
    assert ramped < 2.0 and shares == pytest.approx(2.0, rel=0.05)
    assert worst_after_return_pct("layer.resume_ramp_s=0")[0] < 2.0
    paper = paper_law("S1", "S2", "S3")
    assert worst_after_return_pct(*paper)[0] < 2.0
    assert worst_after_return_pct("layer.resume_ramp_s=0", *paper)[0] > 2.0


def test_a_source_left_in_fallback_near_zero_current_holds_instead_of_ringing_up():
    """Seen across hosts with the paper's law: the coordinator went away 10 ms into S3's plug-in ramp, leaving S3 in
    fallback (its own terminal's power) near zero current, where the exact mapping's fast mode u/(i L) is far above
    1 kHz: its commands alternated ever wider until saturated, and with 5 % of them late the network diverged
    within a second. For that law the 1 kHz scenario idles (holds u) in fallback below 300 W of its own power
    (layer.fallback_idle_power_W). The nested law has no such mode: it holds with that threshold at 0 too."""
    stranded = ["links.*.silent_from_s=4.01", "timing.duration_s=10", "timing.command_late=0.05"]
    paper = paper_law("S1", "S2", "S3")
    m = _run("realtime", *stranded, *paper).metrics
    assert not m["diverged"], m["diverged_at_s"]
    # the layer's messages never came back: S1 follows its own terminal, S3 holds
    assert m["sources"]["S1"]["fallback_s"] > 5.0 and m["sources"]["S3"]["final_mode"] == "idle"
    assert _run("realtime", *stranded, *paper, "layer.fallback_idle_power_W=30").metrics["diverged"]
    m = _run("realtime", *stranded, "layer.fallback_idle_power_W=0").metrics
    assert not m["diverged"] and m["sources"]["S1"]["fallback_s"] > 5.0
    assert m["buses"]["bus"]["v_min"] > 0.9 * 80.0


def test_the_shipped_radial_16_is_the_bench_generator_s_and_regulates():
    """scenarios/network/radial-16.toml is clients.bench.network.radial(16) written out (so the bench's scale
    figures are the shipped scenario's); a short run regulates with every source sharing."""
    import tomllib

    from clients.bench.network import radial
    from schemas.network import network_from_dict

    shipped = network_from_dict(tomllib.loads((NET / "radial-16.toml").read_text()))
    assert shipped == network_from_dict(radial(16))
    m = _run("radial-16", "timing.duration_s=0.4").metrics
    assert not m["diverged"] and all(abs(s["sharing_error_pp"]) <= 2.0 for s in m["sources"].values())
    assert all(b["ss_dev_pct"] <= 1.0 for b in m["buses"].values())


def test_each_source_of_a_network_log_replays_identical(tmp_path):
    """energyctl sim NETWORK --out writes one log with each source's channels under its own prefix; replaying one
    source rebuilds its core from its own core record and reproduces every command it answered, through the
    layer's v_ref moves (config events) and its idle periods (holds with a rate): S3 idles until it plugs in."""
    from clients.cli import main

    out = tmp_path / "plug-in.mcap"
    assert main(["sim", str(NET / "plug-in.toml"), "--out", str(out)]) == 0
    from service.logio.reader import component_names
    from service.replay import replay

    assert component_names(out) == ["S1", "S2", "S3"]
    for name in ("S1", "S3"):
        r = replay(out, progress=False, component=name)
        assert r["identical"] and r["compared"] == 12000, (name, r["first_divergence"])
    with pytest.raises(Exception, match="name the component"):
        replay(out, progress=False)


def test_a_what_if_replay_of_a_network_source_keeps_the_layer_s_v_ref_moves(tmp_path):
    """The layer's v_ref moves are inputs of a network source, not an operator's config: a what-if with the gain it
    already had reproduces the log, so a what-if with another gain changes only what the gain changes."""
    from service.logio.mcapfile import write_network_mcap
    from service.logio.reader import read_log
    from service.replay import replay

    out, what_if = tmp_path / "net.mcap", tmp_path / "what-if.mcap"
    res = _run("two-source", "timing.duration_s=0.3")
    write_network_mcap(out, res)
    assert len(res.config_events["S1"]) >= 2  # the layer moved S1's v_ref at least twice
    assert replay(out, overrides=["K_per_s=1000.0"], out=str(what_if), progress=False, component="S1")["ticks"] == 3000

    def commands(log, component=None) -> np.ndarray:  # du/dt of each cmd row (code 2; seq, t, du_dt, ...)
        rows = np.concatenate(read_log(log, component=component).rows)
        return rows[rows[:, 0] == 2][:, 3]

    assert np.array_equal(commands(out, "S1"), commands(what_if))


def test_short_runs_still_get_their_metrics():
    """A run shorter than the sharing filter (5 ms) is measured, not a crash."""
    for seconds in (0.0001, 0.003):
        m = _run("two-source", f"timing.duration_s={seconds}").metrics
        assert not m["diverged"] and m["t_end"] < seconds


def _continuous(floor_A: float) -> list[str]:
    """Every ring source on the paper's law with its continuous mapping du/dt = (u di/dt - u_z) / i, i floored at
    floor_A."""
    return [*paper_law("S1", "S2", "S3", "S4"), *(f"sources.{s}.controller.{k}" for s in ("S1", "S2", "S3", "S4")
                                                  for k in ('mapping="continuous"', f"limits.i_floor_A={floor_A}"))]


def test_light_load_in_the_ring_breaks_the_mapping_that_divides_by_i():
    """Hazard 1, light load per source: in the ring S4 carries about 170 W (2.1 A). The paper's continuous
    mapping, which divides by i (the reference's 2 A floor), diverges within 20 ms, as the reference study found;
    with the load doubled it holds, so the light load is what breaks it. The exact mapping regulates the same ring,
    and so does the default (nested) law, which divides by nothing. (Here the floor's size does not decide it: 0.5 A
    diverges as well.)"""
    naive = _run("ring", "timing.delay_samples=0", *_continuous(2.0)).metrics
    assert naive["diverged"] and naive["diverged_at_s"] < 0.02
    assert _run("ring", "timing.delay_samples=0", *_continuous(0.5)).metrics["diverged"]
    assert not _run("ring", "timing.delay_samples=0", "load_scale=2.0", *_continuous(2.0)).metrics["diverged"]
    for law in (paper_law("S1", "S2", "S3", "S4"), []):
        m = _run("ring", *law).metrics
        assert not m["diverged"] and m["sources"]["S4"]["final_mode"] == "active"
        assert abs(m["sources"]["S4"]["sharing_error_pp"]) <= 2.0


def test_a_source_s_own_link_entry_adds_to_the_common_one():
    from service.network.netsim import link_of

    net = load_network(NET / "two-source.toml", ["links.*.delay_s=0.005", "links.S2.loss=0.1"])
    assert (link_of(net, "S1").delay_s, link_of(net, "S1").loss) == (0.005, 0.0)
    assert (link_of(net, "S2").delay_s, link_of(net, "S2").loss) == (0.005, 0.1)


def test_the_1_khz_scenarios_and_the_realtime_settings_agree():
    """One set of 1 kHz settings: the bench's and demo's realtime_sets applied to the 10 kHz demo give its realtime
    twin's layer, rate, delay and controllers, and scenarios/network/realtime.toml has the same."""
    from clients.bench.network_live import realtime_sets

    twin = load_network(ROOT / "clients" / "embedded" / "network-demo-realtime.toml")
    for path in (ROOT / "clients" / "embedded" / "network-demo.toml", NET / "realtime.toml"):
        names = list(load_network(path).sources)
        net = load_network(path, realtime_sets(1000.0, names))
        assert net.layer == twin.layer, path
        assert (net.timing.control_rate_hz, net.timing.delay_samples) == (1000.0, 4)
        assert all(net.sources[s].controller == twin.sources["S1"].controller for s in names), path


def test_a_bus_no_source_reaches_is_a_blackout_not_a_divergence():
    """Both breakers open: the bus's load drains it to 0 V. That is reported as the bus unsupplied from the second
    trip (and fails the buses' band checks), not as a divergence; the sources' own terminals stay watched."""
    trips = 'events=[{t_s=0.5, kind="trip", target="S2"}, {t_s=0.7, kind="trip", target="S1"}]'
    res = _run("two-source-trip", trips, "timing.duration_s=0.9")
    m = res.metrics
    assert not m["diverged"] and m["unsupplied_s"] == {"bus": pytest.approx(0.7, abs=2e-4)}
    assert res.buses["bus"][-1] < 1.0  # it did collapse
    for s in ("S1", "S2"):
        assert 0.5 * 80.0 < res.sources[s]["v"][-1] < 2.0 * 80.0
    assert _run("two-source-trip", "timing.duration_s=0.6").metrics["unsupplied_s"] == {}  # one trip: still fed


def test_a_trace_without_the_controllers_reports_feasibility_violations_as_unknown():
    """A live rig's trace (no controllers: the daemons' monitors count excursions) reported 0 feasibility violations
    per source, a count it cannot know; now null (the offline run, which has them, still counts)."""
    from service.metrics import network_metrics

    net = load_network(SCENARIOS / "network" / "two-source.toml", ["timing.duration_s=0.05", "events=[]"])
    res = run_network(net)
    assert all(isinstance(m["feasibility_violations"], int) for m in res.metrics["sources"].values())
    live = network_metrics(res, None, None)
    assert all(m["feasibility_violations"] is None for m in live["sources"].values()), live["sources"]


def test_without_the_coordinator_the_sources_keep_their_last_shares():
    """The layer's messages silent from just after S3's plug-in (2:1:1 of 2.4 kW: 1200, 600, 600 W). Following their
    own terminals alone, the sources split by their lines and v_refs, and S3, whose v_ref the layer had not moved
    yet, kept 228 of its 600 W (across hosts S2 fell so below 300 W, idled, and 2:1 became 90:10). Keeping the last
    allocation (the default), each keeps its share, the bus within +-2 %."""
    silent = ["links.*.silent_from_s=4.06", "timing.duration_s=6"]

    def powers(*extra):
        r = _run("realtime", *silent, *extra)
        late = r.t >= 5.0
        return {s: float(r.sources[s]["P"][late].mean()) for s in ("S1", "S2", "S3")}, r

    kept, r = powers()
    total = sum(kept.values())
    for s, share in (("S1", 0.5), ("S2", 0.25), ("S3", 0.25)):
        assert kept[s] / total == pytest.approx(share, abs=0.03), kept
    assert all(m["final_mode"] == "fallback" for m in r.metrics["sources"].values()), r.metrics["sources"]
    assert np.abs(r.buses["bus"][r.t >= 4.2] - 80.0).max() < 0.02 * 80.0
    own, _ = powers('layer.fallback="own-terminal"')
    assert own["S3"] / sum(own.values()) < 0.15, own  # what the own-terminal fallback did
    # silent 20 ms into S3's plug-in ramp: it keeps about where the ramp was, below the 300 W fallback floor of the
    # own-terminal law, and does not idle (that floor is the paper law's hazard, not the kept share's)
    r = _run("realtime", "links.*.silent_from_s=4.02", "timing.duration_s=5")
    assert r.metrics["sources"]["S3"]["final_mode"] == "fallback", r.metrics["sources"]["S3"]


def test_a_new_run_does_not_keep_the_previous_runs_share():
    """A source keeping its last allocation (nested law, coordinator silent) takes what it was last asked for; once
    the rig restarts (reset_fallback) and this run's allocation has not come yet, the previous run's share is not
    kept: it follows its own terminal (P^{r,in} = -v i_out)."""
    from service.core.types import Sample

    ctl = SourceController(make_core(ControllerConfig(kind="nested"), CircuitParams(), 1e-4, 2), 1e-4,
                           idle_power_W=0.0, fallback="last-allocation")
    s = Sample(seq=0, t=0.0, i=10.0, v=80.0, u=80.1, i_load=10.0)  # 800 W at its terminal
    ctl.step(s, -1500.0, 0.0, True, True)  # asked for 1.5 kW
    ctl.step(Sample(1, 1e-4, 10.0, 80.0, 80.1, 10.0), 0.0, 0.0, True, False)  # silent: the kept share
    assert ctl.P_in_used == pytest.approx(-1500.0)
    ctl.reset_fallback()
    ctl.step(Sample(2, 2e-4, 10.0, 80.0, 80.1, 10.0), 0.0, 0.0, True, False)
    assert ctl.P_in_used == pytest.approx(-800.0)
