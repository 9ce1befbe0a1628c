"""energyctl report: PNG figures like the paper's and a Markdown summary, from one log or two."""

from __future__ import annotations

import argparse
import sys


def add_parser(subparsers) -> argparse.ArgumentParser:
    re_ = subparsers.add_parser("report", help="PNG figures like the paper's and a Markdown summary (one log, or two)")
    re_.add_argument("logs", nargs="+", metavar="LOG.mcap")
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
