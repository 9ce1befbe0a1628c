"""energyctl report: PNG figures like the paper's and a Markdown summary, from one log or two."""

from __future__ import annotations

import argparse
import sys


def add_parser(subparsers) -> argparse.ArgumentParser:
    re_ = subparsers.add_parser(
        "report", help="PNG figures like the paper's and a Markdown summary (one log, or two)",
        description="Draws a log (from energyctl sim --out or the daemon) like the paper's figures: states.png (i, "
                    "v with the +-2 % band, u, du/dt), energy.png (y_z against y_ref, u_z), interaction.png (the "
                    "outgoing against the incoming interaction variable, with the feasibility bands per window); "
                    "with two logs, both in each figure (e.g. a run and its replayed what-if). Writes them and "
                    "summary.md (metrics, config) into --out. Needs matplotlib: python3 -m pip install -e "
                    "'.[report]'. Exit 2 on a log it cannot read.")
    re_.add_argument("logs", nargs="+", metavar="LOG.mcap", help="one log, or two to compare")
    re_.add_argument("--out", default="report", help="output directory (default: %(default)s)")
    re_.set_defaults(func=run)
    return re_


def run(args: argparse.Namespace) -> int:
    from clients.report import ReportError, report

    try:
        res = report(args.logs, args.out)
    except (ReportError, OSError) as e:
        print(f"energyctl report: {e}", file=sys.stderr)
        return 2
    print(f"wrote {', '.join(res['figures'])} and summary.md to {res['out']}")
    return 0
