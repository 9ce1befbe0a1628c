"""energyctl coordinator: the interconnection layer of a live network as a Zenoh service."""

from __future__ import annotations

import argparse
import json
import sys

from clients.options import add_core, add_scenario_set, add_zenoh

DESCRIPTION = """\
Runs the interconnection layer of a network scenario as a service. With PREFIX (--prefix, default energyctl), it \
reads the rig's sample on PREFIX/RIG/grid and publishes each source's window message on PREFIX/SOURCE/window at \
its first sample, at each window's end and at a breaker change (its share alpha_s, the v_ref it moves once per \
window to hold the buses at nominal, its breaker, its feasibility range Z^{r,in}); each source forms its P^{r,in} \
(its share of what the connected sources deliver) from the grid sample itself every sample. It answers \
PREFIX/ID/status (shares, windows, verdicts, who is connected) and PREFIX/ID/connect, the plug-in handshake: a \
source asks, the coordinator forecasts its Z^{r,out} for its share of the current window and has the rig close its \
breaker only if Z^{r,out} lies inside Z^{r,in}; a refusal carries the reason. A source whose liveliness token \
disappears is tripped (the rig opens its breaker, the others take its share). At start it resumes each source's \
v_ref from its daemon. Every process of the network reads the same scenario file. SIGINT/SIGTERM stop it; it \
prints its final status as JSON."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    co = subparsers.add_parser("coordinator", help="the interconnection layer of a live network (Zenoh service)",
                               description=DESCRIPTION)
    co.add_argument("network", metavar="NETWORK.toml", help="the network scenario (kind = \"network\")")
    add_scenario_set(co)
    co.add_argument("--id", default="coordinator", help="its id (default: %(default)s)")
    co.add_argument("--rig", default="rig", help="the rig's id (default: %(default)s)")
    co.add_argument("--prefix", default="energyctl", help="key-expression prefix (default: %(default)s)")
    co.add_argument("--realtime", action="store_true",
                    help="answer only the newest grid sample (a realtime rig); default: every sample in order "
                         "(lockstep)")
    co.add_argument("--out", metavar="FILE.mcap", help="its log: per sample what it saw and the shares, its windows, "
                                                       "verdicts and trips (energyctl replay FILE.mcap replays it)")
    co.add_argument("--no-trip-on-loss", action="store_true",
                    help="do not trip a source whose liveliness token disappears")
    add_core(co)
    add_zenoh(co)
    co.set_defaults(func=run)
    return co


def run(args: argparse.Namespace) -> int:
    from clients.live import start_process
    from clients.options import zenoh_from_args
    from schemas.netlive import CoordinatorConfig
    from schemas.network import load_network
    from service.daemon.coordinator import run_coordinator

    net = load_network(args.network, args.set)
    cfg = CoordinatorConfig(id=args.id, rig=args.rig, prefix=args.prefix, zenoh=zenoh_from_args(args),
                            lockstep=not args.realtime, out=args.out, trip_on_loss=not args.no_trip_on_loss)
    stop = start_process(cfg, "coordinator")
    try:
        status = run_coordinator(cfg, net, stop, args.core)
    except ValueError as e:
        print(f"energyctl coordinator: {e}", file=sys.stderr)
        return 2
    print(json.dumps(status), flush=True)
    return 1 if status.get("loop_ended_by_itself") else 0
