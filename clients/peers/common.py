"""What the plant and load stand-ins share: waiting for their peers on the bus."""

from __future__ import annotations

import threading
import time


def wait_alive(session, key_expr: str, timeout_s: float, stop: threading.Event) -> bool:
    """Block until a liveliness token matching key_expr exists (or timeout / stop)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop.is_set():
        for r in session.liveliness().get(key_expr, timeout=0.5):
            if r.ok is not None:
                return True
        stop.wait(0.05)
    return False


def matched(pub, timeout_s: float, stop: threading.Event) -> bool:
    """Block until the publisher's puts are routed to a subscriber.

    A peer's liveliness token can be seen here before its subscription is routed (a peer answers a liveliness
    query from what it already knows); a sample published before then goes nowhere. (The realtime arm on the
    first answer, in the plant's PlantRig, is what made sample 0 reliably answered; this only rules out the race.)"""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop.is_set():
        if pub.matching_status.matching:
            return True
        stop.wait(0.01)
    return False
