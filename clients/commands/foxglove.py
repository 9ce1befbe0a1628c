"""energyctl foxglove: a Foxglove WebSocket server showing running components live (clients/foxglove_bridge.py), or
playing recorded logs with Foxglove's playback controls (--log, clients/foxglove_playback.py)."""

from __future__ import annotations

import argparse
import json
import sys

from clients.options import add_zenoh, zenoh_from_args


def add_parser(subparsers) -> argparse.ArgumentParser:
    fx = subparsers.add_parser(
        "foxglove", help="bridge running components to the Foxglove app (WebSocket): live plots, parameters; "
                         "or play logs (--log)",
        description="Serves running components to the Foxglove app over its WebSocket protocol (the foxglove-sdk "
                    "package: python3 -m pip install foxglove-sdk). For each component ID it subscribes on Zenoh to "
                    "PREFIX/ID/meas (PREFIX/PLANT/meas for ID:PLANT), PREFIX/ID/cmd and PREFIX/ID/z and logs them, "
                    "as JSON, on the channels PREFIX/ID/meas, PREFIX/ID/cmd and PREFIX/ID/z_out: the topics and JSON "
                    "Schemas of the daemon's MCAP log, so a layout made for a log also shows the live run (its "
                    "est, loop, z_in and events channels exist only in logs). Each channel passes at most "
                    "--rate-hz messages a second and counts the rest. The controller settings are Foxglove "
                    "parameters ID.controller.<key> (and ID.lifecycle); setting one sends it to PREFIX/ID/config/set, "
                    "and the app shows the value now in force, or the daemon's refusal naming the field as an error "
                    "status. Services ID/status, ID/config and ID/config/set answer with the daemon's JSON. The "
                    "connection graph (the app's Topic Graph panel) shows every component under the prefix that "
                    "holds its liveliness token PREFIX/ID/alive, with the Zenoh keys it publishes (PREFIX/ID/z; a "
                    "controller also PREFIX/ID/cmd) and subscribes to (PREFIX/PLANT/meas, PREFIX/N/z of each "
                    "neighbour N named in its status), updated as tokens come and go. With --log instead of "
                    "--components it plays MCAP logs: their messages on their own topics and schemas, merged in "
                    "log-time order and paced by their log times, with the app's playback controls (play, pause, "
                    "seek, speed). Open the app's Foxglove WebSocket connection at ws://HOST:PORT. Runs until "
                    "Ctrl-C (SIGINT) or SIGTERM, then prints its counters as JSON: messages received, logged, "
                    "dropped by the rate limit and invalid, per channel; parameter gets and sets, service calls; "
                    "the live components (with --log: messages logged, requests, seeks). Exit 2 without the "
                    "foxglove-sdk package, when the port is taken or a log cannot be read, 3 when the Zenoh "
                    "session cannot be opened.")
    what = fx.add_mutually_exclusive_group(required=True)
    what.add_argument("--components", metavar="ID[:PLANT],...",
                      help="the components' ids, comma-separated; ID:PLANT when ID's plant publishes its "
                           "measurements under another id (the controller's plant_id)")
    what.add_argument("--log", nargs="+", metavar="LOG.mcap",
                      help="play these MCAP logs instead (one timeline, in log-time order); starts paused at the "
                           "start of the data")
    fx.add_argument("--prefix", default="energyctl", help="key-expression prefix (default: %(default)s)")
    fx.add_argument("--host", default="127.0.0.1",
                    help="address the WebSocket server listens on (default: %(default)s; 0.0.0.0: every interface)")
    fx.add_argument("--port", type=int, default=8765, help="its TCP port (default: %(default)s; 0: a free one)")
    fx.add_argument("--rate-hz", type=float, default=1000.0,
                    help="at most this many messages a second on each channel, the rest dropped and counted "
                         "(default: %(default)s; 0: all; not with --log, which sends every message)")
    fx.add_argument("--poll-s", type=float, default=1.0,
                    help="how often the configs of components whose parameters a client subscribes to are reread, "
                         "their changes published (default: %(default)s s)")
    fx.add_argument("--backlog", type=int, default=65536,
                    help="with --log: messages buffered for each client before the oldest are dropped "
                         "(default: %(default)s)")
    add_zenoh(fx)
    fx.set_defaults(func=run)
    return fx


def run(args: argparse.Namespace) -> int:
    import threading

    from clients.foxglove_bridge import Bridge, parse_components
    from clients.live import install_stop_handlers

    if args.log is None:
        try:
            components = parse_components(args.components)
        except ValueError as e:
            print(f"energyctl foxglove: --components: {e}", file=sys.stderr)
            return 2
    if args.rate_hz < 0:
        print("energyctl foxglove: --rate-hz: must be 0 (all) or more", file=sys.stderr)
        return 2
    if not args.poll_s > 0:
        print("energyctl foxglove: --poll-s: must be more than 0", file=sys.stderr)
        return 2
    if args.backlog < 1:
        print("energyctl foxglove: --backlog: must be 1 or more", file=sys.stderr)
        return 2
    try:
        import foxglove.websocket  # noqa: F401 - (a bare "foxglove" could be the layout directory)
    except ImportError:
        print("energyctl foxglove: needs the foxglove-sdk package: python3 -m pip install foxglove-sdk",
              file=sys.stderr)
        return 2
    stop = threading.Event()
    install_stop_handlers(stop)
    if args.log is not None:
        from clients.foxglove_playback import PlaybackError, Player

        player = Player(args.log, port=args.port, host=args.host, backlog=args.backlog)
        return _serve(player, args, stop, (PlaybackError,), lambda: (
            f"playing {len(args.log)} log(s), {len(player.channels)} channels, "
            f"{(player.end_ns - player.start_ns) / 1e9:.3f} s"))
    bridge = Bridge(zenoh_from_args(args), components, prefix=args.prefix, port=args.port, rate_hz=args.rate_hz,
                    host=args.host, poll_s=args.poll_s)
    return _serve(bridge, args, stop, (), lambda: f"serving {', '.join(bridge.ids)}")


def _serve(server, args: argparse.Namespace, stop, refused: tuple, what) -> int:
    """Start the bridge or the player, serve until SIGINT/SIGTERM, print its status JSON. refused: the errors
    that mean its input was wrong (exit 2, as a port that is taken does). A bridge whose thread failed stops and
    exits 1."""
    from service.daemon.failure import EXIT_FAILED

    try:
        server.start()
    except refused as e:
        print(f"energyctl foxglove: --log: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # the SDK's FoxgloveError, e.g. the port is taken
        print(f"energyctl foxglove: cannot serve on {args.host}:{args.port}: {e}", file=sys.stderr)
        return 2
    try:
        print(f"energyctl foxglove: {what()} on ws://{args.host}:{server.port} (in the Foxglove app: open "
              f"connection, Foxglove WebSocket; or {server.app_url()})", file=sys.stderr, flush=True)
        failure = getattr(server, "failure", None)  # the bridge's (service.daemon.failure): a thread of it ended
        while not stop.wait(0.5):
            if failure:
                break
    finally:
        status = server.status()
        server.close()
    print(json.dumps(status))
    if failure:
        print(f"energyctl foxglove: failed: {failure.reason}", file=sys.stderr, flush=True)
        return EXIT_FAILED
    return 0
