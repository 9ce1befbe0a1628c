"""The coordinator's side of the plug-in handshake, without Zenoh: an offer, the source's own forecast announced
against it, and what makes an announcement refused (an offer too old, the breakers changed since, none at all, a
malformed one) -- each answered, none breaking the coordinator."""

from __future__ import annotations

import json

import pytest
from conftest import SCENARIOS, QueryStub

from schemas.netlive import CoordinatorConfig
from schemas.network import load_network
from service.daemon import coordinator as coordinator_module
from service.daemon.coordinator import Coordinator
from service.forecast import forecast_outgoing
from service.network.layer import MAX_OFFER_AGE_WINDOWS


@pytest.fixture
def co(monkeypatch):
    """A coordinator of the 1 kHz network at sample 100, S3 (open) alive; the rig closes whatever it is asked to."""
    monkeypatch.setattr(coordinator_module, "request", lambda *a, **k: (True, {}))
    c = Coordinator(CoordinatorConfig(), load_network(SCENARIOS / "network" / "realtime.toml"))
    c.alive["S3"] = True
    c.seq = 100
    return c


def ask(c: Coordinator, body: dict) -> tuple[str, dict]:
    q = QueryStub()
    c._connect(q, body)
    assert q.got is not None, "no answer"
    return q.got


def announcement(c: Coordinator) -> dict:
    """S3 asks for its offer and forecasts its Z^{r,out} for it, as its daemon does."""
    src = c.net.sources["S3"]
    kind, offer = ask(c, {"source": "S3", "controller": src.controller.model_dump(), "offer": True})
    assert kind == "ok" and offer["offer"] and len(offer["box"]) == 4, offer
    ctl = src.controller.model_copy(update={"v_ref_V": offer["v_ref_V"]})
    f = forecast_outgoing(ctl, src.model_params(), 1e-3, c.d, tuple(offer["box"]), offer["tau_prime_s"],
                          max_ramp_s=offer["window_s"])
    return {"source": "S3", "controller": src.controller.model_dump(), "saturation": f.saturation,
            "Z_out": {"P": [f.P_lo, f.P_hi], "Qdot": [f.Qdot_lo, f.Qdot_hi]}}


def test_an_announcement_within_its_offer_s_time_is_accepted_and_an_old_one_refused(co):
    body = announcement(co)
    co.seq += MAX_OFFER_AGE_WINDOWS * co.layer.per_window  # the forecast took long: still within the bound
    kind, r = ask(co, body)
    assert kind == "ok" and r["accepted"] and r["announced"], r
    assert co.counters["accepted"] == 1 and co.verdicts[-1]["source"] == "S3"

    body = announcement(co)
    co.seq += (MAX_OFFER_AGE_WINDOWS + 1) * co.layer.per_window
    kind, r = ask(co, body)
    assert kind == "ok" and not r["accepted"] and "windows old" in r["reason"], r


def test_an_announcement_after_the_breakers_changed_or_without_an_offer_is_refused(co):
    body = announcement(co)
    co.connected[1] = False  # S2 tripped meanwhile: S3's share of the load is another
    kind, r = ask(co, body)
    assert kind == "ok" and not r["accepted"] and "breakers changed" in r["reason"], r
    kind, r = ask(co, body)  # the offer was used up
    assert kind == "ok" and not r["accepted"] and "no offer" in r["reason"], r
    assert co.counters["refused"] == 2 and [v["accepted"] for v in co.verdicts] == [False, False]


@pytest.mark.parametrize(("z_out", "field"), [
    ({"P": [0.0, 10 ** 400], "Qdot": [0.0, 1.0]}, "Z_out.P"),  # float() overflows
    ({"P": [0.0, 1.0], "Qdot": [float("nan"), 1.0]}, "Z_out.Qdot"),
    ({"P": [1.0, 0.0], "Qdot": [0.0, 1.0]}, "Z_out.P"),
    ([0.0, 1.0], "Z_out:"),
])
def test_a_malformed_announcement_is_refused_by_name_and_the_next_request_answered(co, z_out, field):
    kind, r = ask(co, {"source": "S3", "controller": {}, "Z_out": z_out})
    assert kind == "err" and field in r["error"], r
    kind, r = ask(co, announcement(co))
    assert kind == "ok" and r["accepted"], r


def test_a_request_that_breaks_the_check_gets_an_error_and_the_held_ones_survive(co, monkeypatch):
    """Whatever raises inside a connect (here the layer's offer) is answered as an error, and a lockstep request
    held for a later sample is still there afterwards."""
    co.cfg = co.cfg.model_copy(update={"lockstep": True})
    held = QueryStub()
    co._connects.put((held, {"source": "S3", "controller": {}, "offer": True, "at_seq": co.seq + 5}))
    bad = QueryStub()
    co._connects.put((bad, {"source": "S3", "controller": {}, "offer": True}))
    monkeypatch.setattr(co.layer, "connect_offer", lambda *a: 1 / 0)
    co._take_connects()
    assert bad.got[0] == "err" and "ZeroDivisionError" in bad.got[1]["error"]
    assert held.got is None and co._connects.qsize() == 1


def test_a_request_without_a_forecast_of_its_own_is_refused_by_name_without_running_one(co, monkeypatch):
    """No forecast runs on the coordinator's loop thread for a peer that announces none (30-350 ms of it)."""
    monkeypatch.setattr(co.layer, "connect_check", lambda *a, **k: pytest.fail("a forecast ran on the loop"))
    kind, r = ask(co, {"source": "S3", "controller": co.net.sources["S3"].controller.model_dump()})
    assert kind == "err" and "Z_out" in r["error"] and not co.verdicts, r


def test_the_log_replays_each_offer_and_each_verdict_stale_ones_included(co, monkeypatch):
    """The coordinator's offer and connect events, fed to the replay's Handshakes with the same layer, give every
    offer bit for bit and every verdict's reason: accepted, an offer too old, breakers changed, no offer."""
    from service.network.layer_replay import Handshakes

    events: list[tuple[int, str, dict]] = []
    monkeypatch.setattr(co, "_event", lambda t, seq, kind, d: events.append((seq, kind, json.loads(json.dumps(d)))))
    ask(co, announcement(co))  # accepted
    body = announcement(co)
    co.seq += (MAX_OFFER_AGE_WINDOWS + 1) * co.layer.per_window
    ask(co, body)  # too old
    body = announcement(co)
    co.connected[1] = False
    ask(co, body)  # breakers changed
    ask(co, body)  # no offer
    hs = Handshakes(co.layer, co.names)
    reasons = []
    for seq, kind, d in events:
        if kind == "offer":
            assert hs.offer(d) is None, d
        elif d.get("announced"):
            assert hs.announced(d, seq) == d["reason"], d
            reasons.append(d["reason"])
    assert reasons[0] == "" and "windows old" in reasons[1] and "breakers changed" in reasons[2]
    assert "no offer" in reasons[3] and sum(k == "offer" for _, k, _ in events) == 3
    # a replay that kept no offers (or forgot one) would call the first "no offer": the check can fail
    assert Handshakes(co.layer, co.names).announced(next(d for _, k, d in events if d.get("announced")), 0) != ""
