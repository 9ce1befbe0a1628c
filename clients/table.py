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
