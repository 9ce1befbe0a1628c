"""energyctl load: the neighbour load, publishing its interaction variable and forecasts on Zenoh."""

from __future__ import annotations

import argparse
import json

from clients.options import add_config_command

DESCRIPTION = """\
Runs the neighbour Sigma_2, a constant-power load following its profile: with PREFIX the config's prefix (default \
energyctl) and ID its id, it publishes its outgoing interaction variable on PREFIX/ID/z (P_l, its rate, their \
integrals, and the announced load range of the current window) and holds the liveliness token PREFIX/ID/alive. \
lockstep pacing answers each measurement of plant_id on PREFIX/PLANT/meas with one message stamped with its seq and \
time; realtime pacing publishes at rate_hz, stamped with the plant's newest time. It stops after duration_s or at \
SIGINT/SIGTERM and prints a JSON line: messages sent, its log, CPU use."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    ld = add_config_command(
        subparsers, "load", help="the neighbour load: publishes its interaction variable and forecasts",
        description=DESCRIPTION, model="LoadPeerConfig", file="LOAD.toml", example="load.value=2400",
        set_examples="--set load.value=2400 --set rate_hz=200", what="the load's")
    ld.set_defaults(func=run)
    return ld


def run(args: argparse.Namespace) -> int:
    from clients.live import start_process
    from clients.peers.load import run_load
    from schemas.component import LoadPeerConfig, load_config

    cfg = load_config(LoadPeerConfig, args.config, args.set)
    stop = start_process(cfg, "load")
    res = run_load(cfg, stop)
    print(json.dumps(res), flush=True)
    return 0
