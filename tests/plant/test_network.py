"""The DC network plant (service/plant/network.py): its physics against closed forms and the energy balance, its
breakers, and its compiled twin bit for bit."""

from __future__ import annotations

import importlib.util
import random

import pytest

from schemas.network import network_from_dict
from service.plant.network import LINE_W, SRC_W, NetworkPlant

TWO_SOURCE = {
    "kind": "network",
    "sources": {"S1": {}, "S2": {}},
    "buses": {"bus": {"C_F": 4.7e-3}},
    "lines": {"L1": {"a": "S1", "b": "bus", "R_ohm": 0.15, "L_H": 150e-6},
              "L2": {"a": "bus", "b": "S2", "R_ohm": 0.10, "L_H": 100e-6}},  # drawn towards S2: the sign matters
    "loads": {"P": {"bus": "bus", "type": "resistive", "R_ohm": 80.0 ** 2 / 1200.0}},  # uncontrolled: a CPL
}                                                                                     # would not settle


def _net(**changes):
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in TWO_SOURCE.items()}
    data.update(changes)
    return network_from_dict(data)


def _settle(plant: NetworkPlant, seconds: float, r=None, T: float = 1e-4, n_sub: int = 10) -> None:
    r = r or [0.0] * len(plant.sources)
    for _ in range(int(round(seconds / T))):
        plant.advance(r, T, n_sub)


def test_a_resistive_divider_settles_where_ohm_says():
    """One source held at u = 80 V through R_s and a 0.15 ohm line into a 5 ohm resistor: i = u / sum(R)."""
    net = network_from_dict({"kind": "network", "sources": {"S": {"R_ohm": 0.01}}, "buses": {"b": {"C_F": 1e-3}},
                             "lines": {"L": {"a": "S", "b": "b", "R_ohm": 0.15, "L_H": 150e-6}},
                             "loads": {"R": {"bus": "b", "type": "resistive", "R_ohm": 5.0}}})
    plant = NetworkPlant(net)
    _settle(plant, 2.0)  # R_s / L_s = 9 /s: the slowest mode
    i = 80.0 / (0.01 + 0.15 + 5.0)
    assert plant.i_s[0] == pytest.approx(i, rel=1e-6)
    assert plant.i_l[0] == pytest.approx(i, rel=1e-6)
    assert plant.v_n[1] == pytest.approx(5.0 * i, rel=1e-6)  # the bus
    assert plant.terminal_current(0) == pytest.approx(i, rel=1e-6)


def test_currents_are_signed_by_the_lines_orientation_and_the_terminal_current_is_out_of_the_source():
    """L2 is drawn bus -> S2, so at steady state its current is negative; S2's terminal current (out of S2) is
    positive, and the line-end power at S2 is what S2 delivers (hazard: the line's own orientation)."""
    plant = NetworkPlant(_net())
    _settle(plant, 2.0)
    s2 = plant.node_index["S2"]
    assert plant.i_l[1] < -1.0
    assert plant.terminal_current(s2) == pytest.approx(-plant.i_l[1])
    assert plant.line_end_power(1, s2) == pytest.approx(plant.v_n[s2] * plant.terminal_current(s2))
    assert plant.line_end_power(1, s2) > 0
    # Kirchhoff at the bus: what the lines bring is what the load draws (the capacitor's current is ~0 now)
    bus = plant.node_index["bus"]
    brought = plant.i_l[0] - plant.i_l[1]  # L1 enters the bus at its b end, L2 leaves it at its a end
    assert brought == pytest.approx(plant.v_n[bus] / (80.0 ** 2 / 1200.0), rel=1e-6)


def test_the_energy_balance_closes():
    """Over 20 ms with sources ramping: the change of stored energy equals what the sources put in minus the
    resistive losses and the load's energy, to the integration's accuracy."""
    plant = NetworkPlant(_net(loads={"P": {"bus": "bus", "value": 1200.0,
                                            "kind": "sines", "components": [{"amplitude": 300.0, "freq_hz": 23.0}]}}))
    _settle(plant, 0.05)
    T, n_sub, r = 1e-4, 10, [500.0, -300.0]
    e0 = plant.stored_energy()
    w_in = w_loss = w_load = 0.0
    for _ in range(200):  # trapezoid over each period's two ends
        def powers():
            src_in = sum(plant.u_s[j] * plant.i_s[j] for j in range(2))
            loss = sum(plant.src[SRC_W * j] * plant.i_s[j] ** 2 for j in range(2)) + \
                sum(plant.lines[LINE_W * j] * plant.i_l[j] ** 2 for j in range(2))
            return src_in, loss, plant.load_power(0, plant.t)
        a = powers()
        plant.advance(r, T, n_sub)
        b = powers()
        w_in += 0.5 * T * (a[0] + b[0])
        w_loss += 0.5 * T * (a[1] + b[1])
        w_load += 0.5 * T * (a[2] + b[2])
    de = plant.stored_energy() - e0
    assert abs(de - (w_in - w_loss - w_load)) < 1e-3 * (w_in + w_load)


def test_an_open_breaker_carries_nothing_and_closing_it_draws_an_inrush():
    """Tripping L2 zeroes its current at once and S1 carries the load; closing it again with S2 held at 82 V
    draws an inrush that then settles."""
    plant = NetworkPlant(_net())
    _settle(plant, 0.2)
    plant.set_breaker(1, False)
    assert plant.i_l[1] == 0.0 and not plant.connected("S2")
    _settle(plant, 2.0)
    assert plant.i_l[1] == 0.0
    bus = plant.node_index["bus"]
    assert plant.i_l[0] == pytest.approx(plant.v_n[bus] / (80.0 ** 2 / 1200.0), rel=1e-6)
    plant.u_s[1] = plant.v_n[1] = 82.0
    plant.set_breaker(1, True)
    peak = 0.0
    for _ in range(200):
        plant.advance([0.0, 0.0], 1e-4, 10)
        peak = max(peak, abs(plant.i_l[1]))
    assert peak > 5.0 and plant.connected("S2")


def test_a_source_that_starts_disconnected_has_its_lines_open():
    plant = NetworkPlant(_net(sources={"S1": {}, "S2": {"connected": False}}))
    assert plant.closed(0) and not plant.closed(1)


@pytest.mark.skipif(not importlib.util.find_spec("service._kernel"), reason="compiled kernel not built")
def test_the_compiled_integrator_gives_the_same_bits():
    """Random commands, a resistive and a CPL load, a trip and a close: every state the same to the bit."""
    net = _net(loads={"P": {"bus": "bus", "value": 1500.0, "kind": "sines",
                            "components": [{"amplitude": 400.0, "freq_hz": 5.0}]},
                      "R": {"bus": "bus", "type": "resistive", "R_ohm": 20.0}})
    a, b = NetworkPlant(net, impl="python"), NetworkPlant(net, impl="c")
    rng = random.Random(7)
    for k in range(300):
        r = [rng.uniform(-2e4, 2e4), rng.uniform(-2e4, 2e4)]
        if k == 100:
            a.set_breaker(1, False)
            b.set_breaker(1, False)
        if k == 200:
            a.set_breaker(1, True)
            b.set_breaker(1, True)
        a.advance(r, 1e-4, 10)
        b.advance(r, 1e-4, 10)
        for name in ("i_s", "u_s", "i_l", "v_n"):
            assert list(getattr(a, name)) == list(getattr(b, name)), (k, name)


@pytest.mark.parametrize("impl", ["python", "c"])
def test_a_sources_current_limit_holds_in_the_network_and_the_twin_gives_the_same_bits(impl):
    """S1 with limits.i_max_A = 12 under commands that drive it far beyond: its current stays within +-12 A and
    sits at the limit for a while, S2 (no limit) goes beyond 12 A; the compiled integrator gives the same bits."""
    if impl == "c" and not importlib.util.find_spec("service._kernel"):
        pytest.skip("compiled kernel not built")
    net = _net(sources={"S1": {"limits": {"i_max_A": 12.0}}, "S2": {}},
               loads={"P": {"bus": "bus", "value": 1500.0}})
    a, b = NetworkPlant(net, impl="python"), NetworkPlant(net, impl=impl)
    rng = random.Random(3)
    i1, i2 = [], []
    for _ in range(400):
        r = [rng.uniform(-1e5, 1e5), rng.uniform(-1e5, 1e5)]
        a.advance(r, 1e-4, 10)
        b.advance(r, 1e-4, 10)
        for name in ("i_s", "u_s", "i_l", "v_n"):
            assert list(getattr(a, name)) == list(getattr(b, name)), name
        i1.append(a.i_s[0])
        i2.append(a.i_s[1])
    assert max(abs(x) for x in i1) == 12.0 and sum(abs(x) == 12.0 for x in i1) > 20
    assert max(abs(x) for x in i2) > 12.0
