"""energyctl secure-profile: a router config with authentication and access control, and the credentials."""

from __future__ import annotations

import argparse
from pathlib import Path

from schemas.scenario import ScenarioError


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser(
        "secure-profile", help="write a router config with authentication and access control",
        description="Writes DIR/router.json5 (Zenoh user/password authentication and an ACL with "
                    "default deny: only the plant publishes measurements, only the controller "
                    "commands, only operators set config), DIR/credentials.txt and one "
                    "DIR/<user>.password per identity (mode 600). Existing passwords are kept. "
                    "Start the router with energyctl router --config DIR/router.json5; each process then "
                    "connects to it as a Zenoh client (zenoh.mode = \"client\", zenoh.connect) with its own "
                    "zenoh.user and zenoh.password_file, and energyctl query with --mode client --user "
                    "--password-file.")
    sp.add_argument("--out", required=True, metavar="DIR")
    sp.add_argument("--prefix", default="energyctl")
    sp.add_argument("--controller", action="append", metavar="ID", help="controller id = its user (default: source)")
    sp.add_argument("--plant", action="append", metavar="USER=CONTROLLER_ID",
                    help="plant user and the controller it serves (default: plant=<first controller>)")
    sp.add_argument("--load", action="append", metavar="ID", help="neighbour load id = its user (default: load)")
    sp.add_argument("--operator", action="append", metavar="USER", help="may set config (default: operator)")
    sp.add_argument("--monitor", action="append", metavar="USER", help="may only read (default: monitor)")
    sp.add_argument("--listen", action="append", metavar="ENDPOINT", help="default: tcp/127.0.0.1:7447")
    sp.add_argument("--tls", action="store_true",
                    help="mutual TLS on tls/ endpoints: also writes DIR/tls/ (a private CA, the router's and one "
                         "certificate per user, via the openssl command); credentials then cross the wire encrypted")
    sp.set_defaults(func=run)
    return sp


def run(args: argparse.Namespace) -> int:
    from clients.secure import write_profile

    plants = None
    if args.plant:
        bad = [p for p in args.plant if "=" not in p]
        if bad:
            raise ScenarioError(f"--plant: expected USER=CONTROLLER_ID, got {bad}")
        plants = dict(p.split("=", 1) for p in args.plant)
    paths = write_profile(args.out, args.prefix, args.controller, plants, args.load, args.operator, args.monitor,
                          args.listen, tls=args.tls)
    users = [u for u in paths if u not in ("router", "credentials", "tls")]
    print(f"wrote {paths['router']} (access control, default deny) and {paths['credentials']}")
    print(f"password files (mode 600) for: {', '.join(users)} in {Path(args.out)}")
    if args.tls:
        print(f"mutual TLS: CA, router and per-user certificates and keys (mode 600) in {paths['tls']}; a client "
              "sets zenoh.tls_root_ca, tls_certificate and tls_private_key and connects to tls/HOST:PORT")
    print(f"start the router:  energyctl router --config {paths['router']}")
    return 0
