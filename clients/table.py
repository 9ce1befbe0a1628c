"""Plain-text tables for metrics (no dependencies)."""

from __future__ import annotations

import math

METRIC_COLUMNS = (
    ("settle_s", "settle ms", lambda v: "never" if v is None else f"{v * 1e3:.1f}"),
    ("v_min", "v_min V", lambda v: "-" if v is None else f"{v:.2f}"),
    ("v_max", "v_max V", lambda v: "-" if v is None else f"{v:.2f}"),
    ("ss_error", "ss_err V", lambda v: "-" if v is None else f"{v:.3f}"),
    ("hold_max_dev_pct", "hold %", lambda v: "-" if v is None else f"{v:.2f}"),
    ("rms_du_dt", "rms du/dt", lambda v: "-" if v is None else f"{v:.3g}"),
    ("max_abs_du_dt", "max|du/dt|", lambda v: "-" if v is None else f"{v:.3g}"),
    ("rms_tracking_error", "rms y_z-y_ref W", lambda v: "-" if v is None else f"{v:.3g}"),
    ("feasibility_violations", "feas viol", str),
    ("diverged", "diverged", lambda v: "YES" if v else "no"),
    ("accepted", "accepted", lambda v: "-" if v is None else ("yes" if v else "NO")),
)


def render(headers: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[k]) for r in rows)) if rows else len(h) for k, h in enumerate(headers)]
    line = "  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True))
    sep = "  ".join("-" * w for w in widths)
    body = ["  ".join(c.rjust(w) if _numeric(c) else c.ljust(w) for c, w in zip(r, widths, strict=True))
            for r in rows]
    return "\n".join([line, sep, *body])


def _numeric(s: str) -> bool:
    try:
        return math.isfinite(float(s))
    except ValueError:
        return False


def metrics_table(labelled: list[tuple[list[str], dict]], label_headers: list[str]) -> str:
    headers = [*label_headers, *(c[1] for c in METRIC_COLUMNS)]
    rows = [[*labels, *(fmt(m.get(key)) for key, _, fmt in METRIC_COLUMNS)] for labels, m in labelled]
    return render(headers, rows)


def _ms(v) -> str:
    return "-" if v is None else f"{v * 1e3:.1f}"


def _num(v, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt)


def network_tables(m: dict) -> str:
    """A network run's metrics: one row per source, per bus, per event (netsim.network_metrics)."""
    src = render(["source", "share %", "target %", "error pp", "P W", "v_min V", "v_max V", "mode", "feas viol"],
                 [[s, _num(x["share_pct"], ".1f"), _num(x["share_target_pct"], ".1f"), _num(x["sharing_error_pp"]),
                   _num(x["P_steady_W"], ".0f"), _num(x["v_min"]), _num(x["v_max"]), str(x["final_mode"]),
                   _num(x["feasibility_violations"], "d")] for s, x in m["sources"].items()])
    bus = render(["bus", "v_min V", "v_max V", "steady dev %"],
                 [[b, _num(x["v_min"]), _num(x["v_max"]), _num(x["ss_dev_pct"])] for b, x in m["buses"].items()])
    rows = []
    for e in m["events"]:
        what = f"{e['kind']} {e['target']}" + ("" if e["accepted"] else f" REFUSED: {e['reason']}")
        buses = e["bus_back_in_band_s"].values()
        terms = e["terminals_back_in_band_s"].values()
        rows.append([f"{e['t_s']:.3f}", what,
                     "never" if None in buses else _ms(max(buses, default=None)),
                     _num(min((v for v in e["bus_min_V"].values() if v is not None), default=None)),
                     "never" if None in terms else _ms(max(terms, default=None)),
                     _ms(e.get("sharing_in_band_s")), _num(e.get("inrush_A"), ".1f")])
    ev = render(["t s", "event", "buses back ms", "bus min V", "terminals back ms", "sharing ms", "inrush A"], rows)
    return "\n\n".join([src, bus, ev if rows else "no events"])
