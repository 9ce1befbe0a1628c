"""The config-key listing of ``run``/``plant``/``load --help``: the same rows as docs/configuration.md, from the
pydantic models through ``schemas.generate.config_keys``, so the help cannot drift from the models."""

from __future__ import annotations

from pydantic import BaseModel

from schemas.generate import config_keys


def key_line(key: str, type_: str, default: str) -> str:
    """'key = default  [type]' for a value, 'key  [table]' for a table, 'key  [type; required]' without default."""
    if type_ in ("table", "list of tables", "tables by name"):
        optional = "; unset by default" if default == "unset" else ""
        value = f" = {default}" if type_ == "list of tables" else ""
        return f"{key}{value}  [{type_}{optional}]"
    if default == "required":
        return f"{key}  [{type_}; required]"
    return f"{key} = {default}  [{type_}]"


def config_epilog(model: type[BaseModel], file: str, example: str) -> str:
    """The --help epilog of a command reading a ``model`` config from ``file``: how keys are written, then every
    key (clients.options.HelpFormatter keeps the indented listing as it is)."""
    table, _, rest = example.partition(".")
    paths = "Zenoh file paths and csv profiles" if "base_dir" in model.model_fields else "Zenoh file paths"
    head = (f"{file} keys (TOML; a dotted key is a key of a table: {example} is written as "
            f"{rest.replace('=', ' = ')} under [{table}], and --set {example} overrides it). A top-level "
            'extends = "OTHER.toml" starts from another file: tables merge key by key, anything else replaces. '
            f"Relative {paths} are taken from the file's directory.")
    lines = []
    for key, type_, default, desc in config_keys(model):
        lines.append(f"  {key_line(key, type_, default)}")
        if desc:
            lines.append(f"      {desc}")
    return head + "\n\n" + "\n".join(lines)
