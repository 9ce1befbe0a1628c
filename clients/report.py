"""energyctl report: PNG figures like the paper's and a Markdown summary, for one log or two side by side.

Figures: states.png (i, v with the +-2 % band, u, du/dt), energy.png (y_z vs y_ref, u_z),
interaction.png (outgoing vs incoming interaction variable, with the feasibility bands Z^{r,in} per window
when the log carries its scenario, or, in a daemon's log, from its forecast events, together with the
Z^{r,out} it forecast ahead of each window). Works on simulator logs (true plant state) and daemon logs
(measured).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.logio.reader import scan
from service.metrics import BAND_SETTLE, max_abs, regulation, rms


class ReportError(RuntimeError):
    pass


def load_series(path: str | Path) -> dict:
    from service.logio.reader import LogError

    try:
        s = scan(path, keep_messages=True)
    except LogError as e:  # empty or not MCAP
        raise ReportError(str(e)) from None
    cols: dict[str, dict[str, list]] = {}
    for m in s["messages"]:
        leaf = s["channels"][m.channel_id].topic.rsplit("/", 1)[-1]
        d = json.loads(m.data)
        c = cols.setdefault(leaf, {})
        for k, v in d.items():
            if isinstance(v, int | float) and not isinstance(v, bool):
                c.setdefault(k, []).append(float(v))
    series = {leaf: {k: np.asarray(v) for k, v in c.items()} for leaf, c in cols.items()}
    forecasts = {}  # a daemon's forecast events by window (the newest, after a config set)
    for m in s["messages"]:
        if s["channels"][m.channel_id].topic.endswith("/events"):
            ev = json.loads(m.data)
            if ev.get("kind") == "forecast":
                f = json.loads(ev["detail"])
                forecasts[f["window"]] = f
    meta = {name: json.loads(m["json"]) for name, m in s["metadata"].items() if "json" in m}
    v_ref = 80.0
    for name in ("scenario", "config", "core"):
        if name in meta and "controller" in meta[name]:
            v_ref = meta[name]["controller"]["v_ref_V"]
            break
    if "meas" not in series and "plant" not in series:
        raise ReportError(f"{path}: no measurement or plant channel")
    if meta.get("scenario", {}).get("kind") == "network":  # v_ref lives per source there
        v_ref = meta["scenario"].get("nominal_v_V", v_ref)
    return {"path": str(path), "name": Path(path).stem, "series": series, "meta": meta, "v_ref": v_ref,
            "complete": s["complete"], "forecasts": forecasts,
            "damage": [d.describe() for d in s["damage"]]}


def state(log: dict) -> dict:
    """The trajectory to plot: the true plant state if logged (simulation), else the measurements."""
    return log["series"].get("plant") or log["series"]["meas"]


def summary_metrics(log: dict) -> dict:
    st, v_ref = state(log), log["v_ref"]
    t = st["t"]
    cmd = log["series"].get("cmd", {}).get("du_dt", np.zeros(1))
    return {**regulation(t, st["v"], v_ref, BAND_SETTLE), "rms_du_dt": rms(cmd), "max_abs_du_dt": max_abs(cmd),
            "duration_s": float(t[-1] - t[0]) if len(t) > 1 else 0.0,
            "source": "plant (true state)" if "plant" in log["series"] else "measurements"}


def feasibility_bands(log: dict):
    """[(t0, t1, P_lo, P_hi, Q_lo, Q_hi, forecast)] per window: Z^{r,in} and, from a daemon's log, its forecast
    of Z^{r,out} made ahead of the window (forecast = (Qdot_lo, Qdot_hi, feasible), else None); from the log's
    scenario (a simulation) or the daemon's forecast events; None if neither."""
    if log.get("forecasts"):
        W = log["meta"].get("config", {}).get("forecast_window_s", 1.0)
        return [(k * W, (k + 1) * W, *f["z_in"], (f["Qdot_lo"], f["Qdot_hi"], f["feasible"]))
                for k, f in sorted(log["forecasts"].items())]
    scn_d = log["meta"].get("scenario")
    if not scn_d:
        return None
    from schemas.scenario import Scenario
    from service.core.control import effective_gain
    from service.core.feasibility import incoming_range, load_box, tau_prime
    from service.plant.profiles import Profile

    scn = Scenario.model_validate(scn_d)
    load = Profile(scn.load, scn.base_dir)
    tp = tau_prime(scn.model.L_H, scn.model.R_ohm, effective_gain(scn.controller, scn.model))
    W = scn.feasibility.window_s
    bands = []
    k = 0
    while k * W < scn.timing.duration_s:
        t0, t1 = k * W, min((k + 1) * W, scn.timing.duration_s)
        box = load_box(*load.range_over(t0, t1), scn.feasibility.forecast_margin)
        bands.append((t0, t1, *incoming_range(*box, tp, scn.feasibility.literal_paper_range), None))
        k += 1
    return bands


def report(paths: list[str], out_dir: str) -> dict:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ReportError("energyctl report needs matplotlib: python3 -m pip install 'energyctl[report]'") from None
    heads = [scan(p) for p in paths]
    coordinators = [p for p, h in zip(paths, heads, strict=True) if "coordinator" in h["metadata"]]
    nets = [k for k, h in enumerate(heads) if _kind(h["metadata"]) == "network" and "coordinator" not in h["metadata"]]
    out = Path(out_dir)
    if nets:  # a network log (energyctl sim NETWORK --out, or a live rig's), with its sources' daemon logs if live
        if len(nets) > 1:
            raise ReportError("one network log at a time (a live network: the rig's log and its daemons' logs)")
        others = [p for k, p in enumerate(paths) if k != nets[0] and p not in coordinators]  # (its figures: replay)
        bad = [p for p, h in zip(paths, heads, strict=True) if p in others and "config" not in h["metadata"]]
        if bad:
            raise ReportError(f"beside a network log only its sources' daemon logs: {bad}")
        out.mkdir(parents=True, exist_ok=True)
        lg = load_series(paths[nets[0]])
        return _network_summary(lg, out, network_report(lg, out, plt, others)["figures"])
    if not 1 <= len(paths) <= 2:
        raise ReportError("report takes one log, or two to compare")
    logs = [load_series(p) for p in paths]
    out.mkdir(parents=True, exist_ok=True)
    figs = []
    n_bands: dict[str, int] = {}

    fig, ax = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    for lg in logs:
        st, cmd = state(lg), lg["series"].get("cmd", {})
        ax[0].plot(st["t"], st["i"], label=lg["name"])
        ax[1].plot(st["t"], st["v"], label=lg["name"])
        ax[2].plot(st["t"], st["u"], label=lg["name"])
        if "du_dt" in cmd:
            ax[3].plot(cmd["t"], cmd["du_dt"], lw=0.6, label=lg["name"])
    v_ref = logs[0]["v_ref"]
    ax[1].axhspan(0.98 * v_ref, 1.02 * v_ref, color="g", alpha=0.12, label="±2 % of v_ref")
    for a, lab in zip(ax, ("i (A)", "v (V)", "u (V)", "du/dt (V/s)"), strict=True):
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
    ax[1].legend(fontsize=8)
    ax[3].set_xlabel("t (s)")
    fig.suptitle("current, terminal voltage, source voltage, commanded rate")
    fig.tight_layout()
    fig.savefig(out / "states.png", dpi=110)
    plt.close(fig)
    figs.append("states.png")

    if any("est" in lg["series"] for lg in logs):
        fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for lg in logs:
            e = lg["series"].get("est")
            if e is None:
                continue
            ax[0].plot(e["t"], e["y_z"], label=f"y_z {lg['name']}")
            ax[0].plot(e["t"], e["y_ref"], "--", label=f"y_ref {lg['name']}")
            ax[1].plot(e["t"], e["u_z"], lw=0.6, label=lg["name"])
        figs.append(_finish(plt, fig, ax, ("W", "u_z = Qdot^u (W/s)"), "energy-space output and reference",
                            out / "energy.png"))

        fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for lg in logs:
            e, zin = lg["series"].get("est"), lg["series"].get("z_in")
            if e is not None:
                ax[0].plot(e["t"], e["P_r_out"], label=f"P^r,out {lg['name']}")
                ax[1].plot(e["t"], e["Qdot_r_out"], lw=0.6, label=f"Qdot^r,out {lg['name']}")
            if zin is not None:
                ax[0].plot(zin["t"], zin["P_r_in"], "--", label=f"P^r,in {lg['name']}")
        any_bands = False
        for lg, color in zip(logs, ("tab:orange", "tab:purple"), strict=False):
            bands = feasibility_bands(lg)  # each log's own: tau' depends on its controller's gain
            n_bands[lg["name"]] = len(bands or [])
            for j, (t0, t1, plo, phi, qlo, qhi, fc) in enumerate(bands or []):
                lab = f"Z^r,in range {lg['name']}" if j == 0 else None
                ax[0].fill_between([t0, t1], plo, phi, color=color, alpha=0.12, label=lab)
                ax[1].fill_between([t0, t1], qlo, qhi, color=color, alpha=0.12, label=lab)
                if fc is not None:  # the forecast Qdot^r,out range: red where it was judged infeasible
                    lab = f"Z^r,out forecast {lg['name']}" if j == 0 else None
                    ax[1].hlines(fc[:2], t0, t1, colors=color if fc[2] else "red", linestyles="--", lw=0.9,
                                 label=lab)
                any_bands = True
        ax[1].set_yscale("symlog", linthresh=1e3)
        title = "outgoing vs incoming interaction variable" + (" with feasibility bands" if any_bands else "")
        figs.append(_finish(plt, fig, ax, ("W", "W/s"), title, out / "interaction.png"))

    metrics = [(lg["name"], _logged_metrics(lg["meta"].get("metrics")) or summary_metrics(lg)) for lg in logs]
    keys = ["settle_s", "v_min", "v_max", "ss_error", "rms_du_dt", "max_abs_du_dt"]
    def source(lg: dict) -> str:
        if lg["meta"].get("metrics"):
            return "metrics as the run logged them"
        return ("metrics from the logged true plant state" if "plant" in lg["series"] else
                "metrics from the measurements the controller saw (noisy; a plant's own log has the true state)")

    lines = ["# energyctl report", "", *(f"- `{lg['path']}`: {source(lg)}" + (
                 "" if lg["complete"] else " (cut off; recovered up to its last complete chunk)")
                 + "".join(f" (CORRUPT, skipped: {d})" for d in lg.get("damage", ())) for lg in logs),
             "", "| log | " + " | ".join(keys) + " |", "|" + " --- |" * (len(keys) + 1)]
    for name, m in metrics:
        lines.append(f"| {name} | " + " | ".join(_fmt(m.get(k)) for k in keys) + " |")
    lines += ["", *(f"![{f}]({f})" for f in figs), ""]
    (out / "summary.md").write_text("\n".join(lines))
    return {"out": str(out), "figures": figs, "summary": str(out / "summary.md"), "metrics": dict(metrics),
            "feasibility_windows": n_bands}


def _kind(meta: dict) -> str | None:
    """The "kind" of the scenario in a log's metadata, if any."""
    try:
        return json.loads(meta["scenario"]["json"]).get("kind")
    except (KeyError, ValueError, AttributeError):
        return None


def _network_summary(log: dict, out: Path, figs: list[str]) -> dict:
    from clients.table import network_tables

    m = log["meta"].get("metrics") or {}
    lines = ["# energyctl report", "", f"- `{log['path']}`", "", "```", network_tables(m) if m else "no metrics",
             "```", "", *(f"![{f}]({f})" for f in figs), ""]
    (out / "summary.md").write_text("\n".join(lines))
    return {"out": str(out), "figures": figs, "summary": str(out / "summary.md"), "metrics": m,
            "feasibility_windows": {}}


def _finish(plt, fig, ax, ylabels: tuple[str, ...], title: str, path: Path) -> str:
    """Labels, grid, legend, title; save as PNG and close. Returns the file name."""
    for a, lab in zip(ax, ylabels, strict=True):
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    ax[-1].set_xlabel("t (s)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def _fmt(v) -> str:
    if v is None:
        return "never"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _logged_metrics(m: dict | None) -> dict | None:
    """A log's "metrics" record: sim writes the metrics themselves, the plant its whole result around them."""
    if isinstance(m, dict) and isinstance(m.get("metrics"), dict):
        return m["metrics"]
    return m


# ------------------------------------------------------------------------------------------------ network logs

def is_network_log(log: dict) -> bool:
    return log["meta"].get("scenario", {}).get("kind") == "network"


def network_series(path: str | Path) -> dict:
    """A network log (energyctl sim NETWORK --out) by element: element -> leaf -> field -> array."""
    s = scan(path, keep_messages=True)
    cols: dict[str, dict[str, dict[str, list]]] = {}
    events, ranges = [], {}
    for m in s["messages"]:
        topic = s["channels"][m.channel_id].topic
        element, leaf = topic.rsplit("/", 2)[-2:]
        d = json.loads(m.data)
        if element == "layer":
            events.append(d)
            continue
        if leaf == "events" and d.get("kind") == "range":
            ranges.setdefault(element, []).append(json.loads(d["detail"]))
            continue
        c = cols.setdefault(element, {}).setdefault(leaf, {})
        for k, v in d.items():
            if isinstance(v, int | float):
                c.setdefault(k, []).append(float(v))
    return {"elements": {e: {leaf: {k: np.asarray(v) for k, v in c.items()} for leaf, c in leaves.items()}
                         for e, leaves in cols.items()}, "events": events, "ranges": ranges}


def network_report(log: dict, out: Path, plt, daemon_logs: list[str] = ()) -> dict:
    """Figures of a network log: bus voltages with their band and the events, source powers and shares, each
    source's incoming interaction variable against its feasibility range per window, the topology. A live rig's log
    holds the plant; its sources' daemon logs (daemon_logs) hold what they followed and the ranges they were sent."""
    from schemas.network import NetworkScenario

    net = NetworkScenario.model_validate(log["meta"]["scenario"])
    data = network_series(log["path"])
    for p in daemon_logs:
        more = network_series(p)
        for e, leaves in more["elements"].items():
            data["elements"].setdefault(e, {}).update({k: v for k, v in leaves.items() if k in ("z_in", "alloc")})
            a = leaves.get("alloc")
            if a is not None and "window" in a:  # the ranges the coordinator sent, one per window
                seen = set()
                for w, has, lo, hi in zip(a["window"], a["has_range"], a["Z_P_min"], a["Z_P_max"], strict=True):
                    if has and w not in seen:
                        seen.add(w)
                        data["ranges"].setdefault(e, []).append({"window": int(w), "P": [lo, hi]})
    el, v_nom = data["elements"], net.nominal_v_V
    figs = []

    def mark_events(ax):
        for ev in data["events"]:
            for a in ax:
                a.axvline(ev["t"], color="k", lw=0.6, ls=":")
            ax[0].annotate(f"{ev['kind']} {json.loads(ev['detail'])['target']}", (ev["t"], 1.0),
                           xycoords=("data", "axes fraction"), fontsize=7, rotation=90, va="top", ha="right")

    fig, ax = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for b in net.buses:
        ax[0].plot(el[b]["plant"]["t"], el[b]["plant"]["v"], label=b)
    for s in net.sources:
        ax[1].plot(el[s]["plant"]["t"], el[s]["plant"]["v"], label=s)
    for a in ax:
        a.axhspan(0.98 * v_nom, 1.02 * v_nom, color="g", alpha=0.12, label="±2 % of nominal")
    mark_events(ax)
    figs.append(_finish(plt, fig, ax, ("bus v (V)", "terminal v (V)"), f"{net.name}: voltages",
                        out / "network_voltages.png"))

    fig, ax = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    t = el[next(iter(net.sources))]["plant"]["t"]
    P = {s: el[s]["plant"]["P_l"] for s in net.sources}
    total = sum(P.values())
    share_sum = sum(src.share for src in net.sources.values())
    for s, src in net.sources.items():
        ax[0].plot(t, P[s], label=s)
        line = ax[1].plot(t, 100.0 * P[s] / np.where(np.abs(total) < 1.0, np.nan, total), lw=0.8, label=s)
        ax[1].axhline(100.0 * src.share / share_sum, color=line[0].get_color(), ls="--", lw=0.8)
    mark_events(ax)
    figs.append(_finish(plt, fig, ax, ("P delivered (W)", "share (%)"), f"{net.name}: powers and shares "
                        "(dashed: configured shares of all sources)", out / "network_powers.png"))

    fig, ax = plt.subplots(len(net.sources), 1, figsize=(9, 2.2 * len(net.sources)), sharex=True, squeeze=False)
    ax = ax[:, 0]
    w = net.layer.window_s
    for j, s in enumerate(net.sources):
        z = el[s].get("z_in")
        if z is None:  # a live rig's log without its daemons' logs
            ax[j].plot([], [], label=f"P^r,in {s}: in its daemon's log (report the rig's log with them)")
        else:
            ax[j].plot(z["t"], z["P_r_in"], lw=0.8, label=f"P^r,in {s}")
        for n, r in enumerate(data["ranges"].get(s, [])):  # the layer's range for each window it was connected
            k = r["window"]
            ax[j].fill_between([k * w, (k + 1) * w], *r["P"], color="tab:orange", alpha=0.15,
                               label="Z^r,in range (P)" if n == 0 else None)
    mark_events(ax)
    figs.append(_finish(plt, fig, ax, tuple("W" for _ in net.sources), f"{net.name}: incoming interaction "
                        "variables and their feasibility ranges", out / "network_interaction.png"))
    figs.append(_topology(net, plt, out / "network_topology.png"))
    return {"figures": figs}


def _topology(net, plt, path: Path) -> str:
    """The network drawn: sources (squares) and buses (circles) on a circle, lines between them with R."""
    nodes = net.nodes()
    angle = {n: 2 * np.pi * k / len(nodes) for k, n in enumerate(nodes)}
    pos = {n: (np.cos(a), np.sin(a)) for n, a in angle.items()}
    fig, ax = plt.subplots(figsize=(6, 6))
    for name, ln in net.lines.items():
        (x0, y0), (x1, y1) = pos[ln.a], pos[ln.b]
        ax.plot([x0, x1], [y0, y1], color="0.5", lw=1.5, ls="-" if ln.closed else ":")
        ax.annotate(f"{name} {ln.R_ohm:g} Ω", ((x0 + x1) / 2, (y0 + y1) / 2), fontsize=7, ha="center")
    for n, (x, y) in pos.items():
        src = n in net.sources
        ax.plot(x, y, "s" if src else "o", ms=16, color="tab:blue" if src else "tab:green")
        loads = sum(ld.value for ld in net.loads.values() if ld.bus == n)
        label = f"{n}\nshare {net.sources[n].share:g}" if src else (f"{n}\n{loads:g} W" if loads else n)
        ax.annotate(label, (x, y), xytext=(0, -22), textcoords="offset points", ha="center", fontsize=8)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(f"{net.name}: sources (squares), buses (circles), lines (dotted: open at start)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name
