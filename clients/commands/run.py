"""energyctl run: the controller daemon for one component, on Zenoh."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from clients.options import add_config_command, add_core, add_zenoh

DESCRIPTION = """\
Fixed-rate control loop for one component on Zenoh. With PREFIX the config's prefix (default energyctl) and ID its \
id, it reads the plant's measurements on PREFIX/PLANT/meas (PLANT: plant_id, default ID) and the interaction \
variables of its neighbours on PREFIX/NEIGHBOUR/z; it publishes one command per measurement on PREFIX/ID/cmd (du/dt \
for the sample's period and the plan for the one after) and its own interaction variable on PREFIX/ID/z; it holds \
the liveliness token PREFIX/ID/alive and answers queries (energyctl query) on PREFIX/ID/status (state, loop \
statistics, last sample and command, estimates, feasibility, neighbours, rejections), PREFIX/ID/config (get) and \
PREFIX/ID/config/set (a JSON {"set": ["controller.K_per_s=800", "lifecycle=inactive"]}; applied at the next tick). \
SIGINT/SIGTERM stop it within one period; it prints its loop statistics as JSON. Should its loop end by an \
unexpected exception, it holds u, publishes nothing more, withdraws its token, says why on stderr (and in the final \
status: state failed, failure) and exits 1."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    r = add_config_command(
        subparsers, "run", help="the controller daemon for one component (Zenoh)",
        description=DESCRIPTION, model="ComponentConfig", file="COMPONENT.toml", example="loop.rate_hz=2000",
        set_examples="--set controller.K_per_s=800 --set loop.rate_hz=2000", what="the component's")
    r.add_argument("--stats-out", metavar="FILE.json", help="write the final status JSON here on exit")
    for a in r._actions:  # --config or --network
        if a.dest == "config":
            a.required = False
            a.help += "; or --network and --source instead"
    net = r.add_argument_group(
        "a source of a live network (instead of --config)",
        "The daemon of one source of a network scenario: its controller, model error, rate and loop delay from the "
        "scenario, P^{r,in} = -alpha_s sum_k P_k formed by itself each sample from the rig's grid sample on "
        "PREFIX/RIG/grid (falling back when that is older than 10 ms of sample time), v_ref and Z^{r,in} from the "
        "coordinator's window message on PREFIX/SOURCE/window, the lines at its terminal as its neighbours, and "
        "the plug-in handshake with the coordinator while its breaker is open. --set then overrides the scenario.")
    net.add_argument("--network", metavar="NETWORK.toml", help="the network scenario (kind = \"network\")")
    net.add_argument("--source", metavar="NAME", help="which of its sources this daemon controls")
    net.add_argument("--prefix", default="energyctl", help="key-expression prefix (default: %(default)s)")
    net.add_argument("--realtime", action="store_true", help="a realtime rig: answer each sample as it comes "
                                                            "(default: lockstep, waiting for each grid sample)")
    net.add_argument("--log-dir", metavar="DIR", help="record to DIR/SOURCE-<UTC time>.mcap")
    net.add_argument("--connect-at", type=float, metavar="SECONDS",
                     help="ask to connect from this sample time on while its breaker is open (default: the time of "
                          "its connect event in the scenario; none: it asks only if the scenario has it connected "
                          "from the start and its first grid sample shows its breaker open, i.e. restarted after a "
                          "trip); 0: whenever its breaker is open")
    net.add_argument("--coordinator", default="coordinator", help="the coordinator's id (default: %(default)s)")
    net.add_argument("--rig", default="rig", help="the rig's id: its grid sample (default: %(default)s)")
    add_core(net)
    add_zenoh(net)
    r.set_defaults(func=run)
    return r


def run(args: argparse.Namespace) -> int:
    from schemas.component import ComponentConfig, load_config
    from schemas.scenario import ScenarioError

    if (args.config is None) == (args.network is None):
        raise ScenarioError("energyctl run: give --config COMPONENT.toml, or --network NETWORK.toml with --source")
    if args.network is not None:
        from clients.options import zenoh_from_args
        from schemas.netlive import source_component
        from schemas.network import load_network

        if not args.source:
            raise ScenarioError("energyctl run --network: --source NAME is required (which source this daemon is)")
        net = load_network(args.network, args.set)
        try:
            cfg = source_component(net, args.source, prefix=args.prefix, zenoh=zenoh_from_args(args),
                                   lockstep=not args.realtime, log_dir=args.log_dir, coordinator=args.coordinator,
                                   connect_at_s=args.connect_at, core=args.core, rig=args.rig)
        except ValueError as e:
            raise ScenarioError(f"--source: {e}") from None
        return run_daemon(cfg, args.stats_out)
    return run_daemon(load_config(ComponentConfig, args.config, args.set), args.stats_out)


def run_daemon(cfg, stats_out: str | None = None) -> int:
    """Open the daemon, run its loop thread until SIGINT/SIGTERM (or the loop ends), print its statistics; exit 1 if
    the loop failed (service.daemon.failure)."""
    from clients.live import start_process
    from service.daemon.daemon import Daemon
    from service.daemon.failure import EXIT_FAILED
    from service.daemon.netsource import NetworkSourceDaemon

    stop = start_process(cfg, "run")
    d = NetworkSourceDaemon(cfg) if cfg.network is not None else Daemon(cfg)
    d.open()
    loop = threading.Thread(target=d.run_loop, name="loop", daemon=True)
    loop.start()
    print(f"energyctl run: {cfg.id} active, {cfg.loop.rate_hz:g} Hz {cfg.loop.trigger} trigger "
          f"({'lockstep' if cfg.loop.lockstep else 'free-running'}), "
          + (f"source of network {cfg.network.network!r}, lines {cfg.network.lines}" if cfg.network is not None
             else f"neighbours {cfg.neighbours or 'none'}"),
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
    print(json.dumps({"id": cfg.id, "loop": status["loop"], "rejected": status["rejected"],
                      "state": status["state"], "failure": status["failure"],
                      "logging": status["logging"]}), flush=True)
    if d.failure:
        print(f"energyctl run: {cfg.id} failed, control stopped: {d.failure.reason}", file=sys.stderr, flush=True)
        return EXIT_FAILED
    return 0
