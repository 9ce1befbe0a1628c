"""energyctl log info / log recover: inspect any MCAP log we write, or rewrite a cut-off one."""

from __future__ import annotations

import argparse
import json
import sys

from clients.table import render
from schemas.scenario import ScenarioError


def add_parser(subparsers) -> argparse.ArgumentParser:
    lg = subparsers.add_parser("log", help="'info LOG.mcap': channels, counts, duration, drops, config; "
                                           "'recover BROKEN.mcap FIXED.mcap': rewrite a cut-off log with a summary")
    lg.description = ("'info' prints what a log holds: complete or truncated (and where), messages and bytes per "
                      "channel, duration, the recorder's drops, the config it ran with, and the loop delay measured "
                      "from its commands. 'recover' reads a log cut off by a killed writer record by record up to "
                      "its last complete chunk and writes every readable record into FIXED.mcap, complete and "
                      "indexed (with the attachments the log had: a cut-off log lost its tick index, so replay "
                      "reads its JSON channels). Both read any MCAP energyctl writes.")
    lg.add_argument("action", choices=["info", "recover"], help="info: describe LOG; recover: rewrite LOG whole")
    lg.add_argument("log", metavar="LOG.mcap", help="the log to read")
    lg.add_argument("fixed", nargs="?", metavar="FIXED.mcap", help="with recover: the file to write")
    lg.add_argument("--json", action="store_true", help="print the result as JSON")
    lg.set_defaults(func=run)
    return lg


def describe_loop_delay(ld: dict) -> str:
    """One line for a measured loop delay (service/core/delay.py), from status or a log."""
    d, comp = ld.get("measured_samples"), ld.get("compensated_samples")
    if d is None:
        return f"not measurable from {ld.get('window', 0)} ticks (commands too steady); compensating {comp}"
    flag = "  MISMATCH: set delay_samples to the measured value" if ld.get("mismatch") else ""
    return (f"measured {d} samples over {ld['window']} ticks (explains {ld['explained']:.0%} of the measured "
            f"du/dt, contrast {ld['contrast']:.2f}); compensating {comp}{flag}")


def print_info(res: dict) -> None:
    state = "complete" if res["complete"] else f"TRUNCATED ({res['truncated_at']})"
    print(f"{res['path']}: {state}, {res['messages']} messages over {res['duration_s']:.3f} s, "
          f"recorder drops {sum(res['drops'].values()) if res['drops'] else 0}"
          + "".join(f", {n} attachment(s) {name}" for name, n in res["attachments"].items()))
    print(render(["channel", "messages", "bytes"],
                 [[t, str(c["messages"]), str(c["bytes"])] for t, c in res["channels"].items()]))
    for name in ("config", "scenario", "core", "build"):
        if name in res:
            print(f"{name}: {json.dumps(res[name])[:400]}")
    if "loop_delay" in res:
        print(f"loop delay: {describe_loop_delay(res['loop_delay'])}")


def run(args: argparse.Namespace) -> int:
    from clients.logtools import info, recover

    try:
        if args.action == "info":
            res = info(args.log)
            if args.json:
                print(json.dumps(res))
            else:
                print_info(res)
        else:
            if not args.fixed:
                raise ScenarioError("log recover: give BROKEN.mcap FIXED.mcap")
            res = recover(args.log, args.fixed)
            print(f"recovered {res['messages']} messages into {res['to']}"
                  + ("" if not res["was_complete"] else " (the source was already complete)"))
    except BrokenPipeError:
        raise
    except OSError as e:
        print(f"energyctl log: {e}", file=sys.stderr)
        return 2
    return 0
