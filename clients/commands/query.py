"""energyctl query: ask a running controller for its status, config (get/set) or a component's interaction."""

from __future__ import annotations

import argparse
import json
import sys

from clients.options import add_zenoh, zenoh_from_args
from clients.table import render


def add_parser(subparsers) -> argparse.ArgumentParser:
    qu = subparsers.add_parser(
        "query", help="ask a running controller: status, config (get/set), interaction",
        description="Asks a running daemon (energyctl run) over Zenoh and prints the answer as a table of fields, "
                    "values and units (--json: the reply itself). 'status' gets PREFIX/ID/status: state, loop "
                    "statistics, the last sample and command, estimates, feasibility, neighbours, rejections. "
                    "'config' gets PREFIX/ID/config; with --set it sends them to PREFIX/ID/config/set, where they "
                    "are validated together and applied at the next tick (all or none; the answer is the new "
                    "config, or the error naming the field). 'interaction' reads the component's newest "
                    "interaction message on PREFIX/ID/z (published only while the daemon steps: its plant "
                    "running). --set with anything but 'config' is refused (exit 2). Exit 1 when no daemon answers "
                    "within --timeout or it refuses.")
    qu.add_argument("what", choices=["status", "config", "interaction"], help="what to ask for")
    qu.add_argument("--component", required=True, metavar="ID", help="the component's id (its config's id)")
    qu.add_argument("--prefix", default="energyctl", help="key-expression prefix (default: %(default)s)")
    qu.add_argument("--set", action="append", metavar="key=value",
                    help="with 'config': controller.K_per_s=800, lifecycle=inactive, ... (repeatable)")
    qu.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the answer (default: %(default)s)")
    qu.add_argument("--json", action="store_true", help="print the reply as JSON")
    add_zenoh(qu)
    qu.set_defaults(func=run)
    return qu


def run(args: argparse.Namespace) -> int:
    from clients.query import QueryError, flatten, query, unit_of

    if args.set and args.what != "config":
        print(f"energyctl query: --set goes with 'config' (it changes the daemon); '{args.what}' only reads",
              file=sys.stderr)
        return 2

    try:
        ans = query(zenoh_from_args(args), args.prefix, args.component, args.what, args.set, args.timeout)
    except QueryError as e:
        print(f"energyctl query: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(ans))
    else:
        print(render(["field", "value", "unit"], [[k, v, unit_of(k)] for k, v in flatten(ans)]))
    return 0
