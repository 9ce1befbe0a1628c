"""energyctl query: ask a running controller for its status or config, set config, read its interaction variable."""

from __future__ import annotations

import json
import time

from schemas.codec import DecodeError, Z
from schemas.component import ZenohConfig
from service.bus import key, open_session


class QueryError(RuntimeError):
    pass


def query(z: ZenohConfig, prefix: str, component: str, what: str, sets: list[str] | None = None,
          timeout_s: float = 2.0) -> dict:
    """Returns the component's JSON answer; raises QueryError with its reason otherwise."""
    session = open_session(z)
    try:
        if what == "interaction":
            return _interaction(session, prefix, component, timeout_s)
        return ask(session, prefix, component, what, sets, timeout_s)
    finally:
        session.close()


def ask(session, prefix: str, component: str, what: str, sets: list[str] | None = None,
        timeout_s: float = 2.0) -> dict:
    """One status/config query on an open session (``query`` opens and closes its own)."""
    if sets:
        what = "config/set"
    selector = key(prefix, component, what)
    payload = json.dumps({"set": sets}) if sets else None
    deadline = time.monotonic() + timeout_s
    while True:  # the route to a just-started peer can take a moment to appear
        replies = list(session.get(selector, payload=payload, timeout=max(0.2, deadline - time.monotonic())))
        if replies or time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    for r in replies:
        if r.ok is not None:
            return json.loads(r.ok.payload.to_bytes())
        raise QueryError(_err_text(r.err.payload.to_bytes()))
    raise QueryError(f"no answer from {selector} within {timeout_s:g} s (is the controller running and "
                     "reachable? see --connect; behind a router with access control, may this user ask it?)")


def _err_text(b: bytes) -> str:
    try:
        return json.loads(b).get("error", b.decode())
    except (ValueError, AttributeError):
        return b.decode(errors="replace")


def _interaction(session, prefix: str, component: str, timeout_s: float) -> dict:
    import zenoh

    sub = session.declare_subscriber(key(prefix, component, "z"), zenoh.handlers.RingChannel(1))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = sub.try_recv()
        if s is not None:
            try:
                return Z.to_dict(Z.decode(s.payload.to_bytes()))
            except DecodeError as e:
                raise QueryError(str(e)) from None
        time.sleep(0.005)
    raise QueryError(f"no interaction message on {key(prefix, component, 'z')} within {timeout_s:g} s")


def flatten(d: dict, prefix: str = "") -> list[tuple[str, str]]:
    rows = []
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            rows += flatten(v, name + ".")
        elif isinstance(v, float):
            rows.append((name, f"{v:.6g}"))
        else:
            rows.append((name, json.dumps(v) if isinstance(v, list) else str(v)))
    return rows
