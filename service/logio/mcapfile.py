"""MCAP output: JSON messages with JSON Schemas generated from schemas/messages.py, zstd chunks."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.writer import CompressionType, Writer

from schemas.messages import MESSAGE_MODELS, json_schema
from service import __version__


def git_revision() -> str:
    """The source tree's git revision, or 'unknown' (read once at start-up, never on the loop)."""
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                             text=True, timeout=2)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


class McapFile:
    """A small MCAP writer: register a topic with a message model, then add pre-built dicts."""

    def __init__(self, path: str | Path, chunk_size: int = 1 << 20):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")
        self._w = Writer(self._f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._w.start(profile="", library=f"energyctl {__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}

    def channel(self, topic: str, schema_name: str) -> int:
        if schema_name not in self._schemas:
            sch = json.dumps(json_schema(MESSAGE_MODELS[schema_name])).encode()
            self._schemas[schema_name] = self._w.register_schema(schema_name, "jsonschema", sch)
        cid = self._w.register_channel(topic, "json", self._schemas[schema_name])
        self._channels[topic] = cid
        self._seq[topic] = 0
        return cid

    def add(self, topic: str, t_s: float, payload: dict) -> None:
        self.add_raw(topic, t_s, json.dumps(payload, separators=(",", ":")).encode())

    def add_raw(self, topic: str, t_s: float, data: bytes) -> None:
        """A message whose JSON text is already encoded."""
        ns = int(round(t_s * 1e9))
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        self._w.add_message(self._channels[topic], log_time=ns, publish_time=ns, sequence=seq, data=data)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, data)

    def attachment(self, name: str, media_type: str, data: bytes, t_s: float) -> None:
        ns = int(round(t_s * 1e9))
        self._w.add_attachment(create_time=ns, log_time=ns, name=name, media_type=media_type, data=data)

    def close(self) -> None:
        self._w.finish()
        self._f.close()


def write_sim_mcap(path: str | Path, result, prefix: str = "energyctl/sim") -> Path:
    """Write a SimResult: channels <prefix>/meas, /cmd, /est, /plant and a ``scenario`` metadata record."""
    from service.core.control import core_metadata

    scn = result.scenario
    core = core_metadata(scn.controller, scn.model, 1.0 / scn.timing.control_rate_hz, result.delay_compensation)
    return write_trace_mcap(path, result.trace, {"scenario": {"json": scn.model_dump_json()},
                                                 "metrics": {"json": json.dumps(result.metrics)},
                                                 "core": {"json": core}}, prefix)


def write_trace_mcap(path: str | Path, tr: dict, metadata: dict[str, dict[str, str]], prefix: str) -> Path:
    """A closed-loop trace (service.sim.TRACE_FIELDS; the estimator columns are optional) as MCAP:
    <prefix>/meas, /cmd, /plant and, when present, /est; one metadata record per ``metadata`` entry."""
    f = McapFile(path)
    for name, data in metadata.items():
        f.metadata(name, {**data, "version": __version__})
    has_est, has_in = "E" in tr, "P_r_in" in tr
    for topic, schema in (("meas", "energyctl.Measurement"), ("cmd", "energyctl.Command"),
                          ("est", "energyctl.Estimate"), ("plant", "energyctl.Plant"), ("z_in", "energyctl.TickInput")):
        if (topic != "est" or has_est) and (topic != "z_in" or has_in):
            f.channel(f"{prefix}/{topic}", schema)
    cols = {k: v.tolist() for k, v in tr.items()}
    nxt = cols.get("du_dt_next") or [0.0] * len(cols["t"])
    est_keys = ("E", "p", "E_t", "y_z", "y_z_balance", "y_ref", "eta", "u_z", "P_r_out", "Qdot_r_out",
                "z_out0", "z_out1")
    for k, t in enumerate(cols["t"]):
        f.add(f"{prefix}/meas", t, {"seq": k, "t": t, "i": cols["i_meas"][k], "v": cols["v_meas"][k],
                                    "u": cols["u_meas"][k], "i_load": cols["i_load_meas"][k]})
        if has_in:
            f.add(f"{prefix}/z_in", t, {"seq": k, "t": t, "P_r_in": cols["P_r_in"][k],
                                        "P_r_in_dot": cols["P_r_in_dot"][k], "stepped": True})
        if cols["du_dt"][k] == cols["du_dt"][k]:  # NaN: no command answered this sample
            f.add(f"{prefix}/cmd", t, {"seq": k, "t": t, "du_dt": cols["du_dt"][k], "du_dt_next": nxt[k],
                                       "limited": False})
        if has_est:
            est = {"t": t}
            for key in est_keys:
                est[key] = cols[key][k]
            f.add(f"{prefix}/est", t, est)
        f.add(f"{prefix}/plant", t, {"t": t, "i": cols["i"][k], "v": cols["v"][k], "u": cols["u"][k],
                                     "P_l": cols["P_l"][k]})
    f.close()
    return Path(path)


def write_network_mcap(path: str | Path, res, prefix: str | None = None) -> Path:
    """A network run (service.network.netsim.NetworkResult) as one MCAP: each source's channels under its own prefix,
    <prefix>/<source>/meas, /z_in, /cmd, /events (the layer's v_ref moves, which replay applies also in a
    what-if, and its Z^{r,in} for each window the source was connected in) and /plant (its true state,
    P_l the power its lines draw), each bus's under <prefix>/<bus>/plant, and the layer's events (breakers,
    connect requests and the answers, load steps) on <prefix>/layer/events; metadata: the scenario, the metrics and
    one core record per source (core:<source>), so that ``energyctl replay LOG --component <source>`` rebuilds and
    replays each source on its own."""
    net = res.net
    prefix = prefix or f"energyctl/{net.name}"
    f = McapFile(path)
    f.metadata("scenario", {"json": net.model_dump_json(), "version": __version__})
    f.metadata("metrics", {"json": json.dumps(res.metrics), "version": __version__})
    for name, core in res.cores.items():
        f.metadata(f"core:{name}", {"json": core, "version": __version__})
    for name in res.sources:
        for leaf, schema in (("meas", "energyctl.Measurement"), ("z_in", "energyctl.TickInput"),
                             ("cmd", "energyctl.Command"), ("events", "energyctl.Event"), ("plant", "energyctl.Plant")):
            f.channel(f"{prefix}/{name}/{leaf}", schema)
    for bus in res.buses:
        f.channel(f"{prefix}/{bus}/plant", "energyctl.Plant")
    f.channel(f"{prefix}/layer/events", "energyctl.Event")
    t = res.t.tolist()
    cols = {name: {k: v.tolist() for k, v in row.items()} for name, row in res.sources.items()}
    buses = {b: v.tolist() for b, v in res.buses.items()}
    events = {name: list(evs) for name, evs in res.config_events.items()}
    for k, tk in enumerate(t):
        for name, c in cols.items():
            p = f"{prefix}/{name}"
            while events[name] and events[name][0][1] == k:  # the layer's v_ref move, applied before this tick
                et, seq, v_ref = events[name].pop(0)
                f.add(f"{p}/events", et, {"t": et, "seq": seq, "kind": "v_ref",
                                          "detail": json.dumps({"v_ref_V": v_ref})})
            f.add(f"{p}/meas", tk, {"seq": k, "t": tk, "i": c["meas_i"][k], "v": c["meas_v"][k],
                                    "u": c["meas_u"][k], "i_load": c["meas_i_load"][k]})
            f.add(f"{p}/z_in", tk, {"seq": k, "t": tk, "P_r_in": c["P_in"][k], "P_r_in_dot": 0.0,
                                    "stepped": bool(c["stepped"][k])})
            f.add(f"{p}/cmd", tk, {"seq": k, "t": tk, "du_dt": c["cmd_du"][k], "du_dt_next": c["cmd_du_next"][k],
                                   "limited": False})
            f.add(f"{p}/plant", tk, {"t": tk, "i": c["i"][k], "v": c["v"][k], "u": c["u"][k], "P_l": c["P"][k]})
        for bus, v in buses.items():
            f.add(f"{prefix}/{bus}/plant", tk, {"t": tk, "i": 0.0, "v": v[k], "u": 0.0, "P_l": 0.0})
    w = net.layer.window_s
    for name, rs in res.ranges.items():  # the layer's Z^{r,in} for each window, as it started
        for k, z in rs:
            f.add(f"{prefix}/{name}/events", k * w, {"t": k * w, "seq": int(round(k * w * net.timing.control_rate_hz)),
                                                      "kind": "range", "detail": json.dumps(
                                                          {"window": k, "P": [z[0], z[1]], "Qdot": [z[2], z[3]]})})
    for ev in res.events:
        detail = json.dumps({"target": ev.target, "accepted": ev.accepted, "reason": ev.reason})
        f.add(f"{prefix}/layer/events", ev.t, {"t": ev.t, "seq": int(round(ev.t * net.timing.control_rate_hz)),
                                               "kind": ev.kind, "detail": detail})
    f.close()
    return Path(path)
