"""schemas/json: current with the generator, the documented wire layout the real one, the replies the real ones."""

from __future__ import annotations

import copy
import importlib
import json
import re
import struct
import threading
import time
from collections import deque
from pathlib import Path
from types import SimpleNamespace

import pytest
from pydantic import BaseModel

from schemas.codec import BY_MODEL, MEAS, Z
from schemas.component import ComponentConfig
from schemas.generate import all_schemas, stale_schemas, write_schemas
from schemas.messages import MESSAGE_MODELS
from schemas.replies import (
    ConfigReply,
    ConfigSetApplied,
    ConfigSetReply,
    ConfigSetRequest,
    ErrorReply,
    StatusReply,
)

JSON_DIR = Path(__file__).resolve().parents[2] / "schemas" / "json"
HINT = "stale: run  energyctl schema --out schemas/json  (schemas.generate.write_schemas)"


def committed(name: str) -> dict:
    return json.loads((JSON_DIR / f"{name}.json").read_text(encoding="utf-8"))


# ---------------------------------------------------------------- (a) the files are the generator's output


def test_schemas_json_is_what_the_generator_writes_now():
    assert stale_schemas(JSON_DIR) == [], HINT


def test_the_staleness_check_catches_a_change_a_reordering_a_missing_and_an_extra_file(tmp_path):
    gen = all_schemas()
    assert stale_schemas(JSON_DIR, gen) == []

    changed = copy.deepcopy(gen)
    changed["energyctl.Command"]["properties"]["limited"]["x-wire-offset"] += 1
    assert stale_schemas(JSON_DIR, changed) == ["energyctl.Command.json: stale"]

    reordered = copy.deepcopy(gen)  # the same dict (== holds), another property order: still stale
    props = reordered["energyctl.Measurement"]["properties"]
    reordered["energyctl.Measurement"]["properties"] = dict(reversed(list(props.items())))
    assert reordered == gen
    assert stale_schemas(JSON_DIR, reordered) == ["energyctl.Measurement.json: stale"]

    described = copy.deepcopy(gen)
    described["energyctl.StatusReply"]["$defs"]["LoopStatus"]["properties"]["cpu_pct"]["description"] += "!"
    assert stale_schemas(JSON_DIR, described) == ["energyctl.StatusReply.json: stale"]

    more = {**gen, "energyctl.Extra": {"type": "object"}}
    assert stale_schemas(JSON_DIR, more) == ["energyctl.Extra.json: missing"]

    write_schemas(tmp_path)
    assert stale_schemas(tmp_path) == []
    (tmp_path / "energyctl.ConfigReply.json").unlink()
    (tmp_path / "energyctl.Old.json").write_text("{}\n")
    assert stale_schemas(tmp_path) == ["energyctl.ConfigReply.json: missing", "energyctl.Old.json: not generated"]


def test_every_message_config_and_reply_has_its_file():
    names = {p.stem for p in JSON_DIR.glob("*.json")}
    assert set(MESSAGE_MODELS) <= names
    assert {"energyctl.ComponentConfig", "energyctl.PlantPeerConfig", "energyctl.LoadPeerConfig",
            "energyctl.Scenario", "energyctl.StatusReply", "energyctl.ConfigReply", "energyctl.ConfigSetRequest",
            "energyctl.ConfigSetReply"} <= names


# ---------------------------------------------------------------- (b) the documented layout is the real one

# how an outsider reads x-wire-type and x-endianness (on purpose not taken from schemas.codec)
STRUCT_CODE = {"u8": "B", "bool/u8": "B", "u64": "Q", "f64": "d"}
ORDER = {"little": "<", "big": ">"}


def _values(model: type[BaseModel], salt: int) -> BaseModel:
    """An instance whose fields all differ: ints above 2^32, floats not integral (negative unless the field's
    documented range starts at 0), bools both ways."""
    props = model.model_json_schema()["properties"]
    vals = {}
    for k, (name, f) in enumerate(model.model_fields.items()):
        if f.annotation is bool:
            vals[name] = (k + salt) % 2 == 0
        elif f.annotation is int:
            vals[name] = (1 << 33) + 1000 * salt + k
        elif "maximum" in props[name]:  # a bounded fraction (alpha): inside its range, not integral
            lo, hi = props[name].get("minimum", 0.0), props[name]["maximum"]
            vals[name] = lo + (hi - lo) * (k + 1 + salt / 7.0) / (k + 3 + salt)
        else:
            vals[name] = (1 if props[name].get("minimum") == 0 else -1) * (1234.5678 * (k + 1) + salt / 7.0)
    return model(**vals)


@pytest.mark.parametrize("name", [n for n, m in MESSAGE_MODELS.items() if m in BY_MODEL])
def test_the_documented_wire_layout_reads_back_what_the_codec_packs(name):
    model, codec = MESSAGE_MODELS[name], BY_MODEL[MESSAGE_MODELS[name]]
    sch = committed(name)
    props = sch["properties"]
    assert list(props) == sch["x-wire-order"] == list(model.model_fields)
    order = ORDER[sch["x-endianness"]]
    header = {h["name"]: h for h in sch["x-wire-header"]}
    assert set(header) == {"magic", "version"}

    # the documented pieces tile the payload: no gap, no overlap, the stated size
    pieces = sorted([(h["x-wire-offset"], h["x-wire-type"]) for h in header.values()]
                    + [(p["x-wire-offset"], p["x-wire-type"]) for p in props.values()])
    pos = 0
    for off, typ in pieces:
        assert off == pos, f"{name}: gap or overlap at byte {pos}"
        pos += struct.calcsize(order + STRUCT_CODE[typ])
    assert pos == sch["x-size-bytes"]
    offsets = [props[f]["x-wire-offset"] for f in sch["x-wire-order"]]
    assert offsets == sorted(offsets)

    magic = int(sch["x-magic"]["hex"], 16)
    ascii_ = sch["x-magic"]["ascii"]
    assert ascii_ is None or ascii_.encode("ascii") == bytes([magic])
    for salt in (1, 2):
        msg = _values(model, salt)
        payload = codec.encode(*(getattr(msg, f) for f in codec.fields))
        assert len(payload) == sch["x-size-bytes"]

        def read(entry, payload=payload):
            return struct.unpack_from(order + STRUCT_CODE[entry["x-wire-type"]], payload, entry["x-wire-offset"])[0]

        assert read(header["magic"]) == magic
        assert read(header["version"]) == sch["x-version"]
        for f, p in props.items():
            got = read(p)
            if p["x-wire-type"] == "bool/u8":
                assert got in (0, 1) and bool(got) == getattr(msg, f), f
            else:
                assert got == getattr(msg, f), f
        # and the other way: bytes laid out from the schema alone are what the codec decodes
        buf = bytearray(sch["x-size-bytes"])
        struct.pack_into(order + "B", buf, header["magic"]["x-wire-offset"], magic)
        struct.pack_into(order + "B", buf, header["version"]["x-wire-offset"], sch["x-version"])
        for f, p in props.items():
            struct.pack_into(order + STRUCT_CODE[p["x-wire-type"]], buf, p["x-wire-offset"], getattr(msg, f))
        assert bytes(buf) == payload
        assert codec.to_dict(codec.decode(bytes(buf))) == msg.model_dump()


def test_a_message_without_a_binary_form_states_no_layout():
    for name, model in MESSAGE_MODELS.items():
        has = any(k.startswith("x-wire") or k == "x-magic" for k in committed(name))
        assert has == (model in BY_MODEL), name
    assert set(BY_MODEL) <= set(MESSAGE_MODELS.values())


# ---------------------------------------------------------------- units in the config and reply schemas

UNIT_SUFFIX = (("_V_per_s", "V/s"), ("_W_per_s", "W/s"), ("_per_s", "1/s"), ("_hz", "Hz"), ("_ns", "ns"),
               ("_us", "µs"), ("_ms", "ms"), ("_s", "s"), ("_pct", "%"), ("_V", "V"), ("_A", "A"), ("_W", "W"),
               ("_J", "J"), ("_ohm", "Ω"), ("_H", "H"), ("_F", "F"), ("_S", "S"), ("_rad", "rad"),
               ("_bytes", "bytes"), ("_samples", "samples"))  # longest first


def _objects(schema: dict):
    yield schema
    yield from schema.get("$defs", {}).values()


@pytest.mark.parametrize("name", ["energyctl.ComponentConfig", "energyctl.PlantPeerConfig", "energyctl.LoadPeerConfig",
                                  "energyctl.Scenario", "energyctl.StatusReply", "energyctl.ConfigReply",
                                  "energyctl.ConfigSetRequest", "energyctl.ConfigSetReply"])
def test_every_field_is_described_and_the_description_names_its_unit(name):
    missing = []
    for obj in _objects(committed(name)):
        for field, p in obj.get("properties", {}).items():
            d = p.get("description", "")
            if not d and "$ref" not in p:  # a nested model is described by its own schema
                missing.append(f"{obj['title']}.{field}: no description")
            unit = next((u for suffix, u in UNIT_SUFFIX if field.endswith(suffix)), None)
            if unit and not re.search(r"(?<![\w/^])" + re.escape(unit) + r"(?![\w/^])", d):
                missing.append(f"{obj['title']}.{field}: unit {unit} not in {d!r}")
    assert missing == []


# ---------------------------------------------------------------- (c) the daemon's real replies validate


def _daemon_module():
    """The module with class Daemon (service/daemon/daemon.py; service/daemon.py before the reorganisation)."""
    for mod in ("service.daemon.daemon", "service.daemon"):
        try:
            m = importlib.import_module(mod)
        except ImportError:
            continue
        if hasattr(m, "Daemon"):
            return m
    pytest.fail("no Daemon class in service.daemon.daemon or service.daemon")


class _Pub:
    def __init__(self):
        self.sent: list[bytes] = []

    def put(self, b: bytes) -> None:
        self.sent.append(b)


class _Sub:
    """A neighbour subscriber that hands out queued payloads (try_recv, as the ring-of-one channel does)."""

    def __init__(self):
        self.q: deque = deque()

    def try_recv(self):
        return SimpleNamespace(payload=_payload(self.q.popleft())) if self.q else None


def _payload(b: bytes):
    return SimpleNamespace(to_bytes=lambda: b)


def _query(payload: dict | None = None, parameters: str = ""):
    """A query as the handlers read it: its payload (None: a get without one) and its parameters."""
    return SimpleNamespace(payload=None if payload is None else _payload(json.dumps(payload).encode()),
                           parameters=parameters)


def _wire(body: dict) -> dict:
    """What the querier gets: the daemon's json.dumps, parsed."""
    return json.loads(json.dumps(body))


@pytest.fixture(scope="module")
def daemon_replies():
    """Status, config and config/set answers from the real Daemon, driven without a Zenoh session: its tick, its
    status and query handlers, with a recording publisher, a neighbour's messages fed to its subscriber, and the
    forecast and recorder parts set as the running daemon has them."""
    mod = _daemon_module()
    cfg = ComponentConfig(id="source", neighbours=["load"], local_reference_W=None)
    d = mod.Daemon(cfg)
    sub = _Sub()
    nb = mod.Neighbour("load", sub)
    d.neighbours, d._by_id, d.cmd_pub, d.z_pub = [nb], {"load": nb}, _Pub(), _Pub()
    out = {"status": [_wire(d.status())]}  # configured: nothing heard yet

    d.state = "active"  # what open() ends with
    T = d.period_s
    prev = time.monotonic_ns()
    for k in range(300):
        t = k * T
        # the load: 1200 W, announcing a box that leaves the component's actual rates outside its range
        sub.q.append(Z.encode(k + 1, t, 1200.0, 0.0, 0.0, 1200.0 * t, 0.0, 0, 0.0, 10.0, -1.0, 1.0))
        if k == 150:
            sub.q.append(b"\x21\x01 too short")  # a malformed neighbour message: rejected, counted
        v = 5000.0 if k == 200 else 80.0  # one out-of-range sample: held (du/dt = 0), counted
        now = time.monotonic_ns()
        d._tick(MEAS.encode(k, t, 15.0, v, 80.0 + 0.01 * 15.0, 15.0), now)
        end = time.monotonic_ns()
        d.stats.record(now - prev if k else 0, end - now, d.put_ns, d.control_ns)
        prev = now
    assert d.cmd_pub.sent and d.z_pub.sent and d.rejected and d.feas.count
    # status reuses its loop-time distributions for 250 ms and its loop-delay estimate for 1 s: compute them anew
    d.stats._dist = d._loop_delay_cache = None
    out["status"].append(_wire(d.status()))

    # the forecast worker (not started: status reads its counters and newest result) and a running recorder
    d.forecaster = mod.ForecastWorker(cfg.model, d.period_s, d.core.d, cfg.forecast, cfg.forecast_window_s)
    out["status"].append(_wire(d.status()))  # no result yet
    d.forecaster.result = (1, SimpleNamespace(
        P_lo=-1250.0, P_hi=-1150.0, P_dot_lo=-10.0, P_dot_hi=10.0, Qdot_lo=-50.0, Qdot_hi=50.0,
        z_in=(-10.0, 0.0, -1.0, 1.0), v_lo=79.0, v_hi=81.0, u_lo=79.5, u_hi=81.5, limited_ticks=0,
        feasible=False, reason="P^{r,out} outside Z^{r,in}"))
    d.forecaster.computed, d.forecaster.last_ms = 1, 12.345
    d._degrade("meas: stale")
    d.log_path = "logs/source-20260101T000000.000000Z.mcap"
    d.recorder = SimpleNamespace(written=1234, drops={"energyctl/source/est": 2}, failed=False, error=None)
    out["status"].append(_wire(d.status()))
    d.recorder, d.log_error = None, "recorder could not start: [Errno 28] No space left on device"
    d.state = "shutdown"
    out["status"].append(_wire(d.status()))
    d.state = "active"

    ok, body = d._config_reply(_query())
    assert ok
    out["config"] = _wire(body)
    ok, body = d._config_reply(_query({"set": ["controller.K_per_s=3000"]}))
    assert not ok
    out["config_error"] = _wire(body)

    out["set_errors"] = []
    for req in ({"set": ["controller.K_per_s=-1"]}, {"set": ["controller.limits.u_min_V=300"]},
                {"set": ["loop.rate_hz=2000"]}, {"set": []}, {"set": ["lifecycle=paused"]},
                {"set": ["controller.kind=smc"]}):
        ok, body = d._config_set_reply(_query(req))
        assert not ok, req
        out["set_errors"].append((req, _wire(body)))

    req = {"set": ["controller.K_per_s=3000", "controller.limits.du_dt_max_V_per_s=1e5", "lifecycle=inactive"]}
    answer = {}
    th = threading.Thread(target=lambda: answer.update(r=d._config_set_reply(_query(req))))
    th.start()
    while th.is_alive():  # the loop's part: apply the pending change between two ticks
        if d._pending is not None or d._pending_state is not None:
            d._apply_pending()
        time.sleep(1e-4)
    th.join()
    ok, body = answer["r"]
    assert ok and d.state == "inactive" and d.config_version == 1
    out["set_request"], out["set_ok"] = req, _wire(body)
    return out


def _fields_seen(obj, seen: dict) -> None:
    """Every key of every model instance in a validated reply, by model class."""
    if isinstance(obj, BaseModel):
        seen.setdefault(type(obj), set()).update(obj.model_fields_set)
        for f in obj.model_fields_set:
            _fields_seen(getattr(obj, f), seen)
    elif isinstance(obj, dict):
        for v in obj.values():
            _fields_seen(v, seen)
    elif isinstance(obj, list | tuple):
        for v in obj:
            _fields_seen(v, seen)


def test_the_daemons_status_replies_validate_and_use_every_modelled_key(daemon_replies):
    seen: dict = {}
    for s in daemon_replies["status"]:
        _fields_seen(StatusReply.model_validate(s), seen)  # extra keys are forbidden: a new one fails here
    first, ticked = (StatusReply.model_validate(s) for s in daemon_replies["status"][:2])
    assert first.last_sample is None and first.loop.exec_us is None and first.loop_delay.explained is None
    assert ticked.loop.exec_us is not None and ticked.neighbours["load"].messages > 0
    assert ticked.feasibility.recent and ticked.rejected
    for model, keys in seen.items():
        if model.__module__ == "schemas.replies":
            assert keys == set(model.model_fields), f"{model.__name__}: never emitted {set(model.model_fields) - keys}"
    assert {m.__name__ for m in seen} >= {"StatusReply", "LoopStatus", "TimeDistribution", "StatusEstimate",
                                          "NeighbourStatus", "Violation", "FeasibilityStatus", "ForecastStatus",
                                          "ForecastZOut", "ForecastZIn", "LoopDelayStatus", "LoggingStatus",
                                          "Measurement", "Command"}


def test_the_daemons_config_replies_validate(daemon_replies):
    r = daemon_replies
    assert ConfigReply.model_validate(r["config"]).config_version == 0
    ErrorReply.model_validate(r["config_error"])
    ConfigSetRequest.model_validate(r["set_request"])
    applied = ConfigSetReply.model_validate(r["set_ok"]).root
    assert isinstance(applied, ConfigSetApplied) and applied.controller.K_per_s == 3000.0
    assert applied.applied == r["set_request"]["set"] and applied.config_version == 1
    for req, body in r["set_errors"]:
        assert isinstance(ConfigSetReply.model_validate(body).root, ErrorReply), req
    errors = {req["set"][0] if req["set"] else "": body["error"] for req, body in r["set_errors"]}
    # a validation error names the field, relative to controller
    assert re.search(r"^  K_per_s: ", errors["controller.K_per_s=-1"], re.M)
    assert "limits" in errors["controller.limits.u_min_V=300"]


def test_the_daemons_replies_validate_against_the_json_schema_files(daemon_replies):
    jsonschema = pytest.importorskip("jsonschema")
    r = daemon_replies

    def check(name: str, body: dict) -> None:
        v = jsonschema.Draft202012Validator(committed(name))
        assert [e.message for e in v.iter_errors(body)] == [], name

    for s in r["status"]:
        check("energyctl.StatusReply", s)
    check("energyctl.ConfigReply", r["config"])
    check("energyctl.ConfigSetRequest", r["set_request"])
    check("energyctl.ConfigSetReply", r["set_ok"])
    check("energyctl.ErrorReply", r["config_error"])
    for _req, body in r["set_errors"]:
        check("energyctl.ConfigSetReply", body)
    # and the files say no to what the daemon never sends
    bad = copy.deepcopy(r["status"][1])
    bad["loop"]["exec_us"] = None  # absent before the first tick, never null
    assert list(jsonschema.Draft202012Validator(committed("energyctl.StatusReply")).iter_errors(bad))
    bad = copy.deepcopy(r["status"][1])
    bad["surprise"] = 1
    assert list(jsonschema.Draft202012Validator(committed("energyctl.StatusReply")).iter_errors(bad))
