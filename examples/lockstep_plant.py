#!/usr/bin/env python3
"""A minimal lockstep hardware-in-the-loop plant for an energyctl controller, written from docs/protocol.md alone.

The paper's circuit: a source voltage u behind R-L, a capacitor C at the terminal, and a constant-power load:
    L di/dt = u - R i - v,   C dv/dt = i - i_load,   i_load = P / v,   du/dt = the commanded rate (held a period)
For each sample k it publishes the neighbour's interaction message (seq k) and the measurement k, waits for the
command answering k, and integrates one period with RK4 at that du/dt. Imports only zenoh and the standard library.

    python examples/lockstep_plant.py --connect tcp/127.0.0.1:7447 --seconds 0.5
"""

import argparse
import json
import math
import queue
import struct
import sys
import time

import zenoh

VERSION = 1
MEAS = struct.Struct("<BBQddddd")  # 0xE1, version, seq, t, i, v, u, i_load: 50 bytes
CMD = struct.Struct("<BBQdddB")  # 0xC1, version, seq, t, du_dt, du_dt_next, limited: 35 bytes
Z = struct.Struct("<BBQddddddQdddd")  # 0x21, version, seq, t, P, P_dot, Qdot, z0, z1, window, box: 98 bytes


def args_parser() -> argparse.ArgumentParser:
    a = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    a.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the controller's Zenoh endpoint")
    a.add_argument("--prefix", default="energyctl")
    a.add_argument("--id", default="source", help="the controller's id (its .../meas, .../cmd, .../alive)")
    a.add_argument("--neighbour", default="load", help="the load's id, whose .../z this plant publishes ('': none)")
    a.add_argument("--seconds", type=float, default=0.5)
    a.add_argument("--rate", type=float, default=10000.0, help="sample rate, Hz: the controller's loop.rate_hz")
    a.add_argument("--step", type=float, default=1e-5, help="RK4 sub-step, s")
    a.add_argument("--window", type=float, default=0.1, help="the controller's forecast_window_s")
    a.add_argument("--R", type=float, default=0.01, help="ohm")
    a.add_argument("--L", type=float, default=1.12e-3, help="H")
    a.add_argument("--C", type=float, default=6.8e-3, help="F")
    a.add_argument("--load-W", type=float, default=1200.0)
    a.add_argument("--v-ref", type=float, default=80.0)
    a.add_argument("--i0", type=float, default=1.0)
    a.add_argument("--v0", type=float, default=80.0)
    a.add_argument("--u-min", type=float, default=0.0)
    a.add_argument("--u-max", type=float, default=200.0)
    a.add_argument("--timeout", type=float, default=2.0, help="wait this long for each command, s")
    a.add_argument("--wait", type=float, default=15.0, help="wait this long for the controller, s")
    return a


def i_load(P: float, v: float, v_min: float = 5.0) -> float:
    return P / v if v >= v_min else P * v / (v_min * v_min)  # resistive below v_min (keeps the RK4 finite)


def advance(x: tuple, r: float, T: float, n: int, a) -> tuple:
    """(i, v, u) after T seconds at du/dt = r, n RK4 steps; u stays in [u_min, u_max]."""
    i, v, u = x
    h = T / n

    def f(i, v, u):
        return (u - a.R * i - v) / a.L, (i - i_load(a.load_W, v)) / a.C

    for _ in range(n):
        um, u1 = (min(max(u + r * s, a.u_min), a.u_max) for s in (h / 2, h))
        k1 = f(i, v, u)
        k2 = f(i + h / 2 * k1[0], v + h / 2 * k1[1], um)
        k3 = f(i + h / 2 * k2[0], v + h / 2 * k2[1], um)
        k4 = f(i + h * k3[0], v + h * k3[1], u1)
        i += h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v += h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        u = u1
    return i, v, u


def open_session(endpoint: str) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    # a port of its own on loopback: a third process (a load that answers these measurements) links to it directly;
    # the daemon does not route between its peers, and a peer that listens nowhere is reached by nobody else
    cfg.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def wait_for(cond, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.01)
    return False


def main() -> int:
    a = args_parser().parse_args()
    T, base = 1.0 / a.rate, f"{a.prefix}/{a.id}"
    n_sub, N = max(1, math.ceil(T / a.step - 1e-9)), int(round(a.seconds * a.rate))
    s = open_session(a.connect)
    try:
        cmds: queue.Queue = queue.Queue()
        sub = s.declare_subscriber(f"{base}/cmd", lambda smp: cmds.put(smp.payload.to_bytes()))  # before sample 0
        pubs = {"meas": s.declare_publisher(f"{base}/meas", express=True)}
        if a.neighbour:
            pubs["z"] = s.declare_publisher(f"{a.prefix}/{a.neighbour}/z", express=True)
        # ready: the controller's liveliness token, then its subscribers matched (else sample 0 may go nowhere)
        alive = lambda: any(r.ok is not None for r in s.liveliness().get(f"{base}/alive", timeout=0.5))  # noqa: E731
        if not wait_for(alive, a.wait) or not wait_for(lambda: all(p.matching_status.matching
                                                                    for p in pubs.values()), a.wait):
            print(f"no controller {a.id!r} ready at {a.connect}", file=sys.stderr)
            return 1
        x = (a.i0, a.v0, a.v0 + a.R * a.i0)  # (i, v, u), u at its equilibrium for i0
        plan, counts, vs, z0 = None, {"samples": 0, "commands": 0, "timeouts": 0, "rejected": 0}, [], 0.0
        for k in range(N):
            t = k * T
            i, v, u = x
            if a.neighbour:  # the load's P^{r,out} = +P (absorbed), seq = k: what the lockstep controller waits for
                w = int(t // a.window) + (1 if t % a.window >= a.window / 2 else 0)
                P, m = a.load_W, 0.05 * abs(a.load_W)
                pubs["z"].put(Z.pack(0x21, VERSION, k, t, P, 0.0, 0.0, z0, 0.0, w, P - m, P + m, 0.0, 0.0))
                z0 += P * T
            pubs["meas"].put(MEAS.pack(0xE1, VERSION, k, t, i, v, u, i_load(a.load_W, v)))
            counts["samples"] += 1
            r, deadline = None, time.monotonic() + a.timeout
            while r is None and (left := deadline - time.monotonic()) > 0:
                try:
                    b = cmds.get(timeout=left)
                except queue.Empty:
                    break
                if len(b) != CMD.size or b[0] != 0xC1 or b[1] != VERSION:
                    counts["rejected"] += 1
                    continue
                _, _, seq, _, du, du_next, _ = CMD.unpack(b)
                if seq == k and math.isfinite(du) and math.isfinite(du_next):
                    r, plan = du, (k, du_next)
                # anything else answers an older sample (or is a repeat): not this period's command
            if r is None:  # missing: the previous command's plan for this period, else hold u
                counts["timeouts"] += 1
                r, plan = (plan[1] if plan is not None and plan[0] == k - 1 else 0.0), None
            else:
                counts["commands"] += 1
            vs.append((t, v))
            x = advance(x, r, T, n_sub, a)
        held = [abs(v - a.v_ref) / a.v_ref for t, v in vs if t >= 0.05]
        out = {**counts, "v_min": min(v for _, v in vs), "v_max": max(v for _, v in vs),
               "max_dev_after_50ms_pct": 100 * max(held) if held else None}
        print(json.dumps(out), flush=True)
        sub.undeclare()
        return 0 if counts["timeouts"] == 0 else 1
    finally:
        s.close()


if __name__ == "__main__":
    sys.exit(main())
