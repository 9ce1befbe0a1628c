"""docs/configuration.md: its key reference is what the generator makes of the models now, and every shipped TOML
uses only keys that reference lists (for the model that reads that file)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from schemas.generate import (
    CONFIG_MODELS,
    DOC_BEGIN,
    DOC_COMMAND,
    DOC_END,
    config_reference_markdown,
    generated_region,
    replace_generated,
    write_docs,
)

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "configuration.md"
HINT = f"docs/configuration.md is stale: run  {DOC_COMMAND}"
SECTION = re.compile(r"^### (\w+) keys$", flags=re.M)
ENTRY = re.compile(r"^- `([^`]+)` \(", flags=re.M)
# which model reads a shipped TOML, by its file name (scenarios/live and scenarios/secure hold process configs)
BY_NAME = {"component.toml": "ComponentConfig", "plant.toml": "PlantPeerConfig", "load.toml": "LoadPeerConfig"}


def stale_region(text: str) -> str | None:
    """None when the generated region of ``text`` is what the generator produces now; else a short diff."""
    have, want = generated_region(text), config_reference_markdown().strip("\n")
    if have == want:
        return None
    for n, (a, b) in enumerate(zip(have.splitlines(), want.splitlines(), strict=False), 1):
        if a != b:
            return f"line {n} of the region: have {a!r}, generated {b!r}"
    return f"the region has {len(have.splitlines())} lines, the generator {len(want.splitlines())}"


def documented_keys(text: str) -> dict[str, set[str]]:
    """Model name ('Scenario', 'ComponentConfig', ...) -> the dotted keys its section of the reference lists."""
    region = generated_region(text)
    parts = SECTION.split(region)  # [before, name, body, name, body, ...]
    return {name: set(ENTRY.findall(body)) for name, body in zip(parts[1::2], parts[2::2], strict=True)}


def toml_keys(data: dict, prefix: str = "") -> set[str]:
    """Every dotted key a TOML document sets, tables included; a list of tables' keys as ``key[].sub``."""
    out: set[str] = set()
    for k, v in data.items():
        key = prefix + k
        out.add(key)
        if isinstance(v, dict):
            out |= toml_keys(v, key + ".")
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for x in v:
                out |= toml_keys(x, key + "[].")
    return out


def undocumented(used: set[str], documented: set[str]) -> set[str]:
    """The used keys the reference does not list; a documented ``key.<name>.sub`` (tables by name) stands for
    every name."""
    named = {k for k in documented if "<name>" in k}
    named |= {k[:k.index("<name>") + len("<name>")] for k in named}  # the named table itself
    patterns = [re.compile("^" + re.escape(k).replace(re.escape("<name>"), "[^.]+") + "$") for k in named]
    return {k for k in used - documented if not any(p.match(k) for p in patterns)}


def model_of(path: Path) -> str:
    """The model that reads a shipped TOML: process configs by name under scenarios/live and scenarios/secure (an
    'id' key confirms it), scenarios everywhere else (which have no 'id')."""
    data = tomllib.loads(path.read_text())
    if path.parent.name in ("live", "secure"):
        assert path.name in BY_NAME, f"{path}: which process reads it? (expected one of {sorted(BY_NAME)})"
        assert "id" in data or "extends" in data, f"{path}: a process config without id or extends"
        return BY_NAME[path.name]
    assert "id" not in data, f"{path}: has an 'id' like a process config, but is not under live/ or secure/"
    return "NetworkScenario" if data.get("kind") == "network" else "Scenario"


def shipped_tomls() -> list[Path]:
    return [*sorted((ROOT / "scenarios").rglob("*.toml")), ROOT / "clients" / "embedded" / "demo.toml"]


def test_the_generated_region_is_current():
    assert stale_region(DOC.read_text(encoding="utf-8")) is None, HINT


def test_a_changed_region_is_detected_and_rewritten(tmp_path):
    text = DOC.read_text(encoding="utf-8")
    # a default edited by hand, a key dropped, and text outside the markers (which is left alone)
    edited = text.replace("default `2000.0`", "default `2500.0`", 1)
    dropped = re.sub(r"^- `controller\.K_per_s` .*\n", "", text, count=1, flags=re.M)
    assert edited != text and dropped != text
    assert "2500.0" in stale_region(edited)
    assert stale_region(dropped) is not None
    copy = tmp_path / "configuration.md"
    copy.write_text(dropped.replace("# Configuration", "# Configuration, edited", 1), encoding="utf-8")
    assert write_docs(copy, check=True) and stale_region(copy.read_text(encoding="utf-8")) is not None
    assert write_docs(copy)  # rewrites the region only
    fixed = copy.read_text(encoding="utf-8")
    assert stale_region(fixed) is None and fixed.startswith("# Configuration, edited")
    assert fixed.split(DOC_END)[1] == text.split(DOC_END)[1]
    assert not write_docs(copy)  # now current


def test_a_model_change_makes_the_region_stale(monkeypatch):
    """What the test above guards against: a new field in a model shows up in the generator, not yet in the doc."""
    from pydantic import Field, create_model

    import schemas.generate as gen

    base = CONFIG_MODELS["energyctl.LoadPeerConfig"]
    grown = create_model("LoadPeerConfig", __base__=base,
                         burst_W=(float, Field(default=0.0, ge=0, description="a new key, W")))
    monkeypatch.setitem(gen.CONFIG_MODELS, "energyctl.LoadPeerConfig", grown)
    assert "- `burst_W` (float ≥ 0; default `0.0`): a new key, W" in config_reference_markdown()
    assert stale_region(DOC.read_text(encoding="utf-8")) is not None


def test_the_markers_must_be_there():
    with pytest.raises(ValueError, match="generated: begin"):
        replace_generated("# no markers\n", "x")
    assert replace_generated(f"a\n{DOC_BEGIN}\nold\n{DOC_END}\nb\n", "new\n") == f"a\n{DOC_BEGIN}\nnew\n{DOC_END}\nb\n"


def test_every_model_has_its_section_with_every_top_level_field():
    keys = documented_keys(DOC.read_text(encoding="utf-8"))
    assert sorted(keys) == sorted(m.__name__ for m in CONFIG_MODELS.values())
    for model in CONFIG_MODELS.values():
        assert set(model.model_fields) <= keys[model.__name__], model.__name__
    assert {"controller.K_per_s", "loop.rate_hz", "zenoh.connect", "controller.limits.u_max_V",
            "extends"} <= keys["ComponentConfig"]
    assert {"load.components[].amplitude", "timing.command_outages"} <= keys["Scenario"]
    assert "extends" not in keys["Scenario"]  # scenarios are read without it


@pytest.mark.parametrize("path", shipped_tomls(), ids=lambda p: str(p.relative_to(ROOT)))
def test_shipped_tomls_use_only_documented_keys(path):
    keys = documented_keys(DOC.read_text(encoding="utf-8"))
    model = model_of(path)
    used = toml_keys(tomllib.loads(path.read_text()))
    assert used, path
    assert sorted(undocumented(used, keys[model])) == [], \
        f"{path.relative_to(ROOT)} ({model}): keys not in docs/configuration.md"


def test_the_key_walk_finds_an_undocumented_key():
    keys = documented_keys(DOC.read_text(encoding="utf-8"))
    data = tomllib.loads('id = "x"\nneighbors = ["load"]\n[loop]\nrate = 1.0\n[load]\n'
                        "components = [{ amplitude = 1.0, freq_hz = 2.0, phase = 0.1 }]\n")
    assert toml_keys(data) - keys["ComponentConfig"] == {"neighbors", "loop.rate", "load", "load.components",
                                                          "load.components[].amplitude", "load.components[].freq_hz",
                                                          "load.components[].phase"}
    assert toml_keys(data) - keys["PlantPeerConfig"] == {"neighbors", "loop", "loop.rate", "load.components[].phase"}


def test_the_doc_keeps_its_form():
    text = DOC.read_text(encoding="utf-8")
    lines = text.splitlines()
    assert [n for n, line in enumerate(lines, 1) if len(line) > 120] == []
    assert not re.search(r"\bissues? \d+|#\d+\b|\b20\d\d-\d\d-\d\d\b", text, flags=re.I)
    for target in re.findall(r"^\[[\w-]+\]: (\S+)$", text, flags=re.M):  # reference-style links
        assert (DOC.parent / target).resolve().exists(), target
