"""energyctl load: the neighbour load, publishing its interaction variable and forecasts on Zenoh."""

from __future__ import annotations

import argparse
import json

from clients.options import LazyText, add_config_set

DESCRIPTION = """\
Runs the neighbour Sigma_2, a constant-power load following its profile: with PREFIX the config's prefix (default \
energyctl) and ID its id, it publishes its outgoing interaction variable on PREFIX/ID/z (P_l, its rate, their \
integrals, and the announced load range of the current window) and holds the liveliness token PREFIX/ID/alive. \
lockstep pacing answers each measurement of plant_id on PREFIX/PLANT/meas with one message stamped with its seq and \
time; realtime pacing publishes at rate_hz, stamped with the plant's newest time. It stops after duration_s or at \
SIGINT/SIGTERM and prints a JSON line: messages sent, its log, CPU use."""


def epilog() -> str:
    """The keys of LOAD.toml, from the config model."""
    from clients.confighelp import config_epilog
    from schemas.component import LoadPeerConfig

    return config_epilog(LoadPeerConfig, "LOAD.toml", "load.value=2400")


def add_parser(subparsers) -> argparse.ArgumentParser:
    ld = subparsers.add_parser("load", help="the neighbour load: publishes its interaction variable and forecasts",
                               description=DESCRIPTION,
                               epilog=LazyText(epilog))
    ld.add_argument("--config", required=True, metavar="LOAD.toml",
                    help="the load's config (TOML; its keys are listed below)")
    add_config_set(ld, "--set load.value=2400 --set rate_hz=200")
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
