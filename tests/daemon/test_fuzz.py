"""Wire fuzzing of the live daemon (issue 30): bad measurement frames (tests/wire_fuzz.py: valid ones with bit
flips, fields at their boundaries, NaN and ±inf, cuts) put on the plant's key with Zenoh's own put, between the
samples of a running stack, lockstep and realtime. The loop keeps ticking, every bad frame is counted under the
reason the protocol gives it, no command follows one, status keeps answering; in lockstep v stays within ±2 % of
v_ref. A neighbour's bad interaction messages, in-process.

Loopback, free ports, multicast scouting off, every process stopped (clients.bench.recovery.Rig). The 100 000-frame
figure is a bench: energyctl bench fuzz (docs/benchmarks.md)."""

from __future__ import annotations

from collections import Counter

import pytest
from conftest import SCENARIOS, RingStub
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from wire_fuzz import bad_fixed, bad_meas

from clients.bench.fuzz import StackFuzzer
from clients.bench.recovery import Rig
from clients.commands.demo import DEMO_REALTIME_DELAY, DEMO_REALTIME_HZ, DEMO_REALTIME_SETS
from schemas.codec import MEAS
from schemas.scenario import load_scenario

SEQ_MAX = 100  # fuzz frames carry seqs the plant has passed before fuzzing starts (bit flips may move them)
V_REF, V_RANGE, I_MAX = 80.0, (1.0, 1000.0), 1000.0  # the shipped config's meas_v_min_V, meas_v_max_V, meas_i_max_A
# live examples: each a batch of frames against the one stack; generated only (a live run cannot be replayed to
# shrink), few enough for CI
LIVE = settings(max_examples=50, deadline=None, phases=[Phase.explicit, Phase.generate],
                suppress_health_check=list(HealthCheck))


def send(fz: StackFuzzer, frames) -> dict:
    """Put the frames beside the stack; once the controller counted each under its reason, check what the module
    docstring says; its status."""
    st = fz.send(frames)
    assert st is not None, (Counter((fz.rig.status() or {}).get("rejected")) - fz.want,
                            fz.want - Counter((fz.rig.status() or {}).get("rejected")))
    assert st["state"] == "active" and not st.get("failure")
    assert st["loop"]["lockstep_timeouts"] == 0
    assert fz.commands_after_bad_frames() == 0  # none in the fuzz frames' seqs (and every command put has come)
    assert fz.answered_twice() == 0  # and the plant's samples got one answer each
    return st


def fuzzed(tmp_path_factory, lockstep: bool):
    """The stack, and the fuzzer beside it; at the end every process stopped and checked (check_the_end).

    Lockstep at the scenario's 10 kHz; realtime as energyctl demo --realtime runs it (2 kHz, its settings and its
    16-sample schedule: with a 1-sample one the stack diverged here under the fuzzer's load, and every later sample
    was held out of range). catch_up 256: the loop answers every queued frame in order (a batch of fuzz frames and the
    samples around it); with 1 a fuzz frame queued after a sample hid it from the loop, and one before it was never
    looked at."""
    rt = {} if lockstep else {"rate_hz": DEMO_REALTIME_HZ, "controller_delay": DEMO_REALTIME_DELAY}
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml", [] if lockstep else DEMO_REALTIME_SETS)
    with Rig(scn, tmp_path_factory.mktemp("fuzz"), lockstep=lockstep, duration_s=600.0,
             comp={"loop": {"catch_up": 256}}, **rt) as rig:
        for name in ("daemon", "load", "plant"):
            rig.start(name)
        fz = StackFuzzer(rig, SEQ_MAX)
        yield fz
        fz.close()
        out = rig.close()
    check_the_end(out)


# each stack lives for its class only: a lockstep plant steps as fast as it can, and left running beside the realtime
# stack and the in-process test it took most of the machine from them (the in-process test 4 s alone, 32 s beside)
@pytest.fixture(scope="class")
def lockstep(tmp_path_factory):
    yield from fuzzed(tmp_path_factory, lockstep=True)


@pytest.fixture(scope="class")
def realtime(tmp_path_factory):
    yield from fuzzed(tmp_path_factory, lockstep=False)


def check_the_end(out: dict) -> None:
    """Stopped with SIGTERM: every process ended cleanly, none printed a traceback, the controller never failed."""
    for name, (rc, _so, se) in out.items():
        if rc != 0 or "Traceback" in se:  # its stderr whole (a stop past the grace prints every thread's stack)
            pytest.fail(f"{name} exited with {rc}; the end of its stderr:\n{se[-6000:]}", pytrace=False)


class TestLockstep:
    @LIVE
    @given(frames=st.lists(bad_meas(SEQ_MAX, V_RANGE, I_MAX, 1e-4), min_size=1, max_size=40))
    def test_bad_frames_between_lockstep_samples_are_counted_and_change_nothing(self, lockstep, frames):
        st = send(lockstep, frames)
        v = st["last_sample"]["v"]
        assert abs(v - V_REF) <= 0.02 * V_REF, v  # still regulated, at the newest sample


class TestRealtime:
    @LIVE
    @given(frames=st.lists(bad_meas(SEQ_MAX, V_RANGE, I_MAX, 5e-4), min_size=1, max_size=40))
    def test_bad_frames_between_realtime_samples_are_counted_and_change_nothing(self, realtime, frames):
        st = send(realtime, frames)
        assert st["loop"]["ticks"] > realtime.sent  # the plant's samples go on being answered


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.lists(bad_fixed("z", "load"), min_size=1, max_size=5))
def test_a_neighbours_bad_messages_are_counted_by_name_and_its_last_good_one_stands(daemon_by_hand, frames):
    """Each bad interaction message is rejected by name when the loop polls it; the neighbour's last good values
    stand and the core steps on every good sample with them."""
    d = daemon_by_hand
    nb = d.neighbours[0]
    before, good = Counter(d.rejected), (nb.seq, nb.t, nb.P, nb.P_dot, nb.count)
    k0 = d._last_seq + 1
    nb.sub = RingStub([f for f, _ in frames])
    for k in range(k0, k0 + len(frames)):  # one message polled per tick, as from a ring of one
        steps = d.core.steps
        d._tick(MEAS.encode(k, k * 1e-4, 15.0, 80.0, 80.15, 15.0), 1)
        assert d.core.steps == steps + 1
    assert Counter(d.rejected) - before == Counter(r for _, r in frames)
    assert (nb.seq, nb.t, nb.P, nb.P_dot, nb.count) == good
