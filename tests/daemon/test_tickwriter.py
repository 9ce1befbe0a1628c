"""The compiled stepped tick (service._kernel.TickWriter) is the daemon's Python lines, byte for byte.

With the compiled core, a stepped tick's kernel step, command payload, loop-delay history entry and recorder slot
(meas, z_in and cmd grouped) are one C call. The same daemon with the TickWriter taken away runs the Python lines
(core.step_values, the CMD struct, _remember, RingRecorder.offer_group). Driven through the same samples, including
rejected, held and skipped ones, both must publish the same bytes, keep the same history and write the same log.
"""

from __future__ import annotations

import functools
import struct

import pytest
from conftest import ROOT
from hypothesis import example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from schemas.codec import CMD, MEAS, VERSION

pytest.importorskip("service.core.compiled", reason="compiled core not built (no C compiler)")

N = 600


class Capture:
    def __init__(self):
        self.sent: list[bytes] = []

    def put(self, payload) -> None:
        self.sent.append(bytes(payload))


def _bad_samples(d, k: int, t: float) -> None:
    """Between ticks k - 1 and k: what the checks refuse (held or rejected; never stepped)."""
    if k == 200:
        d._tick(MEAS.encode(k - 1, t, 15.0, 80.0, 80.1, 15.0), 0)  # duplicate seq: rejected
    if k == 300:
        d._tick(MEAS.encode(10**6, t, 15.0, 500.0, 80.1, 15.0), 0)  # v out of range: held at du/dt = 0
    if k == 400:
        d._tick(b"\x00" * 7, 0)  # malformed: rejected


def _drive(tmp_path, name: str, compiled_tick: bool):
    from clients.bench.tick import _trace, drive_daemon

    scn, tr = _trace(str(ROOT / "clients" / "embedded" / "demo.toml"), N)
    skip = set(range(450, 455))  # samples the daemon never gets: a gap in the sequence, counted missing
    sent = Capture()

    def setup(d):
        assert d.core.impl == "c" and d._fast is not None  # the compiled core comes with the compiled tick
        if not compiled_tick:
            d._fast.close()
            d._fast = None
        d.cmd_pub = sent

    hooks = {0: setup}
    for k in (200, 300, 400):
        hooks[k] = functools.partial(_bad_samples, k=k, t=tr["t"][k - 1])
    log_dir = tmp_path / name
    log_dir.mkdir()
    hist = {}

    def keep_hist(d):
        hist["seq"], hist["u"], hist["r"] = list(d._hist_seq), list(d._hist_u), list(d._hist_r)

    hooks[N - 1] = keep_hist
    _times, st = drive_daemon(scn, tr, str(log_dir), hooks=hooks, skip=skip)
    with open(st["log_path"], "rb") as f:
        msgs = [(c.topic, m.log_time, m.data) for _s, c, m in make_reader(f).iter_messages()
                if c.topic.rsplit("/", 1)[-1] not in ("loop", "events")]  # those two hold wall-clock timings
    return sent.sent, hist, msgs, st


def test_the_compiled_tick_publishes_records_and_remembers_what_the_python_lines_do(tmp_path):
    sent_c, hist_c, log_c, st_c = _drive(tmp_path, "c", True)
    sent_p, hist_p, log_p, st_p = _drive(tmp_path, "py", False)
    assert len(sent_c) == N - 5 + 1  # every sample given answered, the held out-of-range one too (rejected: not)
    assert sent_c == sent_p
    assert hist_c == hist_p
    kinds = [topic.rsplit("/", 1)[-1] for topic, _t, _d in log_c]
    assert kinds.count("meas") == kinds.count("z_in") == kinds.count("cmd") == N - 5
    assert kinds.count("est") > 0 and kinds.count("z_out") > 0
    assert log_c == log_p
    assert st_c["loop"]["missing_samples"] == st_p["loop"]["missing_samples"] == 5
    assert st_c["rejected"] == st_p["rejected"] and sum(st_c["rejected"].values()) == 3
    assert st_c["logging"]["drops"] == st_p["logging"]["drops"] == {}
    loop = st_c["loop"]  # each tick's time split: the command's put, and the rest
    assert 0 < loop["publish_us"]["p50"] < loop["exec_us"]["p50"]
    assert 0 < loop["compute_us"]["p50"] < loop["exec_us"]["p50"]
    assert loop["compute_us"]["max"] <= loop["exec_us"]["max"]


def _ring(slots: int):
    from service.logio.ring import _HDR, SLOT

    return bytearray(_HDR.size + slots * SLOT)


def test_the_tick_writers_slot_is_offer_groups_and_a_full_ring_is_a_drop():
    from array import array

    from service._kernel import TickWriter

    from schemas.codec import TICK_IN
    from schemas.scenario import load_scenario
    from service.core.compiled import CompiledCore
    from service.logio.ring import _HDR, GROUP_BASE, SLOT

    scn = load_scenario(ROOT / "clients" / "embedded" / "demo.toml")
    core = CompiledCore(scn.controller, scn.model, 1e-4, 2)
    hs, hu, hr = array("q", [-1] * 8), array("d", [0.0] * 8), array("d", [0.0] * 8)
    fmt = "<Bd" + "".join(c.struct.format[3:] for c in (MEAS, TICK_IN, CMD))
    ring, wi = _ring(2), array("q", [0])
    tw = TickWriter(core._k, hs, hu, hr, CMD.struct.format, CMD.magic, VERSION, ring=ring, ring_index=wi, slots=2,
                    group_id=GROUP_BASE, group_format=fmt)
    x = (13, 0.0013, 15.0, 80.0, 80.15, 14.9, -1190.0, 2.5)
    cmd, du, du_next, limited, late, P_out, Qdot_out, dropped = tw.step(*x)
    assert not dropped and wi[0] == 1 and ring[_HDR.size] == 1
    assert cmd == CMD.encode(13, 0.0013, du, du_next, limited)
    want = struct.pack(fmt, GROUP_BASE, x[1], *x[:6], 13, x[1], x[6], x[7], True, 13, x[1], du, du_next, limited)
    assert bytes(ring[_HDR.size + 1:_HDR.size + 1 + len(want)]) == want
    assert (hs[13 & 7], hu[13 & 7], hr[13 & 7]) == (13, 80.15, du)
    assert P_out == core.out.est.P_r_out_port and Qdot_out == core.out.est.Qdot_r_out_port
    tw.step(14, 0.0014, *x[2:])
    before = bytes(ring)
    *_, dropped = tw.step(15, 0.0015, *x[2:])  # both slots full (nobody empties this ring)
    assert dropped and wi[0] == 2 and bytes(ring) == before
    ring[17] = 1  # the writer failed: nothing offered, nothing counted
    ring[_HDR.size] = ring[_HDR.size + SLOT] = 0
    *_, dropped = tw.step(16, 0.0016, *x[2:])
    assert not dropped and wi[0] == 2
    tw.close()
    with pytest.raises(RuntimeError, match="released"):
        tw.step(*x)
    with pytest.raises(ValueError, match="layout"):
        TickWriter(core._k, hs, hu, hr, "<BBQddd", CMD.magic, VERSION)
    with pytest.raises(ValueError, match="group layout"):
        TickWriter(core._k, hs, hu, hr, CMD.struct.format, CMD.magic, VERSION, ring=ring, ring_index=wi, slots=2,
                   group_id=GROUP_BASE, group_format="<Bd")


def _accept_writer():
    from array import array

    from service._kernel import TickWriter

    from schemas.scenario import load_scenario
    from service.core.compiled import CompiledCore

    scn = load_scenario(ROOT / "clients" / "embedded" / "demo.toml")
    core = CompiledCore(scn.controller, scn.model, 1e-4, 2)
    hist = array("q", [-1] * 8), array("d", [0.0] * 8), array("d", [0.0] * 8)
    r = MEAS.half_open_ranges()
    return TickWriter(core._k, *hist, CMD.struct.format, CMD.magic, VERSION, meas_format=MEAS.struct.format,
                      meas_magic=MEAS.magic, v_min=10.0, v_max=150.0, i_max=60.0, seq_limit=r["seq"][1],
                      t_min=r["t"][0], t_limit=r["t"][1]), core


def _python_would_step(payload: bytes, last_seq: int, last_t: float):
    """What Daemon._checked steps on, for a daemon past its first sample (limits as in _accept_writer)."""
    from schemas.codec import DecodeError

    try:
        v = MEAS.decode(payload)
    except DecodeError:
        return None
    if not 10.0 <= v[3] <= 150.0 or abs(v[2]) > 60.0 or abs(v[5]) > 60.0:
        return None
    if v[0] == 0 and last_seq > 0:
        return None  # a restart: _checked re-initialises, accept leaves it to _checked
    if v[0] <= last_seq or v[1] <= last_t:
        return None
    return v


_any = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-200.0, 200.0))


@settings(max_examples=400, deadline=None)
@example(seq=5, t=0.5, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # time not advancing
@example(seq=4, t=0.6, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # duplicate seq
@example(seq=0, t=0.6, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # restart
@example(seq=5, t=0.6, i=60.0, v=150.0, u=80.0, il=-60.0, last_seq=4, last_t=0.5, damage="")  # on the limits
@example(seq=5, t=0.6, i=1.0, v=150.00000000000003, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # just off
@example(seq=2**63, t=0.6, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # beyond int64
@example(seq=2**53, t=0.6, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # not exact as a double
@example(seq=2**53 - 1, t=0.6, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # the largest seq
@example(seq=5, t=-0.25, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=-0.5, damage="")  # a time before 0
@example(seq=5, t=2.0**32, i=1.0, v=80.0, u=80.0, il=1.0, last_seq=4, last_t=0.5, damage="")  # beyond the time range
@given(seq=st.integers(0, 2**64 - 1) | st.integers(0, 50) | st.sampled_from([2**53 - 1, 2**53]),
       t=_any | st.sampled_from([0.0, -0.0, -5e-324, 2.0**32, 2.0**32 - 2.0**-20]), i=_any, v=_any, u=_any, il=_any,
       last_seq=st.integers(-1, 40), last_t=st.floats(-1.0, 1.0), damage=st.sampled_from(["", "magic", "version",
                                                                                          "short", "long"]))
def test_accept_takes_exactly_the_samples_the_python_checks_step_on(seq, t, i, v, u, il, last_seq, last_t, damage):
    tw, _core = _accept_writer()
    payload = bytearray(MEAS.struct.pack(MEAS.magic, VERSION, seq, t, i, v, u, il))
    if damage == "magic":
        payload[0] ^= 0xFF
    elif damage == "version":
        payload[1] = VERSION + 1
    elif damage == "short":
        payload = payload[:-1]
    elif damage == "long":
        payload += b"\x00"
    payload = bytes(payload)
    got = tw.accept(payload, last_seq, last_t)
    # None leaves it to _checked: always right, and what accept does for the first sample
    want = _python_would_step(payload, last_seq, last_t) if last_seq >= 0 else None
    assert got == want
    if got is not None:
        assert type(got[0]) is int and got == MEAS.decode(payload)  # the very tuple decode gives


def test_the_compiled_tick_answers_a_seq_above_2_to_the_53_with_that_seq():
    """The command's seq is the sample's, exactly: the tick carried it as a double, so 2^53 + 1 went out as 2^53 (the
    plant then took the answer for another sample). The wire bound (schemas.codec: seq < 2^53) keeps such a sample
    out of a daemon; the tick itself no longer depends on it."""
    from array import array

    from service._kernel import Kernel, TickWriter

    from schemas.scenario import Scenario
    from service.core import make_core

    scn = Scenario()
    core = make_core(scn.controller, scn.model, 1e-4, 2, "c")
    k = core._k
    assert isinstance(k, Kernel)
    hist = (array("q", [-1] * 8), array("d", [0.0] * 8), array("d", [0.0] * 8))
    tw = TickWriter(k, *hist, CMD.struct.format, CMD.magic, VERSION, seq_limit=2**53)
    for seq in (2**53 + 1, 2**53 + 2, 2**53 + 3):
        payload = tw.step(seq, 1.0, 15.0, 80.0, 80.15, 15.0, -1200.0, 0.0)[0]
        assert struct.unpack_from("<Q", payload, 2)[0] == seq  # the command layout: magic, version, seq
        assert hist[0][seq & 7] == seq and core.out.seq == seq
