"""energyctl router: a Zenoh router in this process (for the secure profile; no zenohd needed)."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    ro = subparsers.add_parser(
        "router", help="a Zenoh router in this process (for the secure profile; no zenohd needed)",
        description="Runs a Zenoh router until SIGINT/SIGTERM. With --config, a Zenoh JSON5 file "
                    "such as the one 'energyctl secure-profile' writes (user/password authentication "
                    "and an access-control list); a relative credentials dictionary is read from that "
                    "file's directory. Multicast scouting stays off. Refused logins and access-control denials "
                    "are logged to stderr from Zenoh's own log (repeats summarised every 10 s) and counted; the "
                    "counts are answered on PREFIX/ID/status (docs/operations.md).")
    ro.add_argument("--config", metavar="ROUTER.json5")
    ro.add_argument("--listen", action="append", metavar="ENDPOINT", help="replaces the file's listen endpoints")
    ro.add_argument("--id", default="router", help="the router's id: its counts are answered on PREFIX/ID/status "
                                                   "(default router)")
    ro.add_argument("--prefix", default="energyctl", help="key prefix (default energyctl)")
    ro.add_argument("--no-audit", action="store_true",
                    help="do not turn on Zenoh's refusal logging (it writes a line per routed message that this "
                         "process reads and drops: docs/decisions/0041-router-refusal-log.md)")
    ro.set_defaults(func=run)
    return ro


def run(args: argparse.Namespace) -> int:
    from clients.secure import run_router

    return run_router(args.config, args.listen or [], audit=not args.no_audit,
                      status_key=f"{args.prefix}/{args.id}/status")
