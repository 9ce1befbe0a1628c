"""Scenario files: shipped ones load; bad ones are rejected with the field named."""

from __future__ import annotations

import math

import pytest
from conftest import SCENARIOS

from schemas.scenario import Scenario, ScenarioError, load_scenario, scenario_from_dict
from service.plant.profiles import Profile


def test_shipped_scenarios_load_and_keep_true_and_model_parameters_apart(paper_files):
    names = {p.name for p in paper_files}
    assert {"paper-constant-load.toml", "paper-varying-load.toml", "paper-r-error.toml",
            "paper-feasibility.toml"} <= names
    s = load_scenario(SCENARIOS / "paper-r-error.toml")
    assert s.plant.R_ohm == 0.01 and s.model.R_ohm == pytest.approx(0.011)


@pytest.mark.parametrize(("data", "field", "words"), [
    ({"plant": {"L_H": -1.0}}, "plant.L_H", "greater than 0"),
    ({"plant": {"L_H": "big"}}, "plant.L_H", "valid number"),
    ({"plant": {"initial": {"v_V": float("nan")}}}, "plant.initial.v_V", "finite"),
    ({"controller": {"kind": "pid"}}, "controller.kind", "fblc"),
    ({"controller": {"limits": {"u_min_V": 10.0, "u_max_V": 5.0}}}, "controller.limits", "u_min_V must be < u_max_V"),
    ({"timing": {"control_rate_hz": 10.0}}, "timing.control_rate_hz", "greater than or equal to 100"),
    ({"timing": {"delay_samples": -1}}, "timing.delay_samples", "greater than or equal to 0"),
    ({"load": {"kind": "steps", "steps": [[0.5, 1.0], [0.1, 2.0]]}}, "load", "sorted"),
    ({"load": {"kind": "csv"}}, "load", "csv_path"),
    ({"sensor": {"noise_v": 0.1}}, "sensor.noise_v", "Extra inputs"),
    ({"contoller": {}}, "contoller", "Extra inputs"),
])
def test_bad_scenarios_name_the_field(data, field, words):
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict(data, source="x.toml")
    msg = str(ei.value)
    assert f"  {field}" in msg and words in msg, msg


def test_bad_files_and_overrides(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[plant\nR_ohm = 1")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(bad)
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")
    with pytest.raises(ScenarioError, match="expected dotted.key=value"):
        load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.delay_samples"])
    with pytest.raises(ScenarioError, match="timing.delay_samples"):
        load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.delay_samples=-2"])
    s = load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.delay_samples=2", 'controller.kind="smc"'])
    assert s.timing.delay_samples == 2 and s.controller.kind == "smc"


def test_csv_load_profile_is_piecewise_linear(tmp_path):
    (tmp_path / "load.csv").write_text("t_s,P_W\n0,1000\n0.1,1500\n0.2,1500\n")
    (tmp_path / "s.toml").write_text('[load]\nkind = "csv"\ncsv_path = "load.csv"\n')
    s = load_scenario(tmp_path / "s.toml")
    prof = Profile(s.load, s.base_dir)
    assert prof.value(0.05) == pytest.approx(1250.0)
    assert prof.rate(0.05) == pytest.approx(5000.0)
    assert prof.value(0.15) == 1500.0 and prof.rate(0.15) == 0.0
    assert prof.value(5.0) == 1500.0
    (tmp_path / "bad.csv").write_text("0,1\n0,2\n")
    s2 = scenario_from_dict({"load": {"kind": "csv", "csv_path": "bad.csv"}, "base_dir": str(tmp_path)})
    with pytest.raises(ValueError, match="strictly increasing"):
        Profile(s2.load, s2.base_dir)


def test_sine_profile_rate_is_its_derivative():
    s = Scenario.model_validate({"load": {"kind": "sines", "value": 1200.0, "components": [
        {"amplitude": 300.0, "freq_hz": 5.0}, {"amplitude": 150.0, "freq_hz": 13.0, "phase_rad": 0.7}]}})
    prof = Profile(s.load)
    for t in (0.0, 0.013, 0.31):
        h = 1e-6
        assert prof.rate(t) == pytest.approx((prof.value(t + h) - prof.value(t - h)) / (2 * h), rel=1e-6)
    lo, hi, dlo, dhi = prof.range_over(0.0, 1.0)
    assert lo < 1200 - 300 and hi > 1200 + 300 and hi <= 1650 and dhi <= 300 * 2 * math.pi * 5 + 150 * 2 * math.pi * 13


def test_shipped_live_configs_validate():
    from schemas.component import ComponentConfig, LoadPeerConfig, PlantPeerConfig, load_config

    live = SCENARIOS / "live"
    assert load_config(ComponentConfig, live / "component.toml").neighbours == ["load"]
    assert load_config(PlantPeerConfig, live / "plant.toml").controller_id == "source"
    assert load_config(LoadPeerConfig, live / "load.toml").plant_id == "source"
    with pytest.raises(ScenarioError, match="loop.rate_hz"):
        load_config(ComponentConfig, live / "component.toml", ["loop.rate_hz=50.0"])
