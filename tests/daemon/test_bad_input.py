"""Bad input never reaches the actuator: each class is rejected with the field named, counted, and
answered with du/dt = 0 (or not at all); the core is never stepped on it."""

from __future__ import annotations

import math
import struct

import pytest
from conftest import SCENARIOS, QueryStub, RingStub

from clients.live import configs_from_scenario
from schemas.codec import CMD, MEAS, Z
from schemas.component import ComponentConfig, config_from_dict
from schemas.scenario import load_scenario
from service.daemon.bus import free_tcp_port
from service.daemon.daemon import Daemon


@pytest.fixture
def daemon(daemon_by_hand):
    return daemon_by_hand


def meas(k, t=None, i=15.0, v=80.0, u=80.15, i_load=15.0):
    return MEAS.encode(k, k * 1e-4 if t is None else t, i, v, u, i_load)


def feed(d, payload, now=1):
    steps = d.core.steps
    d._tick(payload, now)
    return d.core.steps > steps  # did the core see it?


def test_good_samples_step_the_core(daemon):
    assert feed(daemon, meas(0)) and feed(daemon, meas(1))
    assert daemon.rejected == {}


@pytest.mark.parametrize(("payload", "reason"), [
    (b"\x00" * 10, "meas.<payload>: invalid"),
    (meas(5)[:-1], "meas.<payload>: invalid"),
    (b"\x00" + meas(5)[1:], "meas.<magic>: invalid"),
    (meas(5)[:1] + b"\x09" + meas(5)[2:], "meas.<version>: invalid"),
    (MEAS.struct.pack(0xE1, 1, 5, 5e-4, math.nan, 80.0, 80.0, 15.0), "meas.i: invalid"),
    (MEAS.struct.pack(0xE1, 1, 5, 5e-4, 15.0, math.inf, 80.0, 15.0), "meas.v: invalid"),
    (MEAS.struct.pack(0xE1, 1, 5, 5e-4, 15.0, 80.0, -math.inf, 15.0), "meas.u: invalid"),
    (MEAS.struct.pack(0xE1, 1, 2**63, 5e-4, 15.0, 80.0, 80.15, 15.0), "meas.seq: invalid"),  # issue 30's frame
    (MEAS.struct.pack(0xE1, 1, 2**64 - 1, 5e-4, 15.0, 80.0, 80.15, 15.0), "meas.seq: invalid"),
    (MEAS.struct.pack(0xE1, 1, 2**53, 5e-4, 15.0, 80.0, 80.15, 15.0), "meas.seq: invalid"),  # not exact as a double
    (meas(5, t=-5e-4), "meas.t: invalid"),
    (meas(5, t=2.0**32), "meas.t: invalid"),
    (meas(5, v=0.0), "meas.v: out of range"),
    (meas(5, v=-3.0), "meas.v: out of range"),
    (meas(5, v=5000.0), "meas.v: out of range"),
    (meas(5, i=2e4), "meas.i: out of range"),
    (meas(5, i_load=-2e4), "meas.i_load: out of range"),
])
def test_malformed_or_out_of_range_measurements_never_reach_the_core(daemon, payload, reason):
    assert feed(daemon, meas(0)) and feed(daemon, meas(1))
    cmd_before = daemon.last_cmd
    assert not feed(daemon, payload)
    assert daemon.rejected == {reason: 1}, daemon.rejected
    if daemon.last_cmd != cmd_before:  # answered: with a hold
        assert daemon.last_cmd[2] == 0.0
    assert feed(daemon, meas(6))  # and the loop goes on


@pytest.mark.parametrize("seq", [2**53, 2**63, 2**64 - 1])
def test_a_seq_beyond_what_the_loop_holds_is_rejected_and_status_keeps_answering(daemon, seq):
    """Issue 30: a frame with seq >= 2^63 passed the codec (u64), reached the loop-delay history (int64) and ended
    the loop thread with OverflowError; a status query then failed in numpy. Now decode rejects it by name, the
    seq after it is taken as the next sample, and status (with its loop-delay estimate) answers."""
    for k in range(3):
        assert feed(daemon, meas(k))
    assert not feed(daemon, MEAS.struct.pack(0xE1, 1, seq, 3e-4, 15.0, 80.0, 80.15, 15.0))
    assert daemon.rejected == {"meas.seq: invalid": 1}
    assert daemon.last_reject == f"meas.seq: invalid ({seq} not in [0, 2^53))"
    assert feed(daemon, meas(3)) and daemon.stats.missing_samples == 0
    st = daemon.status()
    assert st["last_sample"]["seq"] == 3 and st["loop_delay"]["window"] >= 0


def test_duplicate_backwards_and_skipped_sequence_numbers(daemon):
    for k in range(3):
        assert feed(daemon, meas(k))
    assert not feed(daemon, meas(2))  # duplicate
    assert not feed(daemon, meas(1))  # backwards
    assert daemon.rejected == {"meas.seq: duplicate or not increasing": 2}
    assert not feed(daemon, meas(3, t=1e-4))  # time going backwards
    assert daemon.rejected["meas.t: not after the previous sample"] == 1 and daemon.last_cmd[2] == 0.0
    assert feed(daemon, meas(7))  # a gap: accepted, counted
    assert daemon.stats.missing_samples == 4


def test_a_passed_seq_gets_no_answer_whatever_its_values_a_new_one_out_of_range_is_held(daemon):
    """A frame of a seq already answered is rejected before its values are looked at: no plant waits for its answer
    (a burst of holds for passed samples crowded the command key, whose puts drop under congestion). A new seq with v
    out of range is held: its hold answers the sample the plant waits for."""
    for k in range(3):
        assert feed(daemon, meas(k))
    answered = daemon.last_cmd
    assert not feed(daemon, meas(1, v=5000.0)) and daemon.last_cmd == answered
    assert daemon.rejected == {"meas.seq: duplicate or not increasing": 1}
    assert not feed(daemon, meas(3, v=5000.0)) and daemon.last_cmd == (3, 3 * 1e-4, 0.0, 0.0, True)
    assert daemon.rejected["meas.v: out of range"] == 1
    assert feed(daemon, meas(3))  # the held sample did not become the previous one


def test_plant_restart_reinitialises_the_estimator(daemon):
    for k in range(50):
        feed(daemon, meas(k, i=15.0 + 0.01 * k))
    assert daemon.core.estimator.fit.count == 50
    daemon._tick(meas(0, t=0.0), 1)  # sequence reset: not a duplicate, a new history
    assert daemon.rejected == {}
    assert daemon.restarts == 1 and daemon.core.steps == 1 and daemon.core.estimator.fit.count == 1


def test_bad_neighbour_messages_are_counted_and_a_local_reference_is_used_when_silent(daemon):
    nb = daemon.neighbours[0]
    bad = Z.struct.pack(0x21, 1, 1, 0.0, math.nan, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    nb.sub = RingStub([bad, b"junk"])  # one message per tick, as from a ring of one
    assert feed(daemon, meas(0)) and feed(daemon, meas(1))
    assert daemon.rejected == {"load.P_r_out: invalid": 1, "load.<payload>: invalid": 1}
    assert nb.P == 1200.0  # the last good value stands
    # the neighbour goes silent: without a local reference the daemon holds ...
    nb.rx_ns = -10**12
    assert not feed(daemon, meas(2), now=1) and daemon.last_cmd[2] == 0.0 and daemon.reference == "none"
    # ... with one, it regulates to it, flagged
    daemon.cfg = daemon.cfg.model_copy(update={"local_reference_W": 1000.0})
    assert feed(daemon, meas(3), now=1) and daemon.reference == "local"
    assert daemon.core.out.y_ref == pytest.approx(-1000.0)


def test_invalid_config_sets_are_refused_with_the_field(daemon):
    ok, body = daemon.apply_sets(["controller.limits.du_dt_max_V_per_s=-5"])
    assert not ok and "du_dt_max_V_per_s" in body["error"]
    ok, body = daemon.apply_sets(["controller.K_per_s=nan"])
    assert not ok and "K_per_s" in body["error"]
    ok, body = daemon.apply_sets(["lifecycle=sideways"])
    assert not ok and "lifecycle" in body["error"]
    assert daemon.core.cfg.K_per_s == 2000.0


@pytest.mark.parametrize(("value", "field"), [
    ("controller.K_per_s=true", "K_per_s"),  # was taken as 1.0: v reached 191 V
    ('controller.K_per_s="2000"', "K_per_s"),
    ('controller.plan_next_period="yes"', "plan_next_period"),
    ("controller.delay_compensation_samples=3.0", "delay_compensation_samples"),
    ("controller.v_ref_V=1e300", "v_ref_V"),
])
def test_lax_config_sets_are_refused_and_nothing_changes(daemon, value, field):
    before = daemon.core.cfg
    ok, body = daemon.apply_sets([value])
    assert not ok and f"\n  {field}: " in body["error"]
    assert daemon.core.cfg is before and daemon._pending is None


def test_an_integer_set_for_a_float_gain_is_taken(daemon):
    import threading

    t = threading.Thread(target=lambda: daemon.apply_sets(["controller.K_per_s=1500"]), daemon=True)
    t.start()
    from clients.live import wait_until

    assert wait_until(lambda: daemon._pending is not None, 5.0)  # validated, handed to the loop
    assert daemon._pending[0].K_per_s == 1500.0
    daemon._apply_pending()  # what the loop does before its next tick
    t.join(5.0)
    assert daemon.core.cfg.K_per_s == 1500.0


def test_stale_measurements_degrade_and_fresh_ones_resume(daemon):
    import threading

    assert feed(daemon, meas(0))
    daemon.cfg = daemon.cfg.model_copy(update={"stale_periods": 5})
    t = threading.Thread(target=daemon.run_loop, kwargs={"max_ticks": 20}, daemon=True)
    t.start()  # clock trigger, no measurements arrive
    t.join(5.0)
    assert daemon.state == "degraded" and daemon.last_cmd is not None
    assert feed(daemon, meas(1))  # fresh data: back by itself
    assert daemon.state == "active"
    assert CMD.size == struct.calcsize("<BBQddd?")


def test_an_unwritable_log_directory_degrades_logging_not_control(tmp_path):
    from clients.live import wait_until

    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the log directory should be")
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=10000.0)
    comp.update({"neighbour_stale_s": 10.0, "log_dir": str(blocker / "logs")})
    comp["loop"]["trigger"] = "clock"
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    try:
        nb = d.neighbours[0]
        nb.count, nb.P, nb.rx_ns = 1, 1200.0, 0
        assert wait_until(lambda: d.recorder.failed, 20.0)
        logging = d.status()["logging"]
        assert logging["state"] == "degraded" and "cannot write" in logging["error"]
        for k in range(20):  # control goes on, and offering to the dead recorder costs nothing
            assert feed(d, meas(k))
    finally:
        d.close()
    assert d.recorder.error and d.recorder.written == 0


def test_rejections_are_recorded_as_diagnostics_without_flooding_the_log(tmp_path):
    """Each rejected class is a diagnostics event in the MCAP naming its field; a plant rejected at every sample
    (it diverged) gives at most one event per reason per REJECT_EVENT_EVERY_NS of the loop's clock, each saying
    how many it stands for, while status counts every one."""
    from service.daemon.daemon import REJECT_EVENT_EVERY_NS
    from service.logio.reader import messages as read_messages

    scn = load_scenario(SCENARIOS / "paper-constant-load.toml")
    comp, _p, _l = configs_from_scenario(scn, f"tcp/127.0.0.1:{free_tcp_port()}", lockstep=False, rate_hz=10000.0)
    comp.update({"neighbour_stale_s": 10.0, "log_dir": str(tmp_path)})
    comp["loop"]["trigger"] = "clock"
    comp["forecast"] = {"enabled": False}
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    try:
        nb = d.neighbours[0]
        nb.count, nb.P, nb.rx_ns = 1, 1200.0, 0
        assert d.recorder.wait_ready()
        feed(d, meas(0))
        feed(d, MEAS.struct.pack(0xE1, 1, 1, 1e-4, math.nan, 80.0, 80.0, 15.0))
        feed(d, meas(2, i=2e4))
        n_flood = 1000  # 0.1 s of samples at 10 kHz, all with v out of range
        for k in range(3, 3 + n_flood):
            feed(d, meas(k, v=5000.0), now=k * 100_000)  # the loop's clock at 10 kHz
        assert d.rejected["meas.v: out of range"] == n_flood
    finally:
        d.close()
    ev = [e for e in read_messages(d.log_path, "/events") if e["kind"] == "reject"]
    details = [e["detail"] for e in ev]
    assert any(x.startswith("meas.i: invalid") for x in details)
    assert any(x.startswith("meas.i: out of range") for x in details)
    flood = [x for x in details if x.startswith("meas.v: out of range")]
    every = REJECT_EVENT_EVERY_NS // 100_000  # samples per event
    assert len(flood) == -(-n_flood // every)  # one per 10 ms: 10, not 1000
    said = len(flood) + sum(int(x.split("[and ")[1].split()[0]) for x in flood if "[and " in x)
    assert said == n_flood - (every - 1)  # all but the last stretch, still waiting for its event


def test_the_query_loop_answers_every_query_a_bad_one_and_an_unencodable_reply_included():
    """service.daemon.bus.serve_queries: a handler that raises is answered with its error, a reply JSON cannot encode
    (a numpy integer) is answered as an error naming why, a query handed on is not answered here, and every answered
    query is dropped; the loop ends when its channel closes."""

    import numpy as np

    from service.daemon.bus import serve_queries

    queries = [QueryStub(n) for n in range(4)]

    class Channel:
        def __init__(self):
            self.left = list(queries)

        def recv(self):
            if not self.left:
                raise RuntimeError("closed")
            return self.left.pop(0)

    def handler(q):
        if q.n == 0:
            return True, {"n": 0}
        if q.n == 1:
            raise ValueError("set: no such key")
        if q.n == 2:
            return True, {"n": np.int64(2)}
        return None  # handed on

    serve_queries(Channel(), "energyctl/x/status", handler)
    assert queries[0].got == ("ok", {"n": 0}) and queries[0].key == "energyctl/x/status"
    assert queries[1].got == ("err", {"error": "ValueError: set: no such key"})
    assert queries[2].got[0] == "err" and "could not be encoded" in queries[2].got[1]["error"]
    assert queries[3].got is None and not queries[3].dropped
    assert all(q.dropped for q in queries[:3])


def test_the_load_peer_follows_only_the_plants_next_sample():
    """The lockstep load answers each measurement on the plant's key with its z for that seq and t: a duplicate, an
    older, a not-later or a malformed frame on that key (a corrupted or stray sender) is not the plant's next sample
    and gets no answer (the controller, which rejects it, then waited for the load's z of the real one); seq 0 is
    the plant restarting."""
    from clients.peers.load import _plant_clock

    assert _plant_clock(meas(5, t=0.5), None) == (5, 0.5)
    assert _plant_clock(meas(6, t=0.6), (5, 0.5)) == (6, 0.6)
    assert _plant_clock(meas(9, t=0.9), (5, 0.5)) == (9, 0.9)  # a gap
    for frame in (meas(5, t=0.7), meas(3, t=0.7), meas(6, t=0.5), meas(6, t=0.7)[:-1],
                  MEAS.struct.pack(0xE1, 1, 2**63, 1.0, 1, 80, 1, 1)):
        assert _plant_clock(frame, (5, 0.5)) is None
    assert _plant_clock(meas(0), (5, 0.5)) == (0, 0.0)  # a restart
