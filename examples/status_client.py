#!/usr/bin/env python3
"""Ask an energyctl controller for its status or config, or set config, written from docs/protocol.md alone.

    python examples/status_client.py --connect tcp/127.0.0.1:7447 status
    python examples/status_client.py --connect tcp/127.0.0.1:7447 config
    python examples/status_client.py --connect tcp/127.0.0.1:7447 set controller.K_per_s=1500 lifecycle=active

Prints the JSON answer on stdout (exit 0), or the controller's error text on stderr (exit 1: a refused query, e.g.
a set that failed validation; exit 2: no answer). Imports only zenoh and the standard library.
"""

import argparse
import json
import sys
import time

import zenoh


def open_session(endpoint: str) -> zenoh.Session:
    """A client session to the controller's endpoint: no listening, no scouting."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def ask(session: zenoh.Session, selector: str, payload: str | None, timeout_s: float) -> tuple[bool, str]:
    """(True, JSON text of the answer) or (False, the error text); retries while no route to the queryable exists
    yet (a just-opened session can ask before it has learnt of it)."""
    deadline = time.monotonic() + timeout_s
    while True:
        replies = list(session.get(selector, payload=payload, timeout=max(0.2, deadline - time.monotonic())))
        if replies or time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    for r in replies:
        if r.ok is not None:
            return True, r.ok.payload.to_bytes().decode()
        text = r.err.payload.to_bytes().decode(errors="replace")
        try:  # errors come as {"error": "..."}
            text = json.loads(text).get("error", text)
        except (ValueError, AttributeError):
            pass
        return False, text
    raise TimeoutError(f"no answer from {selector} within {timeout_s:g} s")


def main() -> int:
    a = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    a.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the controller's Zenoh endpoint")
    a.add_argument("--prefix", default="energyctl")
    a.add_argument("--id", default="source", help="the controller's component id")
    a.add_argument("--timeout", type=float, default=5.0, help="s")
    a.add_argument("what", choices=["status", "config", "set"], nargs="?", default="status")
    a.add_argument("sets", nargs="*", metavar="KEY=VALUE", help="with set: controller.X=value or lifecycle=...")
    args = a.parse_args()
    if (args.what == "set") != bool(args.sets):
        a.error("KEY=VALUE arguments go with 'set', and 'set' needs at least one")
    base = f"{args.prefix}/{args.id}"
    selector, payload = {"status": (f"{base}/status", None), "config": (f"{base}/config", None),
                         "set": (f"{base}/config/set", json.dumps({"set": args.sets}))}[args.what]
    try:
        session = open_session(args.connect)
    except zenoh.ZError as e:  # a client session needs its router or peer there: nothing answers
        print(f"status_client: cannot reach {args.connect}: {e}", file=sys.stderr)
        return 2
    try:
        ok, text = ask(session, selector, payload, args.timeout)
    except TimeoutError as e:
        print(f"status_client: {e}", file=sys.stderr)
        return 2
    finally:
        session.close()
    if not ok:
        print(f"status_client: {selector} refused: {text}", file=sys.stderr)
        return 1
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
