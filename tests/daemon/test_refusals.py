"""Refused config requests leave a trace: counted in status, and logged (a stderr line and a config_refused event in
the daemon's log) at most once a second, saying how many each line stands for."""

from __future__ import annotations

import json
from types import SimpleNamespace

import service.daemon.queries as queries
from schemas.component import ComponentConfig
from schemas.replies import StatusReply
from service.daemon.daemon import Daemon


def _query(payload: bytes | None = None):
    return SimpleNamespace(payload=None if payload is None else SimpleNamespace(to_bytes=lambda: payload),
                           parameters="")


def test_refused_config_requests_are_counted_and_logged_at_most_once_a_second(monkeypatch, capsys):
    clock = [10**12]
    monkeypatch.setattr(queries, "time", SimpleNamespace(monotonic_ns=lambda: clock[0]))
    d = Daemon(ComponentConfig(id="source", neighbours=[], local_reference_W=None))
    d.neighbours, d._by_id = [], {}  # what open() sets up, without a session
    events = []
    d.t_ev, d.log_path = "energyctl/source/events", "logs/source.mcap"
    d.recorder = SimpleNamespace(offer=lambda topic, t, values: events.append((topic, values)), written=0, drops={},
                                 failed=False, error=None)
    try:
        assert d.status()["config_refused"] == 0
        assert d._config_reply(_query())[0]  # a read is no refusal
        refused = [d._config_set_reply(_query(b"{not json")),
                   d._config_set_reply(_query(json.dumps({"set": []}).encode())),
                   d._config_set_reply(_query(json.dumps({"set": ["controller.K_per_s=-1"]}).encode())),
                   d._config_reply(_query(json.dumps({"set": ["controller.K_per_s=1"]}).encode()))]
        assert not any(ok for ok, _body in refused)
        st = d.status()
        StatusReply.model_validate(json.loads(json.dumps(st)))
        assert st["config_refused"] == 4 and st["last_config_refused"].startswith("config: read-only here")
        # within the second: one line and one event, for the first
        assert len(events) == 1
        topic, (t, seq, kind, detail) = events[0]
        assert topic == "energyctl/source/events" and kind == "config_refused" and detail.startswith("config/set: ")
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and "refused config/set" in err[0] and "(1 refused so far)" in err[0]

        clock[0] += 1_100_000_000
        ok, body = d._config_set_reply(_query(json.dumps({"set": ["loop.rate_hz=1"]}).encode()))
        assert not ok and d.status()["config_refused"] == 5
        assert len(events) == 2
        assert events[1][1][3] == f"config/set: {body['error']} [and 3 more since the last of these]"
        assert "(5 refused so far)" in capsys.readouterr().err
    finally:
        d.recorder = None
