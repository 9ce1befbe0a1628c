"""energyctl router: a Zenoh router in this process (for the secure profile; no zenohd needed)."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    ro = subparsers.add_parser(
        "router", help="a Zenoh router in this process (for the secure profile; no zenohd needed)",
        description="Runs a Zenoh router until SIGINT/SIGTERM. With --config, a Zenoh JSON5 file "
                    "such as the one 'energyctl secure-profile' writes (user/password authentication "
                    "and an access-control list); a relative credentials dictionary is read from that "
                    "file's directory. Multicast scouting stays off.")
    ro.add_argument("--config", metavar="ROUTER.json5")
    ro.add_argument("--listen", action="append", metavar="ENDPOINT", help="replaces the file's listen endpoints")
    ro.set_defaults(func=run)
    return ro


def run(args: argparse.Namespace) -> int:
    from clients.secure import run_router

    return run_router(args.config, args.listen or [])
