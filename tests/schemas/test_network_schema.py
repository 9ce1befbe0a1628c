"""Network scenarios are checked before anything runs: names, references, a connected graph, buses with a
capacitance; each error names what is wrong."""

from __future__ import annotations

import pytest

from schemas.network import network_from_dict
from schemas.scenario import ScenarioError

BASE = {
    "kind": "network",
    "sources": {"S1": {}, "S2": {}},
    "buses": {"bus": {"C_F": 4.7e-3}},
    "lines": {"L1": {"a": "S1", "b": "bus", "R_ohm": 0.15, "L_H": 150e-6},
              "L2": {"a": "S2", "b": "bus", "R_ohm": 0.10, "L_H": 100e-6}},
    "loads": {"P": {"bus": "bus", "value": 1200.0}},
}


def _with(**changes) -> dict:
    return {**BASE, **changes}


def test_the_base_network_is_valid():
    net = network_from_dict(BASE)
    assert net.nodes() == ["S1", "S2", "bus"]


@pytest.mark.parametrize(("data", "message"), [
    (_with(lines={**BASE["lines"], "L3": {"a": "S1", "b": "nowhere", "R_ohm": 0.1, "L_H": 1e-4}}),
     "lines.L3: 'nowhere' is not a bus or a source"),
    (_with(loads={"P": {"bus": "S1", "value": 1.0}}), "loads.P.bus: 'S1' is not a bus"),
    (_with(buses={"bus": {}}), "buses.bus.C_F: Field required"),
    (_with(buses={"bus": {"C_F": 0.0}}), "buses.bus.C_F"),
    (_with(lines={"L1": BASE["lines"]["L1"]}), "not connected to S1: S2"),
    (_with(buses={"bus": {"C_F": 1e-3}, "S2": {"C_F": 1e-3}}), "name 'S2' is both a source and a bus"),
    (_with(sources={"S1": {}, "2bad": {}}), "source name '2bad'"),
    (_with(sources={}), "a network needs at least one source"),
    (_with(lines={**BASE["lines"], "L3": {"a": "bus", "b": "bus", "R_ohm": 0.1, "L_H": 1e-4}}),
     "a line must join two different nodes"),
    (_with(events=[{"t_s": 0.1, "kind": "connect", "target": "L1"}]), "connect names a source"),
    (_with(events=[{"t_s": 0.1, "kind": "trip", "target": "S9"}]), "'S9' is not a line or a source"),
    (_with(links={"S9": {"delay_s": 0.001}}), "links.S9: not a source"),
    (_with(loads={"P": {"bus": "bus", "type": "resistive"}}), "a resistive load needs R_ohm"),
    (_with(sources={"S1": {"limits": {"u_min_V": 100.0, "u_max_V": 50.0}}, "S2": {}}), "u_min_V must be < u_max_V"),
    (_with(bogus=1), "bogus: Extra inputs are not permitted"),
])
def test_a_bad_network_is_refused_naming_what_is_wrong(data, message):
    with pytest.raises(ScenarioError, match="invalid network scenario") as err:
        network_from_dict(data)
    assert message in str(err.value)


def test_an_override_names_an_element():
    net = network_from_dict(BASE, ["sources.S2.controller.K_per_s=500.0", "lines.L2.R_ohm=0.2"])
    assert net.sources["S2"].controller.K_per_s == 500.0 and net.lines["L2"].R_ohm == 0.2
    with pytest.raises(ScenarioError, match="sources.S2.controller.K_per_s"):
        network_from_dict(BASE, ["sources.S2.controller.K_per_s=-1"])
