"""energyctl compare: scenarios under several controllers, one table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from clients.commands.common import ACCEPTANCE_HELP, failure_lines, kinds, load, parallel
from clients.options import add_scenario_set
from clients.table import metrics_table


def add_parser(subparsers) -> argparse.ArgumentParser:
    c = subparsers.add_parser(
        "compare", help="run scenarios under several controllers, one table",
        description="Runs every scenario under every controller in --controllers offline (as energyctl sim does, "
                    "in parallel processes) and prints one metrics table, a row per scenario and controller "
                    "(--json: a JSON list, one object per row). The metrics are those of energyctl sim --help. "
                    "A baseline that leaves the band where the scenario requires it makes the comparison exit 1: "
                    "the table is complete, and the failed rows are named under it. " + ACCEPTANCE_HELP)
    c.add_argument("scenarios", nargs="+", metavar="SCENARIO", help="scenario TOML files (see scenarios/)")
    c.add_argument("--controllers", default="fblc,smc,lqr,bm", help="comma list (default: %(default)s)")
    add_scenario_set(c)
    c.add_argument("--jobs", type=int, default=None, help="processes (default: all cores)")
    c.add_argument("--json", action="store_true", help="a JSON list of rows instead of the table")
    c.set_defaults(func=run)
    return c


def run(args: argparse.Namespace) -> int:
    controllers = kinds(args.controllers)
    jobs = [(path, [*(args.set or []), f'controller.kind="{k}"'], (Path(path).stem, k))
            for path in args.scenarios for k in controllers]
    for path, ovs, _ in jobs:  # validate everything before starting work
        load(path, ovs)
    results = parallel([(p, o) for p, o, _ in jobs], args.jobs)
    rows = [([label[0], label[1]], m) for (_, _, label), m in zip(jobs, results, strict=True)]
    if args.json:
        print(json.dumps([{"scenario": r[0][0], "controller": r[0][1], **r[1]} for r in rows]))
    else:
        print(metrics_table(rows, ["scenario", "controller"]))
        for labels, m in rows:
            for line in failure_lines(" ".join(labels), m):
                print(line)
    return 0 if all(m["accepted"] for _, m in rows) else 1
