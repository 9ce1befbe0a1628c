"""What is generated from the models: every JSON Schema in schemas/json, and the key reference in
docs/configuration.md (``python3 -m schemas.generate --out schemas/json --docs docs/configuration.md``;
``energyctl schema`` writes the schemas too).

JSON Schemas:

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

docs/configuration.md: the text between its ``<!-- generated: begin -->`` and ``<!-- generated: end -->`` lines is
:func:`config_reference_markdown`, every key of the scenario and the three process configs as a dotted key with its
type, constraints, default and description; :func:`write_docs` rewrites only that region.
"""

from __future__ import annotations

import argparse
import inspect
import json
import re
import types
import typing
from pathlib import Path

from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from schemas.codec import BY_MODEL, VERSION, Codec
from schemas.component import ComponentConfig, LoadPeerConfig, PlantPeerConfig
from schemas.messages import MESSAGE_MODELS
from schemas.network import NetworkScenario
from schemas.replies import REPLY_MODELS
from schemas.scenario import Scenario

DIALECT = "https://json-schema.org/draft/2020-12/schema"

CONFIG_MODELS: dict[str, type[BaseModel]] = {
    "energyctl.ComponentConfig": ComponentConfig,
    "energyctl.PlantPeerConfig": PlantPeerConfig,
    "energyctl.LoadPeerConfig": LoadPeerConfig,
    "energyctl.Scenario": Scenario,
    "energyctl.NetworkScenario": NetworkScenario,
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


# --- docs/configuration.md: every key of the scenario and the three process configs, from the models -------------

DOC_BEGIN = "<!-- generated: begin -->"
DOC_END = "<!-- generated: end -->"
DOC_COMMAND = "python3 -m schemas.generate --docs docs/configuration.md"
DOC_WIDTH = 120

# (JSON Schema stem, what reads the file when the model's docstring does not say); the model is CONFIG_MODELS[stem]
DOC_SECTIONS: list[tuple[str, str]] = [
    ("energyctl.Scenario", "`energyctl sim`, `compare`, `sweep`, `demo` and `bench`"),
    ("energyctl.NetworkScenario", "`energyctl sim` (a file with kind = \"network\")"),
    ("energyctl.ComponentConfig", ""),
    ("energyctl.PlantPeerConfig", ""),
    ("energyctl.LoadPeerConfig", ""),
]
SCENARIO_INTRO = ("A scenario: the true plant, the controller's own model of it, the load, the sensors, the timing and "
                  "the controller of one closed loop, run offline or as a lockstep co-simulation.")
# keys the loader reads before validation (schemas.component.load_config), for the models it loads
EXTENDS_DOC = ("another config file of the same kind (path relative to this file) to start from: tables merge key by "
               "key, any other value in this file replaces the other's; read by the loader, not a field of the model")
LOADER_KEYS: dict[type[BaseModel], list[tuple[str, str]]] = {
    m: [("extends", EXTENDS_DOC)] for m in (ComponentConfig, PlantPeerConfig, LoadPeerConfig)}


def _members(tp) -> list:
    """The members of a union (the type itself when it is not one)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return list(typing.get_args(tp))
    return [tp]


def _unannotated(tp) -> tuple[object, list]:
    """Annotated[T, meta...] -> (T, constraints): the annotated_types constraints of the metadata, Field()s opened."""
    if typing.get_origin(tp) is not typing.Annotated:
        return tp, []
    base, *meta = typing.get_args(tp)
    out: list = []
    for m in meta:
        out += list(m.metadata) if isinstance(m, FieldInfo) else [m]
    return base, out


def _number(v) -> str:
    return repr(v) if isinstance(v, float) else str(v)


def _constraint_text(constraints: list) -> tuple[str, bool]:
    """('> 0', '≥ 0', 'in [1000, 20000]', 'in (0, 60]', 'in [0, 1)' or '', finite) from annotated_types
    constraints."""
    b: dict[str, object] = {}
    finite = False
    for c in constraints:
        for name in ("gt", "ge", "lt", "le"):
            if getattr(c, name, None) is not None:
                b[name] = getattr(c, name)
        if getattr(c, "allow_inf_nan", None) is False:
            finite = True
    low = ("(", b["gt"]) if "gt" in b else ("[", b["ge"]) if "ge" in b else None
    high = (")", b["lt"]) if "lt" in b else ("]", b["le"]) if "le" in b else None
    if low and high:
        return f"in {low[0]}{_number(low[1])}, {_number(high[1])}{high[0]}", False
    if low:
        return f"{'>' if low[0] == '(' else '≥'} {_number(low[1])}", finite
    if high:
        return f"{'<' if high[0] == ')' else '≤'} {_number(high[1])}", finite
    return "", finite


_TOML_TYPES = {str: "string", int: "integer", float: "float", bool: "boolean"}


def type_text(tp, constraints: list | None = None) -> str:
    """A field's type as a reader writes it in TOML: 'float > 0', 'list of string', '"peer", "client" or "router"',
    '[float ≥ 0, float > 0]' (a two-element array), 'float or "measured"', 'integer in [0, 200]' (interval
    notation), 'finite float' (no inf or nan); None in a union is left out (such a field is optional: its default
    says 'unset')."""
    tp, more = _unannotated(tp)
    constraints = [*(constraints or []), *more]
    members = [m for m in _members(tp) if m is not type(None)]
    if len(members) > 1:
        literals = [v for m in members if typing.get_origin(m) is typing.Literal for v in typing.get_args(m)]
        others = [type_text(m, constraints) for m in members if typing.get_origin(m) is not typing.Literal]
        return _or(others + [json.dumps(v) for v in literals])
    (tp,) = members
    if typing.get_origin(tp) is typing.Annotated:
        return type_text(tp, constraints)
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        return _or([json.dumps(v) for v in typing.get_args(tp)])
    if origin is list:
        (item,) = typing.get_args(tp)
        return f"list of {type_text(item)}"
    if origin is tuple:
        return "[" + ", ".join(type_text(a) for a in typing.get_args(tp)) + "]"
    if origin is dict:
        k, v = typing.get_args(tp)
        return f"table of {type_text(k)} to {type_text(v)}"
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return "table"
    name = _TOML_TYPES.get(tp, getattr(tp, "__name__", str(tp)))
    bounds, finite = _constraint_text(constraints)
    return " ".join(w for w in ("finite" if finite else "", name, bounds) if w)


def _or(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def toml_value(v) -> str:
    """A default as written in TOML (None: 'unset', the key left out)."""
    if v is None:
        return "unset"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return _number(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, BaseModel):
        v = v.model_dump()
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    return str(v)


def _model_in(tp) -> tuple[type[BaseModel] | None, str]:
    """(the model a field holds, how: "" one table, "list" a list of them, "dict" tables by name); (None, "") for a
    plain value."""
    for m in _members(_unannotated(tp)[0]):
        m = _unannotated(m)[0]
        if isinstance(m, type) and issubclass(m, BaseModel):
            return m, ""
        origin = typing.get_origin(m)
        if origin in (list, dict):
            item = _unannotated(typing.get_args(m)[-1])[0]
            if isinstance(item, type) and issubclass(item, BaseModel):
                return item, "list" if origin is list else "dict"
    return None, ""


def _doc_of(model: type[BaseModel]) -> str:
    """The model's own docstring (not an inherited one) as one paragraph, RST ``code`` as Markdown `code`."""
    doc = model.__dict__.get("__doc__") or ""
    return " ".join(inspect.cleandoc(doc).split()).replace("``", "`")


def config_keys(model: type[BaseModel], prefix: str = "", defaults: BaseModel | None = None
                ) -> list[tuple[str, str, str, str]]:
    """(dotted key, type, default, description) for every key of the model, its tables' keys after the table's
    own row; a list of tables' keys as ``key[].sub``, tables by name as ``key.<name>.sub``. ``defaults``: the
    instance whose values are the defaults here (a table's default can differ from its model's own field
    defaults: ComponentConfig.forecast)."""
    out: list[tuple[str, str, str, str]] = []
    for name, field in model.model_fields.items():
        key = prefix + name
        if defaults is not None:
            default = getattr(defaults, name)
        elif field.is_required():
            default = PydanticUndefined
        else:
            default = field.get_default(call_default_factory=True)
        desc = field.description or ""
        sub, how = _model_in(field.annotation)
        if sub is not None:
            doc = _doc_of(sub)
            desc = f"{desc}. {doc}" if desc and doc else desc or doc
            if how == "list":
                out.append((key, "list of tables", toml_value(default), desc))
                out += config_keys(sub, f"{key}[].")
            elif how == "dict":
                out.append((key, "tables by name", "required" if default is PydanticUndefined else "", desc))
                out += config_keys(sub, f"{key}.<name>.")
            else:
                out.append((key, "table", "unset" if default is None else "", desc))
                out += config_keys(sub, f"{key}.", default if isinstance(default, BaseModel) else None)
            continue
        shown = "required" if default is PydanticUndefined else toml_value(default)
        out.append((key, type_text(field.annotation, list(field.metadata)), shown, desc))
    return out


def _key_line(key: str, type_: str, default: str, desc: str) -> str:
    """One Markdown list item, wrapped at DOC_WIDTH."""
    if default == "required":
        head = f"- `{key}` ({type_}, required)"
    elif type_ == "table":
        head = f"- `{key}` (table{', optional' if default == 'unset' else ''})"
    elif type_ == "tables by name":
        head = f"- `{key}` (tables by name: `[{key}.NAME]`)"
    else:
        head = f"- `{key}` ({type_}; default `{default}`)"
    return "\n".join(wrap(f"{head}: {desc}" if desc else head, indent="  "))


_BLOCK_START = re.compile(r"^([-+*>#|]|\d+[.)])(\s|$)")


def wrap(text: str, indent: str = "") -> list[str]:
    """Greedy wrap at DOC_WIDTH with ``indent`` before every line but the first, never breaking a word, and never
    starting a line with what Markdown would read as a list item, quote, heading or table ('- x' in a formula)."""
    lines: list[list[str]] = [[]]
    for word in text.split():
        line = lines[-1]
        width = len(indent if len(lines) > 1 else "") + len(" ".join([*line, word]))
        if line and width > DOC_WIDTH:
            carried = [word]
            while _BLOCK_START.match(" ".join(carried)) and len(line) > 1:
                carried.insert(0, line.pop())
            lines.append(carried)
        else:
            line.append(word)
    return [(indent if n else "") + " ".join(line) for n, line in enumerate(lines)]


def config_reference_markdown() -> str:
    """The generated region of docs/configuration.md: for the scenario and each process config, a heading, the
    model's docstring, a link to its JSON Schema, and one list item per dotted key (type and constraints, default,
    description). Nothing in it is written by hand; rewrite it with DOC_COMMAND."""
    out = [f"<!-- written by {DOC_COMMAND}: edit the models in schemas/, not this -->"]
    for stem, readers in DOC_SECTIONS:
        model = CONFIG_MODELS[stem]
        out += ["", f"### {model.__name__} keys", ""]
        intro = _doc_of(model) or SCENARIO_INTRO
        read_by = f" Read by {readers}." if readers else ""
        out += wrap(f"{intro}{read_by} JSON Schema: [{stem}.json](../schemas/json/{stem}.json).")
        out.append("")
        rows = [(k, "string", "unset", d) for k, d in LOADER_KEYS.get(model, [])] + config_keys(model)
        out += [_key_line(*row) for row in rows]
    return "\n".join(out) + "\n"


def replace_generated(text: str, generated: str) -> str:
    """``text`` with everything between the DOC_BEGIN and DOC_END lines replaced by ``generated``."""
    begin, end = text.find(DOC_BEGIN), text.find(DOC_END)
    if begin < 0 or end < begin or text.count(DOC_BEGIN) != 1 or text.count(DOC_END) != 1:
        raise ValueError(f"expected one {DOC_BEGIN!r} line, then one {DOC_END!r} line")
    head = text[:begin + len(DOC_BEGIN)]
    return f"{head}\n{generated.strip(chr(10))}\n{text[end:]}"


def generated_region(text: str) -> str:
    """What is between the markers now (as replace_generated writes it: without the newlines next to them)."""
    begin, end = text.find(DOC_BEGIN), text.find(DOC_END)
    if begin < 0 or end < begin:
        raise ValueError(f"expected one {DOC_BEGIN!r} line, then one {DOC_END!r} line")
    return text[begin + len(DOC_BEGIN):end].strip("\n")


def write_docs(path: str | Path, check: bool = False) -> bool:
    """Rewrite the generated region of ``path`` (docs/configuration.md); True when it changed (check: only say)."""
    p = Path(path)
    old = p.read_text(encoding="utf-8")
    new = replace_generated(old, config_reference_markdown())
    if new != old and not check:
        p.write_text(new, encoding="utf-8")
    return new != old


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python3 -m schemas.generate",
                                 description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--docs", metavar="FILE.md", help="rewrite the generated region of this file "
                                                      "(docs/configuration.md)")
    ap.add_argument("--out", metavar="DIR", help="write every JSON Schema into DIR (schemas/json)")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 when --docs / --out is stale")
    args = ap.parse_args(argv)
    if not args.docs and not args.out:
        ap.error("nothing to do: give --docs FILE.md and/or --out DIR")
    stale = False
    if args.docs:
        changed = write_docs(args.docs, check=args.check)
        stale |= changed
        print(f"{args.docs}: {'stale' if args.check and changed else 'rewritten' if changed else 'current'}")
    if args.out:
        if args.check:
            problems = stale_schemas(args.out)
            stale |= bool(problems)
            print("\n".join(problems) or f"{args.out}: current")
        else:
            for p in write_schemas(args.out):
                print(p)
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    raise SystemExit(main())
