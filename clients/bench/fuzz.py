"""Wire fuzzing: bad frames built from valid ones, what the protocol says each gets, and ``energyctl bench fuzz``.

Frames are valid messages changed by mutations: ``("flip", bit)`` flips one bit, ``("set", field, value)`` writes a
field with its wire type (the boundaries below, NaN, ±inf), ``("cut", n)`` keeps the first n bytes, ``("grow", b)``
appends bytes. Which of them are bad, and what a receiver does with each, comes from the protocol as docs/protocol.md
states it (sizes, magics, finiteness, the admissible ranges, the daemon's checks), written out here on purpose rather
than taken from the decoders they check (schemas.codec).

The property tests (tests/wire_fuzz.py) draw mutations with hypothesis; the bench draws them with a seeded
``random.Random``: frames sent between the samples of a live lockstep stack, every one of them bad, and then whether
the loop kept ticking, every frame was counted under the reason the protocol gives it, no command followed one, and v
stayed within ±2 % of v_ref.
"""

from __future__ import annotations

import json
import math
import random
import struct
from collections import Counter

# the boundary values a field is set to: those of the issue (0, 2^31, 2^32, 2^53, 2^63, 2^64 - 1), around the
# admissible ranges' ends, and the non-finite ones
U64_EDGES = (0, 1, 2**31, 2**32, 2**53 - 1, 2**53, 2**63, 2**64 - 1)
F64_EDGES = (0.0, -0.0, 5e-324, -1.0, 2.0**31, 2.0**32, 2.0**53, 2.0**63, 2.0**64, 1.7976931348623157e308,
             -1.7976931348623157e308, math.nan, math.inf, -math.inf)
U8_EDGES = (0, 1, 2, 255)
SEQ_LIMIT, T_LIMIT = 2**53, 2.0**32  # docs/protocol.md, "Admissible ranges"

# the fixed-size messages as docs/protocol.md lays them out: magic, struct format, field names
SPECS = {
    "meas": (0xE1, "<BBQddddd", ("seq", "t", "i", "v", "u", "i_load")),
    "cmd": (0xC1, "<BBQdddB", ("seq", "t", "du_dt", "du_dt_next", "limited")),
    "z": (0x21, "<BBQddddddQdddd", ("seq", "t", "P_r_out", "P_r_out_dot", "Qdot_r_out", "z_out0", "z_out1", "window",
                                    "P_min", "P_max", "P_dot_min", "P_dot_max")),
}
GRID_HEAD = "<BBQdHHH"  # magic 0x47, version, seq, t, then the counts n_s, n_b, n_l; then 3 n_s + n_b + n_l f64


def layout(kind: str, frame: bytes | None = None) -> list[tuple[str, str, int]]:
    """(field, struct code, offset) of every field of a message kind, the header bytes included; for ``grid`` those
    of this frame (its counts say how many values follow)."""
    if kind == "grid":
        _, _, _, _, ns, nb, nl = struct.unpack_from(GRID_HEAD, frame)
        names = (["magic", "version", "seq", "t", "n_s", "n_b", "n_l"]
                 + [f"{a}[{j}]" for a, n in (("v", ns), ("i_out", ns), ("connected", ns), ("bus_v", nb),
                                              ("load_P", nl)) for j in range(n)])
        fmt = GRID_HEAD[1:] + "d" * (3 * ns + nb + nl)
    else:
        names, fmt = ["magic", "version", *SPECS[kind][2]], SPECS[kind][1][1:]
    out, off = [], 0
    for name, c in zip(names, fmt, strict=True):
        out.append((name, c, off))
        off += struct.calcsize("<" + c)
    return out


def mutate(kind: str, frame: bytes, mutations) -> bytes:
    """The frame with the mutations applied in order (a mutation out of the frame's bytes, after a cut, is skipped)."""
    fields = {name: (c, off) for name, c, off in layout(kind, frame)}
    b = bytearray(frame)
    for m in mutations:
        if m[0] == "flip" and m[1] // 8 < len(b):
            b[m[1] // 8] ^= 1 << (m[1] % 8)
        elif m[0] == "set" and m[1] in fields:
            c, off = fields[m[1]]
            if off + struct.calcsize("<" + c) <= len(b):
                x = m[2]
                if c == "d":
                    x = float(x)
                else:  # an integer of the wire type: edges beyond it wrap, a float becomes its integer bits
                    x = int(x) if not isinstance(x, float) else struct.unpack("<Q", struct.pack("<d", x))[0]
                    x &= (1 << (8 * struct.calcsize("<" + c))) - 1
                struct.pack_into("<" + c, b, off, x)
        elif m[0] == "cut":
            del b[m[1]:]
        elif m[0] == "grow":
            b += m[1]
    return bytes(b)


def decode_verdict(kind: str, frame: bytes, prefix: str) -> str | None:
    """The rejection a receiver names for a frame of a fixed-size kind (``prefix.<field>: invalid``), checked in the
    protocol's order: size, magic, version, every f64 finite, every field in its admissible range; None if it
    decodes."""
    magic, fmt, names = SPECS[kind]
    if len(frame) != struct.calcsize(fmt):
        return f"{prefix}.<payload>: invalid"
    vals = struct.unpack(fmt, frame)
    if vals[0] != magic:
        return f"{prefix}.<magic>: invalid"
    if vals[1] != 1:
        return f"{prefix}.<version>: invalid"
    codes = fmt[3:]
    for name, c, x in zip(names, codes, vals[2:], strict=True):
        if c == "d" and not math.isfinite(x):
            return f"{prefix}.{name}: invalid"
    for name, c, x in zip(names, codes, vals[2:], strict=True):
        bad = ((c == "Q" and x >= SEQ_LIMIT) or (name == "t" and not 0.0 <= x < T_LIMIT)
               or (c == "B" and x not in (0, 1)))
        if bad:
            return f"{prefix}.{name}: invalid"
    return None


REJECTED, HELD = "rejected", "held"


def meas_verdict(frame: bytes, v_range: tuple[float, float], i_max: float, last_seq: int) -> tuple[str, str] | None:
    """What the controller does with a measurement (docs/protocol.md, "What the daemon does with each input"), after
    accepting samples up to ``last_seq`` (>= 1): (REJECTED, reason) — no answer —, (HELD, reason) — answered with a
    hold —, or None: a sample it steps on (the next one, a gap, or seq 0: the plant restarting), not a bad frame."""
    why = decode_verdict("meas", frame, "meas")
    if why is not None:
        return REJECTED, why
    seq, _t, i, v, _u, i_load = struct.unpack(SPECS["meas"][1], frame)[2:]
    if 0 < seq <= last_seq:
        return REJECTED, "meas.seq: duplicate or not increasing"
    if not v_range[0] <= v <= v_range[1]:
        return HELD, "meas.v: out of range"
    if abs(i) > i_max or abs(i_load) > i_max:
        return HELD, f"meas.{'i' if abs(i) > i_max else 'i_load'}: out of range"
    return None


def fuzz_verdict(frame: bytes, v_range: tuple[float, float], i_max: float, seq_max: int) -> tuple[str, str] | None:
    """meas_verdict for a fuzz frame beside a running stack past sample seq_max, and None for a held one too: that is
    a sample of a new seq (0, or one the plant has not sent yet) with values out of range, and the protocol answers
    it (a lockstep plant would take that hold for its own sample), and the load stand-in, which follows the
    measurements' seq and t (not their v: it knows no controller's ranges), would take it for a restart or a jump
    ahead. A held frame is the plausibility of a sample, not a range a decoder checks (tests/daemon/test_bad_input.py
    holds them); every frame this keeps is rejected without an answer."""
    verdict = meas_verdict(frame, v_range, i_max, seq_max)
    return None if verdict is None or verdict[0] == HELD else verdict


def grid_verdict(frame: bytes, sizes: tuple[int, int, int], T: float, v_nom: float, last_seq: int) -> str | None:
    """Why the coordinator refuses a grid sample after taking samples up to ``last_seq`` (>= 1): malformed, non-finite,
    out of its admissible range, not the scenario's counts, t not seq x T, implausible values (schema checks and the
    coordinator's: v and bus_v within [0, 2.5 v_nom], |i_out| <= 1e4 A, |load_P| <= 1e7 W), or an old seq; None for
    one it takes (a later seq, or 0: the rig restarting)."""
    h = struct.calcsize(GRID_HEAD)
    if len(frame) < h:
        return "grid.<payload>: invalid"
    magic, version, seq, t, ns, nb, nl = struct.unpack_from(GRID_HEAD, frame)
    if magic != 0x47:
        return "grid.<magic>: invalid"
    if version != 1:
        return "grid.<version>: invalid"
    if len(frame) != h + 8 * (3 * ns + nb + nl):
        return "grid.<payload>: invalid"
    vals = struct.unpack_from(f"<{3 * ns + nb + nl}d", frame, h)
    if not math.isfinite(t) or not all(map(math.isfinite, vals)):
        return "grid: not finite"
    if seq >= SEQ_LIMIT or not 0.0 <= t < T_LIMIT:
        return "grid: out of its admissible range"
    if (ns, nb, nl) != sizes:
        return "grid: not the scenario's sizes"
    if abs(t - seq * T) > 0.5 * T:
        return "grid.t: not seq x T"
    v, i_out, bus_v, load_P = vals[:ns], vals[ns:2 * ns], vals[3 * ns:3 * ns + nb], vals[3 * ns + nb:]
    if (any(not 0.0 <= x <= 2.5 * v_nom for x in (*v, *bus_v)) or any(abs(x) > 1e4 for x in i_out)
            or any(abs(x) > 1e7 for x in load_P)):
        return "grid: implausible"
    if seq == 0 or seq > last_seq:
        return None
    return "grid.seq: not after the newest"


# ---------------------------------------------------------------- random frames (the bench)

def random_mutations(rng: random.Random, kind: str, frame: bytes) -> list:
    """One to three mutations of the kinds the property tests draw: bit flips, a field at a boundary or non-finite,
    a cut, bytes appended."""
    fields = layout(kind, frame)
    out = []
    for _ in range(rng.randint(1, 3)):
        what = rng.random()
        if what < 0.4:
            out.append(("flip", rng.randrange(8 * len(frame))))
        elif what < 0.85:
            name, c, _ = rng.choice(fields)
            out.append(("set", name, rng.choice(F64_EDGES if c == "d" else U64_EDGES if c == "Q" else U8_EDGES)))
        elif what < 0.95:
            out.append(("cut", rng.randrange(len(frame))))
        else:
            out.append(("grow", bytes(rng.randrange(256) for _ in range(rng.randint(1, 9)))))
    return out


def random_bad_meas(rng: random.Random, seq_max: int, v_range: tuple[float, float], i_max: float,
                    period_s: float) -> tuple[bytes, tuple[str, str]]:
    """A bad measurement for a controller past sample seq_max: a valid one of a seq it has passed (1..seq_max),
    mutated until the protocol says it is rejected or held (fuzz_verdict); with its verdict."""
    while True:
        seq = rng.randint(1, seq_max)
        base = struct.pack(SPECS["meas"][1], 0xE1, 1, seq, seq * period_s, rng.uniform(1.0, 30.0),
                           rng.uniform(70.0, 90.0), rng.uniform(70.0, 90.0), rng.uniform(1.0, 30.0))
        frame = mutate("meas", base, random_mutations(rng, "meas", base))
        verdict = fuzz_verdict(frame, v_range, i_max, seq_max)
        if verdict is not None:
            return frame, verdict


# ---------------------------------------------------------------- a live stack under fuzz (the tests and the bench)

class StackFuzzer:
    """A running stack (clients.bench.recovery.Rig: controller ``source``, its load and plant) and a fuzzer beside
    it: its own publisher on the plant's key (Zenoh's put, congestion control BLOCK: none of its frames is dropped on
    the way), and every command the controller sends from then on. Fuzz frames carry seqs up to ``seq_max``, which
    the plant has passed before fuzzing starts."""

    def __init__(self, rig, seq_max: int, after_seq: int | None = None, timeout_s: float = 60.0):
        """Starts once the plant is past sample after_seq (default 2 seq_max)."""
        import zenoh

        from schemas.codec import CMD

        self.rig, self.seq_max = rig, seq_max
        after = 2 * seq_max if after_seq is None else after_seq
        self.start = rig.wait_status(lambda s: (s.get("last_sample") or {}).get("seq", 0) > after, timeout_s)
        if self.start is None:
            raise RuntimeError(f"the stack did not pass sample {after} within {timeout_s:g} s")
        self.cmds: list[tuple] = []
        s = rig.session()
        self.sub = s.declare_subscriber("energyctl/source/cmd", lambda m: self.cmds.append(
            CMD.decode(m.payload.to_bytes())))
        self.pub = s.declare_publisher("energyctl/source/meas", congestion_control=zenoh.CongestionControl.BLOCK)
        self.want = Counter(self.start["rejected"])  # what the controller should have counted, by reason
        self.sent = 0

    def send(self, frames, timeout_s: float = 20.0) -> dict | None:
        """Put (frame, (kind, reason)) pairs; the controller's status once it counted each under its reason and
        every command it sent before has come (caught_up), None if that is not within timeout_s."""
        for frame, (_kind, reason) in frames:
            self.pub.put(frame)
            self.want[reason] += 1
        self.sent += len(frames)
        st = self.rig.wait_status(lambda s: Counter(s["rejected"]) == self.want, timeout_s)
        return st if st is not None and self.caught_up(st["last_sample"]["seq"], timeout_s) else None

    def caught_up(self, seq: int, timeout_s: float) -> bool:
        """Wait until the command of a plant sample after ``seq`` came: the controller put it after every command it
        may have put for a frame it had counted by then, on the same publisher, which Zenoh delivers in order."""
        from clients.live import wait_until

        return wait_until(lambda: any(c[0] > seq for c in reversed(self.cmds[-64:])), timeout_s)

    def commands_after_bad_frames(self) -> int:
        """Commands in the fuzz frames' seqs (the plant passed them before fuzzing): none may come."""
        return sum(1 for c in list(self.cmds) if c[0] <= self.seq_max)

    def answered_twice(self) -> int:
        """The plant's samples (after seq_max) answered more than once."""
        real = [c[0] for c in list(self.cmds) if c[0] > self.seq_max]
        return len(real) - len(set(real))

    def close(self) -> None:
        self.sub.undeclare()
        self.pub.undeclare()


def bench_fuzz(frames: int = 100_000, batch: int = 200, seed: int = 1, seq_max: int = 100, workdir: str | None = None,
               progress=None) -> dict:
    """``energyctl bench fuzz``: ``frames`` bad measurements (random_bad_meas) in batches of ``batch`` between the
    samples of the paper's constant-load stack in lockstep at 10 kHz, each batch waited for until the controller
    counted it. Reports frames sent against counted (by reason), the loop's deaths and the tracebacks of every
    process, commands that followed a bad frame, lockstep timeouts, v's largest deviation from v_ref after 50 ms (the
    plant's own trace), and the rate."""
    import signal
    import tempfile
    import time
    from pathlib import Path

    from clients.bench.recovery import Rig
    from clients.live import _last_json, wait_until
    from schemas.component import ComponentConfig, config_from_dict
    from schemas.scenario import load_scenario

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper-constant-load.toml")
    rng = random.Random(seed)
    base = Path(workdir or tempfile.mkdtemp(prefix="energyctl-fuzz-"))
    v_ref = scn.controller.v_ref_V
    out: dict = {"frames": frames, "batch": batch, "seed": seed, "rate_hz": scn.timing.control_rate_hz,
                 "pacing": "lockstep", "workdir": str(base)}
    with Rig(scn, base, lockstep=True, duration_s=600.0, comp={"loop": {"catch_up": 256}}) as rig:
        c = config_from_dict(ComponentConfig, rig.cfg["daemon"])
        v_range, i_max, T = (c.meas_v_min_V, c.meas_v_max_V), c.meas_i_max_A, 1.0 / c.loop.rate_hz
        for name in ("daemon", "load", "plant"):
            rig.start(name)
        fz = StackFuzzer(rig, seq_max, after_seq=round(0.05 / T))  # from 50 ms on: v settled (the plant's metric)
        t0, seq0 = time.monotonic(), fz.start["last_sample"]["seq"]
        st, lost_at = fz.start, None
        while fz.sent < frames:
            n = min(batch, frames - fz.sent)
            st = fz.send([random_bad_meas(rng, seq_max, v_range, i_max, T) for _ in range(n)])
            if st is None:
                lost_at = fz.sent
                break
            if progress is not None and fz.sent % (50 * batch) == 0:
                progress(f"{fz.sent} frames, sample {st['last_sample']['seq']}, v {st['last_sample']['v']:.3f} V")
        wall = time.monotonic() - t0
        last = rig.status() or st or {}
        out.update(wall_s=round(wall, 2), frames_per_s=round(fz.sent / wall), frames_sent=fz.sent,
                   samples_meanwhile=(last.get("last_sample") or {}).get("seq", seq0) - seq0,
                   counted_equal_sent=lost_at is None, counts_diverged_after=lost_at,
                   sent_by_reason=dict(fz.want), counted_by_reason=last.get("rejected"),
                   commands_after_bad_frames=fz.commands_after_bad_frames(), samples_answered_twice=fz.answered_twice(),
                   lockstep_timeouts=(last.get("loop") or {}).get("lockstep_timeouts"),
                   state_at_end=last.get("state"))
        fz.close()
        # the plant first, and given the time its end takes (metrics over the trace, its log closed): stopped with the
        # rest, after a long run it was killed before it printed them
        plant_proc = rig.proc("plant")
        plant_proc.send_signal(signal.SIGTERM)
        wait_until(lambda: plant_proc.poll() is not None, 120.0)
        procs = rig.close()
    plant = _last_json(procs.get("plant", (None, "", ""))[1])
    status = json.loads(rig.stats_path.read_text()) if rig.stats_path.exists() else {}
    daemon_err = procs.get("daemon", (None, "", ""))[2]
    # a loop thread that died: failed in the final status (it is caught now), or Python's "Exception in thread"
    out.update(loop_deaths=int(status.get("state") == "failed") + daemon_err.count("Exception in thread"),
               daemon_exit=procs.get("daemon", (None,))[0], daemon_final_state=status.get("state"),
               tracebacks={name: se.count("Traceback") for name, (_rc, _so, se) in procs.items()},
               plant_timeouts=(plant.get("counters") or {}).get("timeouts"),
               v_max_dev_after_50ms_pct=plant.get("max_dev_after_50ms_pct"), v_ref_V=v_ref,
               v_equals_offline_run=_equals_offline(scn, rig.plant_out), **_not_stepped(rig.daemon_log()))
    return out


def _not_stepped(log) -> dict:
    """The daemon log's ticks not stepped on (held: the neighbour's last message older than neighbour_stale_s of wall
    time, which a starved stack reaches in lockstep too) and its degraded events: what makes a lockstep run differ
    from the offline one without any bad frame changing a command."""
    from service.logio.reader import messages

    if log is None:
        return {}
    try:
        return {"ticks_not_stepped": sum(1 for m in messages(str(log), "/z_in") if not m["stepped"]),
                "degraded_events": sum(1 for e in messages(str(log), "/events") if e["kind"] == "degraded")}
    except (OSError, ValueError):
        return {}


def _equals_offline(scn, plant_log) -> bool | None:
    """Whether the plant's v, sample by sample, is the offline run's of the same length to 1e-9 (lockstep over Zenoh
    reproduces ``energyctl sim``: with no bad frame changing a command, the fuzzed run must too); None without a
    trace."""
    import numpy as np

    from service.logio.reader import messages
    from service.sim import run

    try:
        v = np.array([m["v"] for m in messages(str(plant_log), "/plant")])
    except (OSError, ValueError):
        return None
    if len(v) == 0:
        return None
    sim = run(scn.model_copy(update={"timing": scn.timing.model_copy(
        update={"duration_s": len(v) / scn.timing.control_rate_hz})})).trace["v"]
    n = min(len(v), len(sim))
    return bool(n > 0 and np.allclose(v[:n], sim[:n], rtol=1e-9, atol=0.0))
