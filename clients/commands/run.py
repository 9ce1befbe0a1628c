"""energyctl run: the controller daemon for one component, on Zenoh."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from clients.options import add_config_command

DESCRIPTION = """\
Fixed-rate control loop for one component on Zenoh. With PREFIX the config's prefix (default energyctl) and ID its \
id, it reads the plant's measurements on PREFIX/PLANT/meas (PLANT: plant_id, default ID) and the interaction \
variables of its neighbours on PREFIX/NEIGHBOUR/z; it publishes one command per measurement on PREFIX/ID/cmd (du/dt \
for the sample's period and the plan for the one after) and its own interaction variable on PREFIX/ID/z; it holds \
the liveliness token PREFIX/ID/alive and answers queries (energyctl query) on PREFIX/ID/status (state, loop \
statistics, last sample and command, estimates, feasibility, neighbours, rejections), PREFIX/ID/config (get) and \
PREFIX/ID/config/set (a JSON {"set": ["controller.K_per_s=800", "lifecycle=inactive"]}; applied at the next tick). \
SIGINT/SIGTERM stop it within one period; it prints its loop statistics as JSON."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    r = add_config_command(
        subparsers, "run", help="the controller daemon for one component (Zenoh)",
        description=DESCRIPTION, model="ComponentConfig", file="COMPONENT.toml", example="loop.rate_hz=2000",
        set_examples="--set controller.K_per_s=800 --set loop.rate_hz=2000", what="the component's")
    r.add_argument("--stats-out", metavar="FILE.json", help="write the final status JSON here on exit")
    r.set_defaults(func=run)
    return r


def run(args: argparse.Namespace) -> int:
    from schemas.component import ComponentConfig, load_config

    return run_daemon(load_config(ComponentConfig, args.config, args.set), args.stats_out)


def run_daemon(cfg, stats_out: str | None = None) -> int:
    """Open the daemon, run its loop thread until SIGINT/SIGTERM (or the loop ends), print its statistics."""
    from clients.live import start_process
    from service.daemon.daemon import Daemon

    stop = start_process(cfg, "run")
    d = Daemon(cfg)
    d.open()
    loop = threading.Thread(target=d.run_loop, name="loop", daemon=True)
    loop.start()
    print(f"energyctl run: {cfg.id} active, {cfg.loop.rate_hz:g} Hz {cfg.loop.trigger} trigger "
          f"({'lockstep' if cfg.loop.lockstep else 'free-running'}), neighbours {cfg.neighbours or 'none'}",
          file=sys.stderr, flush=True)
    warned = False
    while not stop.is_set() and loop.is_alive():
        stop.wait(0.05)
        if not warned and d.recorder is not None and d.recorder.failed:
            warned = True  # once: control goes on without the log
            print(f"energyctl run: logging degraded, control continues: {d.recorder.error}", file=sys.stderr,
                  flush=True)
    d.stop()
    loop.join(timeout=1.0)
    d.close()
    status = d.status()
    if stats_out:
        Path(stats_out).write_text(json.dumps(status))
    print(json.dumps({"id": cfg.id, "loop": status["loop"], "rejected": status["rejected"]}), flush=True)
    return 0
