"""energyctl: command-line entry point. Assembles the subcommands of clients/commands (each has --help)."""

from __future__ import annotations

import os
import sys

from clients.commands import COMMANDS
from clients.options import Parser
from schemas.scenario import ScenarioError
from service import __version__


def build_parser() -> Parser:
    p = Parser(
        prog="energyctl",
        description="Energy-space controller for a power-electronic voltage source feeding a DC bus "
                    "(Jaddivada & Ilic, distributed energy control). All quantities in SI units.")
    p.add_argument("--version", action="version", version=f"energyctl {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a program: started by another energyctl (clients.live.Processes), end with it
        from service.priority import die_with_parent_from_env

        die_with_parent_from_env()
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ScenarioError as e:
        print(f"energyctl: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. piped into head (a ConnectionError subclass: caught first); quiet at exit too
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except ConnectionError as e:
        print(f"energyctl: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("energyctl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
