"""Wire fuzzing of the live daemon (issue 30): bad measurement frames (tests/wire_fuzz.py: valid ones with bit
flips, fields at their boundaries, NaN and ±inf, cuts) put on the plant's key with Zenoh's own put, between the
samples of a running stack, lockstep and realtime. The loop keeps ticking, every bad frame is counted under the
reason the protocol gives it, no command follows one (a held frame gets its hold, nothing else), status keeps
answering; in lockstep v stays within ±2 % of v_ref. A neighbour's bad interaction messages, in-process.

Loopback, free ports, multicast scouting off, every process stopped (clients.bench.recovery.Rig). The 100 000-frame
figure is a bench: energyctl bench fuzz (docs/benchmarks.md)."""

from __future__ import annotations

import struct
from collections import Counter

import pytest
from conftest import SCENARIOS, RingStub
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from wire_fuzz import bad_fixed, bad_meas

from clients.bench.fuzz import HELD
from clients.bench.recovery import Rig
from clients.commands.demo import DEMO_REALTIME_DELAY, DEMO_REALTIME_HZ, DEMO_REALTIME_SETS
from clients.live import wait_until
from schemas.codec import CMD, MEAS
from schemas.scenario import load_scenario

SEQ_MAX = 100  # fuzz frames carry seqs the plant has passed before fuzzing starts (bit flips may move them)
V_REF, V_RANGE, I_MAX = 80.0, (1.0, 1000.0), 1000.0  # the shipped config's meas_v_min_V, meas_v_max_V, meas_i_max_A
# live examples: each a batch of frames against the one stack; generated only (a live run cannot be replayed to
# shrink), few enough for CI
LIVE = settings(max_examples=50, deadline=None, phases=[Phase.explicit, Phase.generate],
                suppress_health_check=list(HealthCheck))


class FuzzedStack:
    """A running stack (Rig: controller, load, plant) and the fuzzer beside it: its own publisher on the plant's key,
    and every command the controller sends from the start of fuzzing on."""

    def __init__(self, rig: Rig, period_s: float):
        self.rig, self.period_s = rig, period_s
        st0 = rig.wait_status(lambda s: (s.get("last_sample") or {}).get("seq", 0) > 2 * SEQ_MAX, 60.0)
        assert st0 is not None, "the stack did not start"
        assert st0["rejected"] == {}
        self.cmds: list[tuple] = []
        s = rig.session()
        self.sub = s.declare_subscriber("energyctl/source/cmd", lambda m: self.cmds.append(
            CMD.decode(m.payload.to_bytes())))
        import zenoh

        self.pub = s.declare_publisher("energyctl/source/meas", congestion_control=zenoh.CongestionControl.BLOCK)
        self.want: Counter = Counter()  # every bad frame sent, by the reason the protocol gives it
        self.holds: Counter = Counter()  # (seq, t) of the held ones: their hold commands
        self.sent = 0

    def send(self, frames: list[tuple[bytes, tuple[str, str]]]) -> dict:
        """Put the frames, wait until the controller counted them, check what the module docstring says; its status."""
        for frame, (kind, reason) in frames:
            self.pub.put(frame)
            self.want[reason] += 1
            if kind == HELD:
                self.holds[struct.unpack_from("<Qd", frame, 2)] += 1
        self.sent += len(frames)
        st = self.rig.wait_status(lambda s: Counter(s["rejected"]) == self.want, 20.0)
        assert st is not None, (Counter((self.rig.status() or {}).get("rejected")) - self.want,
                                self.want - Counter((self.rig.status() or {}).get("rejected")))
        assert st["state"] == "active" and not st.get("failure")
        assert st["loop"]["lockstep_timeouts"] == 0
        # no command follows a bad frame: in the fuzz frames' seqs, only the holds of the held ones
        assert wait_until(lambda: self._fuzz_cmds() == self.holds, 5.0), (self._fuzz_cmds(), self.holds)
        assert all(c[2:] == (0.0, 0.0, 1) for c in self.cmds if c[0] <= SEQ_MAX)
        real = [c[0] for c in self.cmds if c[0] > SEQ_MAX]
        assert len(real) == len(set(real))  # and the plant's samples got one answer each
        return st

    def _fuzz_cmds(self) -> Counter:
        return Counter(c[:2] for c in list(self.cmds) if c[0] <= SEQ_MAX)


def fuzzed_stack(tmp_path_factory, lockstep: bool):
    """Lockstep at the scenario's 10 kHz; realtime as energyctl demo --realtime runs it (2 kHz, its settings and its
    16-sample schedule: with a 1-sample one the stack diverged here under the fuzzer's load, and every later sample
    was held out of range). catch_up 256: the loop answers every queued frame in order (a batch of fuzz frames and the
    samples around it); with 1 a fuzz frame queued after a sample hid it from the loop, and one before it was never
    looked at."""
    rt = {} if lockstep else {"rate_hz": DEMO_REALTIME_HZ, "controller_delay": DEMO_REALTIME_DELAY}
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml", [] if lockstep else DEMO_REALTIME_SETS)
    rig = Rig(scn, tmp_path_factory.mktemp("fuzz"), lockstep=lockstep, duration_s=600.0,
              comp={"loop": {"catch_up": 256}}, **rt)
    return rig, 1.0 / rig.cfg["daemon"]["loop"]["rate_hz"]


@pytest.fixture(scope="module")
def lockstep(tmp_path_factory):
    rig, T = fuzzed_stack(tmp_path_factory, lockstep=True)
    with rig:
        for name in ("daemon", "load", "plant"):
            rig.start(name)
        stack = FuzzedStack(rig, T)
        yield stack
        stack.sub.undeclare()
        out = rig.close()
    check_the_end(out)


@pytest.fixture(scope="module")
def realtime(tmp_path_factory):
    rig, T = fuzzed_stack(tmp_path_factory, lockstep=False)
    with rig:
        for name in ("daemon", "load", "plant"):
            rig.start(name)
        stack = FuzzedStack(rig, T)
        yield stack
        stack.sub.undeclare()
        out = rig.close()
    check_the_end(out)


def check_the_end(out: dict) -> None:
    """Stopped with SIGTERM: every process ended cleanly, none printed a traceback, the controller never failed."""
    for name, (rc, _so, se) in out.items():
        assert rc == 0 and "Traceback" not in se, (name, rc, se[-2000:])


@LIVE
@given(frames=st.lists(bad_meas(SEQ_MAX, V_RANGE, I_MAX, 1e-4), min_size=1, max_size=40))
def test_bad_frames_between_lockstep_samples_are_counted_and_change_nothing(lockstep, frames):
    st = lockstep.send(frames)
    v = st["last_sample"]["v"]
    assert abs(v - V_REF) <= 0.02 * V_REF, v  # still regulated, at the newest sample


@LIVE
@given(frames=st.lists(bad_meas(SEQ_MAX, V_RANGE, I_MAX, 5e-4), min_size=1, max_size=40))
def test_bad_frames_between_realtime_samples_are_counted_and_change_nothing(realtime, frames):
    st = realtime.send(frames)
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
