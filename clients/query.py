"""energyctl query: ask a running controller for its status or config, set config, read its interaction variable."""

from __future__ import annotations

import json
import re
import time

from schemas.codec import DecodeError, Z
from schemas.component import ZenohConfig
from schemas.messages import Command, Estimate, Interaction, Measurement
from service.daemon.bus import close_session, key, open_session

# s: a query's session gives up a link's handshake after this (Zenoh's 10 s made `energyctl query` take 9.5 s more
# to exit while a stopped peer was connected: its close waited for the dial to it)
QUERY_OPEN_TIMEOUT_S = 2.0


class QueryError(RuntimeError):
    pass


def query(z: ZenohConfig, prefix: str, component: str, what: str, sets: list[str] | None = None,
          timeout_s: float = 2.0) -> dict:
    """Returns the component's JSON answer; raises QueryError with its reason otherwise."""
    session = query_session(z)
    try:
        if what == "interaction":
            return _interaction(session, prefix, component, timeout_s)
        return ask(session, prefix, component, what, sets, timeout_s)
    finally:
        close_session(session)


def query_session(z: ZenohConfig):
    """A one-shot query's Zenoh session: its links' handshakes (and so its close, beside a peer that stopped
    reading) bounded by QUERY_OPEN_TIMEOUT_S unless the config sets zenoh.open_timeout_s."""
    if z.open_timeout_s is None:
        z = z.model_copy(update={"open_timeout_s": QUERY_OPEN_TIMEOUT_S})
    return open_session(z)


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


_UNIT = re.compile(r"(?:^|,\s*)([A-Za-z%µ][A-Za-z0-9/^%µ]*)\s*(?::|$)")


def _model_units(model) -> dict[str, str]:
    """Field -> unit from a message model's descriptions: "..., W", "..., V/s: more" or just "W/s"."""
    out = {}
    for name, f in model.model_fields.items():
        d = (f.description or "").strip()
        m = _UNIT.search(d)
        if m and (m.start() > 0 or m.group(1) == d.split(":")[0].strip()):
            out[name] = m.group(1)
    return out


# status sections whose fields are a message model's (units from its descriptions); the rest by name
_SECTION_UNITS = {"last_sample": _model_units(Measurement), "last_command": _model_units(Command),
                  "estimate": {**_model_units(Estimate), "P_r_out_port": "W", "Qdot_r_out_port": "W/s"}}
_LEAF_UNITS = {**_model_units(Interaction), **_model_units(Estimate), "P": "W", "P_dot": "W/s", "Qdot": "W/s",
               "v_range": "V", "u_range": "V", "z_out": "J, W"}
_SUFFIX_UNITS = (("_V_per_s", "V/s"), ("_W_per_s", "W/s"), ("_per_s", "1/s"), ("_us", "µs"), ("_ms", "ms"),
                 ("_s", "s"), ("_pct", "%"), ("_hz", "Hz"), ("_V", "V"), ("_A", "A"), ("_W", "W"), ("_J", "J"),
                 ("_ohm", "Ω"), ("_H", "H"), ("_F", "F"), ("_S", "S"))  # longest first


def unit_of(name: str) -> str:
    """The unit of a flattened status field (``loop.exec_us.p99``, ``estimate.eta``, ``neighbours.load.age_s``),
    '' when it has none (counts, states, flags)."""
    parts = name.split(".")
    if len(parts) == 2 and parts[0] in _SECTION_UNITS:
        return _SECTION_UNITS[parts[0]].get(parts[1], "")
    for part in reversed(parts):
        if part in _LEAF_UNITS and not (part == "t" and len(parts) > 2):
            return _LEAF_UNITS[part]
        for suffix, unit in _SUFFIX_UNITS:
            if part.endswith(suffix):
                return unit
    return ""
