"""MCAP output: JSON messages with JSON Schemas generated from schemas/messages.py, zstd chunks."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.writer import CompressionType, Writer

from schemas.messages import MESSAGE_MODELS, json_schema

from . import __version__


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
        ns = int(round(t_s * 1e9))
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        self._w.add_message(self._channels[topic], log_time=ns, publish_time=ns, sequence=seq,
                            data=json.dumps(payload, separators=(",", ":")).encode())

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, data)

    def close(self) -> None:
        self._w.finish()
        self._f.close()


def write_sim_mcap(path: str | Path, result, prefix: str = "energyctl/sim") -> Path:
    """Write a SimResult: channels <prefix>/meas, /cmd, /est, /plant and a ``scenario`` metadata record."""
    from .core import core_metadata

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
    est_keys = ("E", "p", "E_t", "y_z", "y_z_balance", "y_ref", "eta", "u_z", "P_r_out", "Qdot_r_out",
                "z_out0", "z_out1")
    for k, t in enumerate(cols["t"]):
        f.add(f"{prefix}/meas", t, {"seq": k, "t": t, "i": cols["i_meas"][k], "v": cols["v_meas"][k],
                                    "u": cols["u_meas"][k], "i_load": cols["i_load_meas"][k]})
        if has_in:
            f.add(f"{prefix}/z_in", t, {"seq": k, "t": t, "P_r_in": cols["P_r_in"][k],
                                        "P_r_in_dot": cols["P_r_in_dot"][k], "stepped": True})
        if cols["du_dt"][k] == cols["du_dt"][k]:  # NaN: no command answered this sample
            f.add(f"{prefix}/cmd", t, {"seq": k, "t": t, "du_dt": cols["du_dt"][k], "limited": False})
        if has_est:
            est = {"t": t}
            for key in est_keys:
                est[key] = cols[key][k]
            f.add(f"{prefix}/est", t, est)
        f.add(f"{prefix}/plant", t, {"t": t, "i": cols["i"][k], "v": cols["v"][k], "u": cols["u"][k],
                                     "P_l": cols["P_l"][k]})
    f.close()
    return Path(path)


class Recorder:
    """MCAP writing off the loop thread, behind a bounded queue.

    ``offer(topic, t, values)`` is what the loop calls: it puts a tuple (no encoding, no I/O) and
    never blocks; when the queue is full the message is dropped and counted per topic, and the counts
    are written as ``recorder_drops`` events. The writer thread encodes JSON and writes zstd chunks.
    ``close()`` drains the queue and finishes the file (summary and index), so a stopped process
    leaves a complete MCAP.
    """

    def __init__(self, path: str | Path, topics: dict[str, tuple[str, tuple[str, ...]]],
                 metadata: dict[str, dict[str, str]], maxsize: int = 100_000, chunk_size: int = 1 << 20):
        import queue
        import threading

        self.path = Path(path)
        self._file = McapFile(self.path, chunk_size=chunk_size)
        for name, data in metadata.items():
            self._file.metadata(name, {**data, "version": __version__})
        self._fields = {}
        for topic, (schema, fields) in topics.items():
            self._file.channel(topic, schema)
            self._fields[topic] = fields
        self._q: queue.Queue = queue.Queue(maxsize)
        self._full = queue.Full
        self.drops: dict[str, int] = {}
        self.written = 0
        self.error: str | None = None
        self._events_topic = next((t for t, (s, _) in topics.items() if s == "energyctl.Event"), None)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def offer(self, topic: str, t: float, values: tuple) -> None:
        try:
            self._q.put_nowait((topic, t, values))
        except self._full:
            self.drops[topic] = self.drops.get(topic, 0) + 1

    def _run(self) -> None:
        get, f, fields = self._q.get, self._file, self._fields
        reported = 0
        while True:
            item = get()
            if item is None:
                break
            topic, t, values = item
            if self.error is not None:
                continue  # keep draining so the loop never blocks; the file is already broken
            try:
                f.add(topic, t, dict(zip(fields[topic], values, strict=True)))
                self.written += 1
                n_drops = sum(self.drops.values())
                if n_drops != reported and self._events_topic:
                    reported = n_drops
                    f.add(self._events_topic, t, {"t": t, "seq": 0, "kind": "recorder_drops",
                                                  "detail": json.dumps(self.drops)})
            except Exception as e:  # noqa: BLE001 - disk full, permissions: control goes on
                self.error = f"{type(e).__name__}: {e}"

    def close(self) -> None:
        self._q.put(None)
        self._thread.join()
        try:
            if self._events_topic and self.drops:
                self._file.add(self._events_topic, 0.0, {"t": 0.0, "seq": 0, "kind": "recorder_drops",
                                                         "detail": json.dumps(self.drops)})
            self._file.close()
        except Exception as e:  # noqa: BLE001
            self.error = self.error or f"{type(e).__name__}: {e}"
