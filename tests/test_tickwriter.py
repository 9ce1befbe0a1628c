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
from mcap.reader import make_reader

from schemas.codec import CMD, MEAS, VERSION

pytest.importorskip("service.fastcore", reason="compiled core not built (no C compiler)")

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
    from clients.bench_tick import _trace, drive_daemon

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
    from service.shmlog import _HDR, SLOT

    return bytearray(_HDR.size + slots * SLOT)


def test_the_tick_writers_slot_is_offer_groups_and_a_full_ring_is_a_drop():
    from array import array

    from service._kernel import TickWriter

    from schemas.codec import TICK_IN
    from schemas.scenario import load_scenario
    from service.fastcore import CompiledCore
    from service.shmlog import _HDR, GROUP_BASE, SLOT

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
