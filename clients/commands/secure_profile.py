"""energyctl secure-profile: a router config with authentication and access control, and the credentials."""

from __future__ import annotations

import argparse
from pathlib import Path

from clients.secure import LOCKSTEP_WAIT_BEFORE_DROP_US, WAIT_BEFORE_DROP_MAX_US
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
    net = sp.add_argument_group(
        "a live network (energyctl plant/coordinator/run --network)",
        "--network NET.toml: identities for the network's processes instead: one per source daemon (the source's "
        "name), the rig (--rig) and the coordinator (--coordinator), with rules for exactly the keys each uses, "
        "and the operators and monitors. Alone: one router for all (DIR/router.json5). With --host and --hub: one "
        "router per host (DIR/router-HOST.json5, mode 600: it holds that router's own password), each admitting "
        "its host's processes, linked hub-and-spoke (docs/across-hosts.md). Also DIR/client.json5 for every "
        "process's --zenoh-config (the link timing).")
    net.add_argument("--network", metavar="NET.toml", help="the network scenario every process reads")
    net.add_argument("--rig", default="rig", help="the rig's id (default: %(default)s)")
    net.add_argument("--coordinator", default="coordinator", help="the coordinator's id (default: %(default)s)")
    net.add_argument("--host", action="append", metavar="HOST=ID[,ID...]",
                     help="a host, and the processes (rig, coordinator, sources) that run there; its router admits "
                          "only them (and operators and monitors)")
    net.add_argument("--hub", metavar="HOST=ENDPOINT[,ENDPOINT]",
                     help="the host whose router the others connect to, and where it listens for them, e.g. "
                          "rig=tcp/10.0.0.1:7448")
    net.add_argument("--uplink-interface", metavar="IFACE",
                     help="the interface a spoke's link to the hub leaves on (e.g. eth0): the spoke then accepts "
                          "the hub's messages only over it")
    net.add_argument("--lease-ms", type=int, default=1000,
                     help="the routers' Zenoh link lease, ms: a link silent this long is closed (a cut between "
                          "hosts is seen within it); every process and router retries a lost link every quarter to "
                          "half of it (default: %(default)s; 0: Zenoh's defaults, a 10 s lease)")
    net.add_argument("--keep-alive", type=int, default=4,
                     help="keep-alive messages per lease on a quiet link (default: %(default)s)")
    net.add_argument("--wait-before-drop-us", type=int, metavar="US",
                     help="how long a sample or command waits for room in a full send queue before it is dropped, "
                          "in every router and process, us (0 to 1000000; default: Zenoh's 1000). A lockstep network "
                          "of many daemons across hosts needs more: demo --network --hosts uses "
                          f"{LOCKSTEP_WAIT_BEFORE_DROP_US} (docs/decisions/0044); realtime, a longer wait is a later "
                          "command instead of a missing one")
    sp.set_defaults(func=run)
    return sp


def run(args: argparse.Namespace) -> int:
    from clients.secure import write_profile

    if args.network is not None:
        return run_network(args)
    given = [o for o, v in (("--host", args.host), ("--hub", args.hub), ("--uplink-interface", args.uplink_interface))
             if v]
    if given:
        raise ScenarioError(f"{', '.join(given)}: only with --network NET.toml")

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


def run_network(args: argparse.Namespace) -> int:
    from clients.secure import write_network_profile
    from schemas.network import load_network

    single = [o for o, v in (("--controller", args.controller), ("--plant", args.plant), ("--load", args.load)) if v]
    if single:
        raise ScenarioError(f"{', '.join(single)}: not with --network (its identities come from the network)")
    if args.tls:
        raise ScenarioError("--tls: not with --network yet (its profile has user/password and access control; keep "
                            "the routers' network private)")
    if args.lease_ms < 0 or args.keep_alive < 1:
        raise ScenarioError("--lease-ms: 0 or more; --keep-alive: 1 or more")
    if args.wait_before_drop_us is not None and not 0 <= args.wait_before_drop_us <= WAIT_BEFORE_DROP_MAX_US:
        raise ScenarioError(f"--wait-before-drop-us: 0 to {WAIT_BEFORE_DROP_MAX_US}, got {args.wait_before_drop_us}")
    hosts = hub = hub_endpoints = None
    if args.host or args.hub:
        if not (args.host and args.hub):
            raise ScenarioError("--host and --hub go together (one router per host, linked to the hub's)")
        hosts = {}
        for h in args.host:
            name, eq, ids = h.partition("=")
            if not eq or not name:
                raise ScenarioError(f"--host: expected HOST=ID[,ID...], got {h!r}")
            hosts[name] = [i for i in ids.split(",") if i]
        hub, eq, eps = args.hub.partition("=")
        if not eq or not eps:
            raise ScenarioError(f"--hub: expected HOST=ENDPOINT, got {args.hub!r}")
        hub_endpoints = eps.split(",")
    net = load_network(args.network)
    lease = args.lease_ms or None
    paths = write_network_profile(args.out, net, args.prefix, args.rig, args.coordinator, args.operator,
                                  args.monitor, args.listen, hosts, hub, hub_endpoints, args.uplink_interface,
                                  lease_ms=lease, keep_alive=args.keep_alive if lease else None,
                                  wait_before_drop_us=args.wait_before_drop_us)
    routers = [p for k, p in paths.items() if k == "router" or k.startswith("router-")]
    users = [u for u in paths if u not in ("router", "credentials", "client") and not u.startswith("router-")]
    print(f"wrote {', '.join(str(p) for p in routers)} (access control, default deny) and {paths['credentials']}")
    print(f"password files (mode 600) for: {', '.join(users)} in {Path(args.out)}")
    print(f"every process: --mode client --connect ENDPOINT --user ID --password-file {Path(args.out)}/ID.password "
          f"--zenoh-config {paths['client']}")
    for p in routers:
        print(f"start a router:  energyctl router --config {p}")
    return 0
