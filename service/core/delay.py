"""The loop delay, measured: which of its past commands moved the measured source voltage.

The plant holds each du/dt over one sampling period (a zero-order hold of the voltage rate), so with a loop
delay of d samples the measured source voltage obeys

    u_{k+1} - u_k = T r_{k-d}        (V; r_k = du/dt answering sample k, V/s; T the period, s)

The estimate is the d that minimises  S_j = sum_k (Delta u_k / T - r_{k-j})^2  over a window (least squares,
one candidate per delay). Sensor noise on u adds the same amount to every S_j, so it only costs resolution;
steady commands (all r alike) make every candidate fit equally, and the estimate then says so instead of
guessing. A command that never acted (lost, late: the source held, r = 0) counts against every candidate.

Pure functions over arrays: the daemon keeps the history (two stores per tick on its loop thread) and its
status query calls this; ``energyctl log info`` calls it on a log.
"""

from __future__ import annotations

import numpy as np


def estimate_loop_delay(u_V, du_dt_V_per_s, T_s: float, max_delay: int = 8, min_contrast: float = 0.5) -> dict:
    """Loop delay in samples from consecutive samples' measured u (V) and the du/dt answering each (V/s).

    Returns {"samples": d or None, "explained": 1 - S_d / sum (x - mean x)^2 (the part of the measured rate
    the delayed commands explain), "contrast": 1 - S_d / S_second (how much better d fits than the next
    best), "n": samples used, "sse": [S_0, ...] normalised by n}. ``samples`` is None when fewer than
    4 * (max_delay + 1) rows can be formed, or when contrast < min_contrast (commands too steady to tell).
    """
    u = np.asarray(u_V, dtype=float)
    r = np.asarray(du_dt_V_per_s, dtype=float)
    n = len(u) - 1 - max_delay  # rows k = max_delay .. len-2: Delta u_k and r_{k-j} for every j
    res: dict = {"samples": None, "explained": None, "contrast": None, "n": max(n, 0), "sse": []}
    if n < 4 * (max_delay + 1) or len(r) != len(u):
        return res
    x = np.diff(u)[max_delay:] / T_s
    ok = np.isfinite(x)
    sse = []
    for j in range(max_delay + 1):
        rj = r[max_delay - j:max_delay - j + n]
        good = ok & np.isfinite(rj)
        sse.append(float(np.mean((x[good] - rj[good]) ** 2)) if good.any() else float("inf"))
    order = np.argsort(sse)
    best, second = int(order[0]), int(order[1])
    var = float(np.var(x[ok])) if ok.any() else 0.0
    res["sse"] = sse
    res["explained"] = 1.0 - sse[best] / var if var > 0 else None
    res["contrast"] = 1.0 - sse[best] / sse[second] if sse[second] > 0 else None
    if res["contrast"] is not None and res["contrast"] >= min_contrast:
        res["samples"] = best
    return res


def on_seq_grid(seq, u_V, du_dt_V_per_s) -> tuple[np.ndarray, np.ndarray]:
    """(u, du/dt) on every sequence number from the first to the last given: u NaN where a sample was not
    ticked (no Delta u there), du/dt 0 where no command was sent (the plant held the source voltage)."""
    s = np.asarray(seq, dtype=np.int64)
    if len(s) == 0:
        return np.zeros(0), np.zeros(0)
    k = s - s.min()
    u = np.full(int(k.max()) + 1, np.nan)
    r = np.zeros(len(u))
    u[k] = u_V
    r[k] = du_dt_V_per_s
    return u, r


def loop_delay_report(seq, u_V, du_dt_V_per_s, T_s: float, compensated: int | None) -> dict:
    """What status and ``log info`` report: the delay measured from ticks (seq, measured u, du/dt sent; one plant
    epoch) against the delay the core compensates."""
    u, r = on_seq_grid(seq, u_V, du_dt_V_per_s)
    est = estimate_loop_delay(u, r, T_s)
    d = est["samples"]
    return {"measured_samples": d, "compensated_samples": compensated, "mismatch": d is not None and d != compensated,
            "window": len(seq), "explained": est["explained"], "contrast": est["contrast"]}
