"""energyctl foxglove: a Foxglove WebSocket server showing running components live (clients/foxglove_bridge.py)."""

from __future__ import annotations

import argparse
import json
import sys

from clients.options import add_zenoh, zenoh_from_args


def add_parser(subparsers) -> argparse.ArgumentParser:
    fx = subparsers.add_parser(
        "foxglove", help="bridge running components to the Foxglove app (WebSocket): live plots, parameters",
        description="Serves running components to the Foxglove app over its WebSocket protocol (the foxglove-sdk "
                    "package: python3 -m pip install foxglove-sdk). For each component ID it subscribes on Zenoh to "
                    "PREFIX/ID/meas (PREFIX/PLANT/meas for ID:PLANT), PREFIX/ID/cmd and PREFIX/ID/z and logs them, "
                    "as JSON, on the channels PREFIX/ID/meas, PREFIX/ID/cmd and PREFIX/ID/z_out: the topics and JSON "
                    "Schemas of the daemon's MCAP log, so a layout made for a log also shows the live run (its "
                    "est, loop, z_in and events channels exist only in logs). Each channel passes at most "
                    "--rate-hz messages a second and counts the rest. The controller settings are Foxglove "
                    "parameters ID.controller.<key> (and ID.lifecycle); setting one sends it to PREFIX/ID/config/set, "
                    "and the app shows the value now in force, or the daemon's refusal naming the field as an error "
                    "status. Services ID/status, ID/config and ID/config/set answer with the daemon's JSON. Open "
                    "the app's Foxglove WebSocket connection at ws://HOST:PORT. Runs until Ctrl-C (SIGINT) or "
                    "SIGTERM, then prints its counters as JSON: messages received, logged, dropped by the rate "
                    "limit and invalid, per channel; parameter gets and sets, service calls. Exit 2 without the "
                    "foxglove-sdk package or when the port is taken, 3 when the Zenoh session cannot be opened.")
    fx.add_argument("--components", required=True, metavar="ID[:PLANT],...",
                    help="the components' ids, comma-separated; ID:PLANT when ID's plant publishes its measurements "
                         "under another id (the controller's plant_id)")
    fx.add_argument("--prefix", default="energyctl", help="key-expression prefix (default: %(default)s)")
    fx.add_argument("--host", default="127.0.0.1",
                    help="address the WebSocket server listens on (default: %(default)s; 0.0.0.0: every interface)")
    fx.add_argument("--port", type=int, default=8765, help="its TCP port (default: %(default)s; 0: a free one)")
    fx.add_argument("--rate-hz", type=float, default=1000.0,
                    help="at most this many messages a second on each channel, the rest dropped and counted "
                         "(default: %(default)s; 0: all)")
    add_zenoh(fx)
    fx.set_defaults(func=run)
    return fx


def run(args: argparse.Namespace) -> int:
    import threading

    from clients.foxglove_bridge import Bridge, parse_components
    from clients.live import install_stop_handlers

    try:
        components = parse_components(args.components)
    except ValueError as e:
        print(f"energyctl foxglove: --components: {e}", file=sys.stderr)
        return 2
    if args.rate_hz < 0:
        print("energyctl foxglove: --rate-hz: must be 0 (all) or more", file=sys.stderr)
        return 2
    try:
        import foxglove.websocket  # noqa: F401 - (a bare "foxglove" could be the layout directory)
    except ImportError:
        print("energyctl foxglove: needs the foxglove-sdk package: python3 -m pip install foxglove-sdk",
              file=sys.stderr)
        return 2
    stop = threading.Event()
    install_stop_handlers(stop)
    bridge = Bridge(zenoh_from_args(args), components, prefix=args.prefix, port=args.port, rate_hz=args.rate_hz,
                    host=args.host)
    try:
        bridge.start()
    except RuntimeError as e:  # the SDK's FoxgloveError, e.g. the port is taken
        print(f"energyctl foxglove: cannot serve on {args.host}:{args.port}: {e}", file=sys.stderr)
        return 2
    try:
        print(f"energyctl foxglove: serving {', '.join(bridge.ids)} on ws://{args.host}:{bridge.port} "
              f"(in the Foxglove app: open connection, Foxglove WebSocket; or {bridge.app_url()})",
              file=sys.stderr, flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        status = bridge.status()
        bridge.close()
    print(json.dumps(status))
    return 0
