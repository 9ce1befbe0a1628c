"""Every JSON Schema in schemas/json, generated from the models (``energyctl schema`` writes them).

* messages (``energyctl.Measurement`` ...): the model's schema with its binary wire layout read off the codec
  (schemas.codec) itself: properties in wire order, ``x-wire-order``, per property ``x-wire-type`` and
  ``x-wire-offset`` (bytes), and at the top ``x-magic``, ``x-version``, ``x-endianness``, ``x-size-bytes`` and
  ``x-wire-header`` (the magic and version bytes before the fields). energyctl.Event has no binary form (JSON text
  in recordings only) and so no x-wire keys;
* configs: the daemon's (energyctl.ComponentConfig, ``energyctl run --config``), the plant's
  (energyctl.PlantPeerConfig), the load's (energyctl.LoadPeerConfig), and energyctl.Scenario;
* the daemon's query replies (schemas.replies).

The text is canonical (2-space indent, keys sorted except each ``properties`` object, which keeps the model's
field order: for a message, its wire order), so a stale file shows in a plain comparison (:func:`stale_schemas`).
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import BaseModel

from schemas.codec import BY_MODEL, VERSION, Codec
from schemas.component import ComponentConfig, LoadPeerConfig, PlantPeerConfig
from schemas.messages import MESSAGE_MODELS
from schemas.replies import REPLY_MODELS
from schemas.scenario import Scenario

DIALECT = "https://json-schema.org/draft/2020-12/schema"

CONFIG_MODELS: dict[str, type[BaseModel]] = {
    "energyctl.ComponentConfig": ComponentConfig,
    "energyctl.PlantPeerConfig": PlantPeerConfig,
    "energyctl.LoadPeerConfig": LoadPeerConfig,
    "energyctl.Scenario": Scenario,
}


def magic_of(codec: Codec) -> dict:
    """The magic byte as written on the wire: hex, and its ASCII character (null when not printable ASCII)."""
    b = codec.magic.to_bytes(1, "little")
    return {"hex": f"0x{codec.magic:02X}", "ascii": b.decode("ascii") if 0x20 <= codec.magic < 0x7F else None}


def message_schema(model: type[BaseModel]) -> dict:
    """The message model's JSON Schema, with its wire layout when the codec has a binary form for it."""
    schema = model.model_json_schema()
    codec = BY_MODEL.get(model)
    if codec is None:
        return schema
    layout = codec.layout()
    header, fields = layout[:2], layout[2:]
    props = schema["properties"]
    if [f[0] for f in fields] != list(props):
        raise AssertionError(f"{codec.name}: codec fields {[f[0] for f in fields]} != model fields {list(props)}")
    schema["properties"] = {name: {**props[name], "x-wire-type": wire, "x-wire-offset": offset}
                            for name, wire, offset, _size in fields}
    schema.update({
        "x-wire-order": [f[0] for f in fields],
        "x-wire-header": [{"name": name, "x-wire-type": wire, "x-wire-offset": offset}
                          for name, wire, offset, _size in header],
        "x-magic": magic_of(codec),
        "x-version": VERSION,
        "x-endianness": codec.endianness,
        "x-size-bytes": codec.size,
    })
    return schema


def all_schemas() -> dict[str, dict]:
    """file stem (``energyctl.Command``) -> JSON Schema, for everything schemas/json holds."""
    out: dict[str, dict] = {}
    for name, model in MESSAGE_MODELS.items():
        out[name] = message_schema(model)
    for name, model in {**CONFIG_MODELS, **REPLY_MODELS}.items():
        out[name] = model.model_json_schema()
    return {name: {"$schema": DIALECT, **schema} for name, schema in out.items()}


def _canonical(node, field_map: bool = False):
    """Keys sorted, except in a schema's "properties" object (field_map: field name -> schema), which keeps the
    model's field order."""
    if isinstance(node, dict):
        keys = list(node) if field_map else sorted(node)
        return {k: _canonical(node[k], not field_map and k == "properties" and isinstance(node[k], dict))
                for k in keys}
    if isinstance(node, list):
        return [_canonical(v) for v in node]
    return node


def schema_text(schema: dict) -> str:
    """The file text of one schema."""
    return json.dumps(_canonical(schema), indent=2, ensure_ascii=False) + "\n"


def write_schemas(out_dir: str | Path) -> list[Path]:
    """Write <name>.json for every schema of all_schemas() into out_dir; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in all_schemas().items():
        p = out / f"{name}.json"
        p.write_text(schema_text(schema), encoding="utf-8")
        paths.append(p)
    return paths


def stale_schemas(out_dir: str | Path, schemas: dict[str, dict] | None = None) -> list[str]:
    """What in out_dir differs from the generator (``schemas``: all_schemas()): one line per file that is stale,
    missing, or not generated at all; [] when everything is current."""
    schemas = all_schemas() if schemas is None else schemas
    d = Path(out_dir)
    problems = []
    for name, schema in schemas.items():
        p = d / f"{name}.json"
        if not p.exists():
            problems.append(f"{p.name}: missing")
        elif p.read_text(encoding="utf-8") != schema_text(schema):
            problems.append(f"{p.name}: stale")
    problems += [f"{p.name}: not generated" for p in sorted(d.glob("*.json")) if p.stem not in schemas]
    return problems
