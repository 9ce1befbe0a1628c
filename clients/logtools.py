"""energyctl log info / log recover: inspect any MCAP we write, including one whose writer was killed or whose bytes
were damaged.

Both read the file through ``service.logio.reader.scan``: as a stream, record by record, without the summary, so
a file cut short by SIGKILL yields everything up to its last complete chunk, and a corrupt chunk (zstd error, CRC
mismatch) is skipped and reported with its byte offset while the chunks after it are still read. A file that is
empty or not MCAP raises LogError.
"""

from __future__ import annotations

import json
from pathlib import Path

from mcap.writer import CompressionType, Writer

from service.logio.reader import scan


def info(path: str | Path) -> dict:
    s = scan(path)
    damage = [d.as_dict() for d in s["damage"]]
    out = {"path": s["path"], "complete": s["complete"], "truncated_at": s["error"], "damage": damage,
           "undeclared": s["undeclared"],
           "intact": s["complete"] and not s["error"] and not damage and not s["undeclared"],
           "duration_s": s["duration_s"],
           "channels": {t: {"messages": n, "bytes": s["bytes"][t]} for t, n in sorted(s["counts"].items())},
           "messages": sum(s["counts"].values()), "drops": s["drops"],
           "attachments": {a.name: sum(1 for b in s["attachments"] if b.name == a.name) for a in s["attachments"]}}
    if "recovered" in s["metadata"]:  # written by recover: what the original lost
        r = s["metadata"]["recovered"]
        out["recovered"] = {"from": r.get("from"), "dropped": json.loads(r.get("dropped") or "[]"),
                            "truncated_at": None if r.get("truncated_at") in (None, "None") else r["truncated_at"]}
    for name in ("config", "core", "scenario", "build", "metrics"):
        if name in s["metadata"]:
            m = s["metadata"][name]
            out[name] = json.loads(m["json"]) if "json" in m else m
    if isinstance(out.get("core"), dict) and "period_s" in out["core"]:  # a daemon or sim log
        out["loop_delay"] = (measured_loop_delay(path, out["core"]) if not damage else
                             {"measured_samples": None, "reason": "not measured: the log has corrupt chunks"})
    return out


def measured_loop_delay(path: str | Path, core: dict) -> dict:
    """The loop delay measured from the log's last plant epoch (service/delay.py)."""
    import numpy as np

    from service.core.delay import loop_delay_report
    from service.replay import SEQ_BITS, ReplayError, collect

    try:
        tk = collect([path])
    except ReplayError:
        return {"measured_samples": None}
    last = tk.keys >> SEQ_BITS == tk.restarts  # the last plant epoch only (seq restarts from 0 at a restart)
    sent = np.where(tk.has_cmd[last], tk.logged[last], 0.0)
    return loop_delay_report(tk.rows[last, 0], tk.rows[last, 4], sent, core["period_s"], core.get("delay_samples"))


def recover(broken: str | Path, fixed: str | Path) -> dict:
    """Rewrite every readable record of `broken` into a complete, indexed MCAP `fixed`: every intact chunk, also
    after a corrupt one (which is dropped and listed in ``dropped``, with its offset and the messages it held when
    the message indexes after it say); ``lost_tail`` says where a cut-off file ended. LogError (nothing written) if
    `broken` is empty or not MCAP."""
    s = scan(broken, keep_messages=True)
    dropped = [d.as_dict() for d in s["damage"]]
    with open(fixed, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="energyctl log recover")
        sid = {old: w.register_schema(sc.name, sc.encoding, sc.data) for old, sc in s["schemas"].items()}
        cid = {old: w.register_channel(ch.topic, ch.message_encoding, sid.get(ch.schema_id, 0), ch.metadata)
               for old, ch in s["channels"].items()}
        for name, data in s["metadata"].items():
            w.add_metadata(name, data)
        w.add_metadata("recovered", {"from": str(broken), "was_complete": str(s["complete"]),
                                     "truncated_at": str(s["error"]), "dropped": json.dumps(dropped),
                                     "undeclared_messages": str(s["undeclared"])})
        for m in s["messages"]:
            w.add_message(cid[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
        for a in s["attachments"]:  # e.g. the tick index: replay uses it only if it covers every tick
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        w.finish()
    return {"from": str(broken), "to": str(fixed), "messages": len(s["messages"]), "was_complete": s["complete"],
            "lost_tail": s["error"], "dropped": dropped, "undeclared": s["undeclared"],
            "dropped_messages": sum(d["messages"] or 0 for d in dropped) + s["undeclared"],
            "whole": s["complete"] and not s["error"] and not dropped and not s["undeclared"]}
