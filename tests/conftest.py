from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.scenario import load_scenario, scenario_from_dict
from service.core.energy import RLCEnergy

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "scenarios"
DATA = ROOT / "tests" / "data"  # files the tests read (a log recorded by an earlier release)

# an ideal setting: no noise, no delay, exact model
IDEAL = {"timing": {"control_rate_hz": 10000.0, "plant_step_s": 1e-5, "duration_s": 0.1}}


def scenario(**sections):
    """Scenario from nested keyword sections on top of IDEAL, e.g. scenario(load={'value': 900.0})."""
    data = {k: dict(v) for k, v in IDEAL.items()}
    for k, v in sections.items():
        if isinstance(v, dict) and isinstance(data.get(k), dict):
            data[k].update(v)
        else:
            data[k] = v
    return scenario_from_dict(data)


def exact_energy_along(trace: dict, R: float, L: float, C: float, Pdot: np.ndarray | None = None):
    """RLCEnergy quantities along a simulated trace, with exact derivatives from the circuit equations."""
    n = len(trace["t"])
    Pdot = np.zeros(n) if Pdot is None else Pdot
    cols = {k: np.zeros(n) for k in RLCEnergy.__slots__}
    cols["di"] = np.zeros(n)
    cols["dv"] = np.zeros(n)
    e = RLCEnergy()
    for k in range(n):
        i, v, u, i2 = trace["i"][k], trace["v"][k], trace["u"][k], trace["i_load"][k]
        P = trace["P_l"][k]
        r = trace["du_dt_applied"][k]
        di = (u - R * i - v) / L
        dv = (i - i2) / C
        di2 = Pdot[k] / v - P * dv / (v * v)
        e.update(R, L, C, i, v, u, i2, di, dv, r, di2)
        for key in RLCEnergy.__slots__:
            cols[key][k] = getattr(e, key)
        cols["di"][k], cols["dv"][k] = di, dv
    return cols


@pytest.fixture
def paper_files():
    return sorted(SCENARIOS.glob("paper-*.toml"))


@pytest.fixture
def daemon_by_hand():
    """An opened daemon (loopback session, no peers) whose loop we drive by hand through _tick."""
    from clients.live import configs_from_scenario
    from schemas.component import ComponentConfig, config_from_dict
    from service.daemon.bus import free_tcp_port
    from service.daemon.daemon import Daemon

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=10000.0)
    comp["neighbour_stale_s"] = 10.0
    comp["loop"]["trigger"] = "clock"
    comp["forecast"] = {"enabled": False}  # no worker process: these tests feed samples, not windows
    comp.pop("local_reference_W")  # the daemon's own default (hold), not the realtime stacks' "measured"
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    nb = d.neighbours[0]
    nb.count, nb.P, nb.rx_ns = 1, 1200.0, 0
    try:
        yield d
    finally:
        d.close()


class PumpingClient:
    """A blocking WebSocket test client (the Foxglove tests'): ``pump`` reads messages into ``_take`` until a
    condition holds; subclasses set ``ws`` and ``_take``, and ``PUMP_TIMEOUT_S``."""

    PUMP_TIMEOUT_S = 5.0

    def pump(self, pred, timeout_s: float | None = None) -> bool:
        """Reads messages until pred() holds or timeout_s (default PUMP_TIMEOUT_S) passes."""
        import time

        deadline = time.monotonic() + (self.PUMP_TIMEOUT_S if timeout_s is None else timeout_s)
        while not pred():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                self._take(self.ws.recv(timeout=left))
            except TimeoutError:
                return pred()
        return True
