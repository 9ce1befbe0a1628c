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
                      "reads its JSON channels). A corrupt chunk (zstd error, CRC mismatch) is skipped and named "
                      "with its byte offset; the chunks after it are still read, and recover keeps every intact one. "
                      "Exit codes, info: 0 the log is whole, 1 it is cut off or has corrupt chunks (what is readable "
                      "is described), 2 not a log (empty, not MCAP, unreadable). recover: 0 every readable record "
                      "written (a cut-off tail is what a killed writer loses), 1 written but corrupt chunks dropped "
                      "(listed), 2 nothing written.")
    lg.add_argument("action", choices=["info", "recover"], help="info: describe LOG; recover: rewrite LOG whole")
    lg.add_argument("log", metavar="LOG.mcap", help="the log to read")
    lg.add_argument("fixed", nargs="?", metavar="FIXED.mcap", help="with recover: the file to write")
    lg.add_argument("--json", action="store_true", help="print the result as JSON")
    lg.set_defaults(func=run)
    return lg


def describe_loop_delay(ld: dict) -> str:
    """One line for a measured loop delay (service/core/delay.py), from status or a log."""
    d, comp = ld.get("measured_samples"), ld.get("compensated_samples")
    if d is None and ld.get("reason"):
        return ld["reason"]
    if d is None:
        return f"not measurable from {ld.get('window', 0)} ticks (commands too steady); compensating {comp}"
    flag = "  MISMATCH: set delay_samples to the measured value" if ld.get("mismatch") else ""
    return (f"measured {d} samples over {ld['window']} ticks (explains {ld['explained']:.0%} of the measured "
            f"du/dt, contrast {ld['contrast']:.2f}); compensating {comp}{flag}")


def print_info(res: dict) -> None:
    state = "complete" if res["complete"] and not res["truncated_at"] else f"TRUNCATED ({res['truncated_at']})"
    if res["damage"]:
        state += f", CORRUPT: {len(res['damage'])} unreadable chunk(s)/record(s) skipped"
    print(f"{res['path']}: {state}, {res['messages']} messages over {res['duration_s']:.3f} s, "
          f"recorder drops {sum(res['drops'].values()) if res['drops'] else 0}"
          + "".join(f", {n} attachment(s) {name}" for name, n in res["attachments"].items()))
    print(render(["channel", "messages", "bytes"],
                 [[t, str(c["messages"]), str(c["bytes"])] for t, c in res["channels"].items()]))
    for name in ("config", "scenario", "core", "build"):
        if name in res:
            print(f"{name}: {json.dumps(res[name])[:400]}")
    for d in res["damage"]:
        print(f"corrupt: {describe_damage(d)}")
    if "recovered" in res:
        r = res["recovered"]
        print(f"recovered from {r['from']}: " + ("; ".join(f"dropped {describe_damage(d)}" for d in r["dropped"])
                                                 or "no corrupt chunk dropped")
              + (f"; the original was {r['truncated_at']}" if r["truncated_at"] else ""))
    if res["undeclared"]:
        print(f"corrupt: {res['undeclared']} message(s) on channels declared only in a lost chunk")
    if "loop_delay" in res:
        print(f"loop delay: {describe_loop_delay(res['loop_delay'])}")


def describe_damage(d: dict) -> str:
    """One line for a corrupt chunk or record (service.logio.reader.Damage.as_dict)."""
    span = f", t {d['start_s']:.6f}..{d['end_s']:.6f} s" if d["start_s"] is not None else ""
    lost = "" if d["messages"] is None else f", {d['messages']} messages"
    return f"{d['what']} at byte {d['offset']} ({d['length']} bytes{span}{lost}): {d['reason']}"


def run(args: argparse.Namespace) -> int:
    from clients.logtools import info, recover
    from service.logio.reader import LogError

    try:
        if args.action == "info":
            res = info(args.log)
            if args.json:
                print(json.dumps(res))
            else:
                print_info(res)
            return 0 if res["intact"] else 1
        if not args.fixed:
            raise ScenarioError("log recover: give BROKEN.mcap FIXED.mcap")
        res = recover(args.log, args.fixed)
    except BrokenPipeError:
        raise
    except (OSError, LogError) as e:
        print(f"energyctl log: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(res))
        return 1 if res["dropped_messages"] or res["dropped"] else 0
    if res["whole"]:
        note = " (the source was already whole: nothing to recover)"
    elif res["lost_tail"]:
        note = f" (the source was {res['lost_tail']})"
    else:
        note = ""
    print(f"recovered {res['messages']} messages into {res['to']}{note}")
    for d in res["dropped"]:
        print(f"dropped {describe_damage(d)}", file=sys.stderr)
    if res["undeclared"]:
        print(f"dropped {res['undeclared']} message(s) on channels declared only in a lost chunk", file=sys.stderr)
    if res["dropped"] or res["undeclared"]:
        known = sum(d["messages"] or 0 for d in res["dropped"]) + res["undeclared"]
        unknown = any(d["messages"] is None for d in res["dropped"])
        print(f"energyctl log recover: {len(res['dropped'])} corrupt chunk(s)/record(s) dropped, {known} messages "
              f"lost{' (and an unknown number in records without a message index)' if unknown else ''}",
              file=sys.stderr)
        return 1
    return 0
