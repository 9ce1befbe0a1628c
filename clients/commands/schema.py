"""energyctl schema: write the JSON Schemas of the messages, configs, scenario and query replies."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    g = subparsers.add_parser("schema", help="write JSON Schemas of the messages, the configs, the scenario and the "
                                             "query replies")
    g.description = ("Writes one JSON Schema file per message (with its binary wire layout: x-wire-order, "
                     "x-wire-type, x-wire-offset, x-magic, x-version, x-size-bytes), per process config (run, plant, "
                     "load), for the scenario and for the query replies, generated from the pydantic models. The "
                     "repository's schemas/json is checked against this output by the tests.")
    g.add_argument("--out", default="schemas/json", help="output directory (default: %(default)s)")
    g.set_defaults(func=run)
    return g


def run(args: argparse.Namespace) -> int:
    from schemas.generate import write_schemas

    for p in write_schemas(args.out):
        print(p)
    return 0
