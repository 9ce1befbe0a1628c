"""Config values are taken only as their own type and inside bounds from physics or sense: a bool, a string or a
float for a number, an integer or a bool is refused, naming the field, in a TOML file, a --set and a config/set
alike; an integer for a float is taken (TOML's K_per_s = 2000)."""

from __future__ import annotations

import json
import types
import typing

import pytest

from schemas.component import ComponentConfig, LoadPeerConfig, PlantPeerConfig, config_from_dict
from schemas.generate import CONFIG_MODELS, _unannotated
from schemas.netlive import CoordinatorConfig, NetworkRigConfig
from schemas.scenario import Scenario, ScenarioError, load_scenario, scenario_from_dict

MODELS = [*CONFIG_MODELS.values(), NetworkRigConfig, CoordinatorConfig]


def _numbers(tp, constraints):
    """(type, constraints) of every int or float a field's type holds (through unions, lists, tuples, tables);
    a nested model comes out as (model, None)."""
    tp, more = _unannotated(tp)
    constraints = [*constraints, *more]
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for a in typing.get_args(tp):
            yield from _numbers(a, constraints)
    elif origin in (list, tuple):
        for a in typing.get_args(tp):
            yield from _numbers(a, [])
    elif origin is dict:
        yield from _numbers(typing.get_args(tp)[1], [])
    elif origin is typing.Annotated:
        yield from _numbers(tp, constraints)
    elif isinstance(tp, type) and hasattr(tp, "model_fields"):
        yield tp, None
    elif tp in (int, float):
        yield tp, constraints


def unbounded_numbers() -> list[str]:
    seen, out, todo = set(), [], list(MODELS)
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        for name, f in m.model_fields.items():
            for tp, cons in _numbers(f.annotation, list(f.metadata)):
                if cons is None:
                    todo.append(tp)
                    continue
                has = {a for c in cons for a in ("ge", "gt", "le", "lt") if getattr(c, a, None) is not None}
                if not (has & {"ge", "gt"} and has & {"le", "lt"}):
                    out.append(f"{m.__name__}.{name}")
    return sorted(set(out))


def test_every_number_of_every_config_has_a_lower_and_an_upper_bound():
    assert unbounded_numbers() == []


def test_every_config_model_is_strict():
    assert all(m.model_config.get("strict") for m in MODELS)


LAX = [  # each was taken before, as the value after the arrow
    ("controller.K_per_s=true", "controller.K_per_s"),  # -> 1.0 (v reached 191 V)
    ('controller.K_per_s="2000"', "controller.K_per_s"),  # -> 2000.0
    ('controller.plan_next_period="yes"', "controller.plan_next_period"),  # -> True
    ("controller.plan_next_period=1", "controller.plan_next_period"),  # -> True
    ("controller.delay_compensation_samples=3.0", "controller.delay_compensation_samples"),  # -> 3
    ("controller.delay_compensation_samples=true", "controller.delay_compensation_samples"),  # -> 1
    ("controller.v_ref_V=1e300", "controller.v_ref_V"),
    ("controller.limits.du_dt_max_V_per_s=1e300", "controller.limits.du_dt_max_V_per_s"),
    ("plant.C_F=1e9", "plant.C_F"),
    ('timing.delay_samples="2"', "timing.delay_samples"),
    ("seed=-1", "seed"),
]


@pytest.mark.parametrize(("override", "field"), LAX)
def test_a_scenario_refuses_lax_values_naming_the_field(override, field):
    with pytest.raises(ScenarioError, match=rf"\n  {field}: "):
        scenario_from_dict({}, [override], "test")


@pytest.mark.parametrize(("override", "field"), LAX[:8])
def test_a_daemon_config_refuses_lax_values_naming_the_field(override, field):
    with pytest.raises(ScenarioError, match=rf"\n  {field}: "):
        config_from_dict(ComponentConfig, {"id": "c"}, [override], "test")


def test_integers_for_floats_are_taken_from_toml_and_from_set(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text("[controller]\nK_per_s = 2000\nv_ref_V = 80\n[plant]\nC_F = 1\n")
    scn = load_scenario(p, ["controller.K_E_per_s=150"])
    assert scn.controller.K_per_s == 2000.0 and type(scn.controller.K_per_s) is float
    assert scn.controller.K_E_per_s == 150.0 and scn.plant.C_F == 1.0
    assert config_from_dict(PlantPeerConfig, {"id": "p", "controller_id": "c"},
                            ["sample_rate_hz=10000"]).sample_rate_hz == 10000.0


def test_arrays_for_pairs_are_taken_from_toml_json_and_a_dump(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[load]\nkind = "steps"\nvalue = 1000\nsteps = [[0.05, 1500], [0.1, 800.0]]\n'
                 "[timing]\ncommand_outages = [[0.02, 0.001]]\n")
    scn = load_scenario(p)
    assert scn.load.steps == [(0.05, 1500.0), (0.1, 800.0)] and scn.timing.command_outages == [(0.02, 0.001)]
    assert Scenario.model_validate_json(scn.model_dump_json()) == scn
    assert Scenario.model_validate(json.loads(scn.model_dump_json())) == scn  # a log's metadata, read back
    with pytest.raises(ScenarioError, match=r"load.steps.0.1"):
        load_scenario(p, ['load.steps=[[0.05, "1500"]]'])


def test_peer_configs_refuse_a_string_count():
    with pytest.raises(ScenarioError, match=r"duration_s"):
        config_from_dict(LoadPeerConfig, {"id": "l"}, ['duration_s="60"'])
