"""energyctl plant: the hardware-in-the-loop stand-in, the plant model as a Zenoh peer."""

from __future__ import annotations

import argparse
import json
import sys

from clients.options import add_config_command

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
    pl.set_defaults(func=run)
    return pl


def run(args: argparse.Namespace) -> int:
    from clients.live import start_process
    from clients.peers.plant import run_plant
    from schemas.component import PlantPeerConfig, load_config

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
