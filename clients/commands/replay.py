"""energyctl replay: re-run a log's inputs through the core; 'identical' or the first divergence, or a what-if."""

from __future__ import annotations

import argparse
import json
import sys

from clients.commands.common import CONTROLLERS
from clients.options import add_core
from schemas.scenario import ScenarioError


def add_parser(subparsers) -> argparse.ArgumentParser:
    rp = subparsers.add_parser(
        "replay", help="re-run a log's inputs through the core; 'identical' or the first divergence",
        description="Feeds the logged measurements and incoming interaction variables through a core "
                    "rebuilt from the log's 'core' record, sample by sample (no clock), and compares "
                    "every command bit for bit: prints 'identical' (exit 0) or the first divergence "
                    "(exit 1). --set/--controller run a what-if into --out NEW.mcap. A coordinator's log "
                    "(energyctl coordinator --out) replays its allocations and plug-in verdicts through the layer "
                    "rebuilt from the scenario in it.")
    rp.add_argument("log", nargs="+", metavar="LOG.mcap", help="a log, or the parts of a rotated log in order")
    rp.add_argument("--set", action="append", metavar="controller.key=value")
    rp.add_argument("--controller", choices=CONTROLLERS)
    rp.add_argument("--out", metavar="NEW.mcap")
    rp.add_argument("--no-index", action="store_true",
                    help="read the JSON channels (what Foxglove shows) even where the log has a tick index")
    rp.add_argument("--json", action="store_true")
    rp.add_argument("--component", metavar="NAME", help="in a network log (energyctl sim NETWORK --out), the source to "
                                                       "replay")
    add_core(rp)
    rp.set_defaults(func=run)
    return rp


def run(args: argparse.Namespace) -> int:
    from service.replay import ReplayError, replay

    if (args.set or args.controller) and not args.out:
        raise ScenarioError("replay: a what-if (--set/--controller) needs --out NEW.mcap")
    from service.network.layer_replay import is_coordinator_log

    try:
        if len(args.log) == 1 and is_coordinator_log(args.log[0]):
            return replay_layer(args)
        res = replay(args.log, args.set, args.controller, args.out, progress=not args.json,
                     use_index=not args.no_index, impl=args.core,
                     component=args.component)
    except (ReplayError, OSError) as e:
        print(f"energyctl replay: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(res))
    elif args.out:
        print(f"what-if: {res['ticks']} ticks replayed into {res['out']} ({res['wall_s']:.2f} s)")
    elif res["identical"]:
        gap = res.get("stopped_at_gap")
        upto = (f"; compared up to t = {gap['start_s']:.6f} s only: the log was recovered and lost a corrupt chunk "
                f"there (byte {gap['offset']} of the original), after which the core's state is unknown" if gap else "")
        print(f"identical: {res['compared']} commands reproduced bit for bit "
              f"({res['ticks']} ticks, {res['wall_s']:.2f} s, {res['speed_x_realtime']:.1f}x real time, "
              f"read from {'the tick index' if 'index' in res['read_from'] else 'the JSON channels'}){upto}")
    else:
        d = res["first_divergence"]
        print(f"diverged at t = {d['t']:.6f} s (seq {d['seq']}): {d['field']} logged {d['logged']!r}, "
              f"replayed {d['replayed']!r}")
    return 0 if (res["identical"] or args.out) else 1


def replay_layer(args: argparse.Namespace) -> int:
    """A coordinator's log: its allocations, window messages and plug-in verdicts recomputed by the layer."""
    from service.network.layer_replay import replay_coordinator

    res = replay_coordinator(args.log[0], args.core)
    if args.json:
        print(json.dumps(res))
    elif res["identical"]:
        print(f"identical: {res['allocations']} allocations over {res['samples']} samples, {res['windows']} window "
              f"messages, {res['offers']} plug-in offers and {res['verdicts']} verdicts reproduced bit for bit "
              f"({res['gaps']} samples the coordinator skipped)")
    else:
        first = (res["mismatches"] or res["windows_differing"] or res["offers_differing"] or res["verdicts_differing"]
                 or [{}])[0]
        print(f"differs: {res['n_mismatches']} of {res['allocations']} allocations, {res['n_windows_differing']} of "
              f"{res['windows']} window messages, {len(res['offers_differing'])} offers, "
              f"{len(res['verdicts_differing'])} verdicts; first: {json.dumps(first)}")
    for note in res["notes"]:
        print(f"note: {note}")
    return 0 if res["identical"] else 1
