"""energyctl schema: write the JSON Schemas of the messages, configs, scenario and query replies."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    g = subparsers.add_parser("schema", help="write JSON Schemas of the messages, the configs, the scenario and the "
                                             "query replies")
    g.add_argument("--out", default="schemas/json", help="output directory (default: %(default)s)")
    g.set_defaults(func=run)
    return g


def run(args: argparse.Namespace) -> int:
    from schemas.generate import write_schemas

    for p in write_schemas(args.out):
        print(p)
    return 0
