"""Hypothesis strategies of bad wire frames, for the fuzz tests against the live daemon, coordinator and rig.

A frame is a valid message changed by one to three mutations (clients.bench.fuzz: bit flips, a field set to a
boundary -- 0, 2^31, 2^32, 2^53, 2^63, 2^64 - 1 and the like -- or to NaN / ±inf, a cut, bytes appended), kept only
if the protocol says its receiver refuses it (clients.bench.fuzz's verdicts, written from docs/protocol.md): a
mutation that leaves a valid frame is a valid frame, not a fuzz case.
"""

from __future__ import annotations

import struct

from hypothesis import assume
from hypothesis import strategies as st

from clients.bench.fuzz import (
    F64_EDGES,
    SPECS,
    U8_EDGES,
    U64_EDGES,
    decode_verdict,
    fuzz_verdict,
    grid_verdict,
    layout,
    mutate,
)

PLAUSIBLE = st.floats(1.0, 100.0)


def mutations(kind: str, frame: bytes):
    """One to three mutations of a frame of this kind."""
    fields = layout(kind, frame)

    def edge(field):
        name, c, _ = field
        return st.sampled_from(F64_EDGES if c == "d" else U64_EDGES if c == "Q" else U8_EDGES).map(
            lambda x: ("set", name, x))

    one = st.one_of(st.integers(0, 8 * len(frame) - 1).map(lambda b: ("flip", b)),
                    st.sampled_from(fields).flatmap(edge),
                    st.integers(0, len(frame) - 1).map(lambda n: ("cut", n)),
                    st.binary(min_size=1, max_size=9).map(lambda b: ("grow", b)))
    return st.lists(one, min_size=1, max_size=3)


@st.composite
def bad_meas(draw, seq_max: int, v_range: tuple[float, float], i_max: float, period_s: float):
    """(frame, (REJECTED, reason)) for a controller past sample seq_max: a valid measurement of a seq it has passed,
    mutated until the controller rejects it (clients.bench.fuzz.fuzz_verdict)."""
    seq = draw(st.integers(1, seq_max))
    base = struct.pack(SPECS["meas"][1], 0xE1, 1, seq, seq * period_s, draw(PLAUSIBLE), draw(st.floats(70.0, 90.0)),
                       draw(st.floats(70.0, 90.0)), draw(PLAUSIBLE))
    frame = mutate("meas", base, draw(mutations("meas", base)))
    verdict = fuzz_verdict(frame, v_range, i_max, seq_max)
    assume(verdict is not None)
    return frame, verdict


@st.composite
def bad_fixed(draw, kind: str, prefix: str):
    """(frame, reason) of a kind the receiver only decodes (a neighbour's z, a command at the rig): a valid message
    mutated until it does not decode."""
    _, fmt, names = SPECS[kind]
    vals = [draw(st.integers(0, 10**6)) if c == "Q" else draw(st.booleans()) if c == "B" else draw(PLAUSIBLE)
            for c in fmt[3:]]
    base = struct.pack(fmt, SPECS[kind][0], 1, *vals)
    frame = mutate(kind, base, draw(mutations(kind, base)))
    reason = decode_verdict(kind, frame, prefix)
    assume(reason is not None)
    return frame, reason


@st.composite
def bad_grid(draw, sizes: tuple[int, int, int], T: float, v_nom: float, seq_max: int):
    """A grid sample the coordinator refuses after sample seq_max: a plausible one of a passed seq, mutated."""
    ns, nb, nl = sizes
    seq = draw(st.integers(1, seq_max))
    vals = ([draw(st.floats(0.9 * v_nom, 1.1 * v_nom)) for _ in range(ns)] + [draw(PLAUSIBLE) for _ in range(ns)]
            + [1.0] * ns + [draw(st.floats(0.9 * v_nom, 1.1 * v_nom)) for _ in range(nb)]
            + [draw(st.floats(0.0, 1e4)) for _ in range(nl)])
    base = struct.pack("<BBQdHHH", 0x47, 1, seq, seq * T, ns, nb, nl) + struct.pack(f"<{len(vals)}d", *vals)
    frame = mutate("grid", base, draw(mutations("grid", base)))
    assume(grid_verdict(frame, sizes, T, v_nom, seq_max) is not None)
    return frame
