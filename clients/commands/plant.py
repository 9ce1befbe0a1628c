"""energyctl plant: the hardware-in-the-loop stand-in, the plant model as a Zenoh peer."""

from __future__ import annotations

import argparse
import json
import sys

from clients.options import add_config_command, add_core, add_zenoh

DESCRIPTION = """\
Runs the plant model (RLC source branch, constant-power load, sensor) as the controller's hardware: with PREFIX the \
config's prefix (default energyctl) and CONTROLLER its controller_id, it waits for the liveliness tokens \
PREFIX/CONTROLLER/alive (and those of the ids in wait_for), then publishes one measurement per sample on \
PREFIX/CONTROLLER/meas and applies the commands answering them from PREFIX/CONTROLLER/cmd; lockstep pacing waits for \
each sample's command (simulated time), realtime pacing samples on the wall clock from the controller's first answer \
on. After duration_s it prints the run's metrics, counters and latency (a table, or JSON with --json) and writes its \
trace to out if set; exit 1 if the controller or a peer is not up within 15 s."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    pl = add_config_command(
        subparsers, "plant", help="hardware-in-the-loop stand-in: the plant model as a Zenoh peer",
        description=DESCRIPTION, model="PlantPeerConfig", file="PLANT.toml", example="sensor.noise_v_V=0.05",
        set_examples="--set duration_s=10 --set sensor.noise_v_V=0.05", what="the plant's")
    pl.add_argument("--json", action="store_true", help="print the result as one JSON object instead of a table")
    net = pl.add_argument_group(
        "a whole network (--config NETWORK.toml, kind = \"network\")",
        "The network rig: every source's measurement on PREFIX/SOURCE/meas, every line end's interaction variable on "
        "PREFIX/LINE/z/NODE, the layer's sample on PREFIX/RIG/grid; each source's command from PREFIX/SOURCE/cmd, "
        "breaker commands from the query PREFIX/RIG/breaker; the scenario's trips and closes at their times. "
        "--set then overrides the scenario. It waits for the coordinator and the sources that run from the start.")
    net.add_argument("--pacing", choices=("lockstep", "realtime"), default="lockstep",
                     help="lockstep (default): sample k + 1 after every live source answered k; realtime: on the "
                          "wall clock")
    net.add_argument("--out", metavar="FILE.mcap", help="the rig's log (the network's true state and its events)")
    net.add_argument("--id", default="rig", help="the rig's id (default: %(default)s)")
    net.add_argument("--prefix", default="energyctl", help="key-expression prefix (default: %(default)s)")
    net.add_argument("--interaction-rate", type=float, default=1000.0, metavar="HZ",
                     help="how often the lines' and loads' interaction variables go out (for the sources' status and "
                          "logs; default %(default)s); lower it across hosts, where they are most of the traffic")
    net.add_argument("--wait-for", action="append", metavar="ID",
                     help="ids to wait for besides the sources (default: coordinator)")
    add_core(net)
    add_zenoh(net)
    pl.set_defaults(func=run)
    return pl


def run(args: argparse.Namespace) -> int:
    from clients.commands.common import is_network_file
    from clients.live import start_process
    from clients.peers.plant import run_plant
    from schemas.component import PlantPeerConfig, load_config

    if is_network_file(args.config):
        return run_network_rig(args)
    cfg = load_config(PlantPeerConfig, args.config, args.set)
    stop = start_process(cfg, "plant")
    try:
        res = run_plant(cfg, stop)
    except RuntimeError as e:
        print(f"energyctl plant: {e}", file=sys.stderr)
        return 1
    res.pop("trace")
    print(json.dumps(res) if args.json else plant_text(res), flush=True)
    return 0


def plant_text(res: dict) -> str:
    from clients.table import metrics_table

    lines = [metrics_table([(["plant", res["pacing"]], res["metrics"])], ["", "pacing"])]
    lines.append("counters: " + ", ".join(f"{k} {v}" for k, v in res["counters"].items()))
    if "latency_us" in res:
        lat = res["latency_us"]
        lines.append(f"measurement->command latency: p50 {lat['p50']:.0f} us, p99 {lat['p99']:.0f} us, "
                     f"max {lat['max']:.0f} us")
    return "\n".join(lines)


def run_network_rig(args: argparse.Namespace) -> int:
    from clients.live import start_process
    from clients.options import zenoh_from_args
    from clients.peers.netrig import NetworkRig
    from schemas.netlive import NetworkRigConfig
    from schemas.network import load_network

    net = load_network(args.config, args.set)
    cfg = NetworkRigConfig(id=args.id, prefix=args.prefix, zenoh=zenoh_from_args(args), pacing=args.pacing,
                           out=args.out, wait_for=args.wait_for or ["coordinator"],
                           interaction_rate_hz=args.interaction_rate)
    stop = start_process(cfg, "plant")
    try:
        res = NetworkRig(cfg, net, stop, args.core).run()
    except RuntimeError as e:
        print(f"energyctl plant: {e}", file=sys.stderr)
        return 1
    res.pop("result")
    if args.json:
        print(json.dumps(res), flush=True)
    else:
        from clients.table import network_tables

        print(network_tables(res["metrics"]), flush=True)
        print("counters: " + ", ".join(f"{k} {v}" for k, v in res["counters"].items()), flush=True)
    if res["failure"]:
        from service.daemon.failure import EXIT_FAILED

        print(f"energyctl plant: failed, sampling stopped: {res['failure']}", file=sys.stderr, flush=True)
        return EXIT_FAILED
    if res["metrics"].get("diverged"):
        print(f"energyctl plant: the network diverged: {res['metrics'].get('diverged_why') or ''}".rstrip(": "),
              file=sys.stderr, flush=True)
        return 1
    return 0
