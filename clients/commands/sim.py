"""energyctl sim: one scenario's closed loop offline, its metrics and feasibility checks."""

from __future__ import annotations

import argparse
import json
import time

from clients.commands.common import ACCEPTANCE_HELP, CONTROLLERS, failure_lines, is_network_file, load
from clients.options import add_core, add_scenario_set
from clients.table import metrics_table, network_tables


def add_parser(subparsers) -> argparse.ArgumentParser:
    s = subparsers.add_parser(
        "sim", help="run one scenario's closed loop offline and print its metrics",
        description="Run a TOML scenario's closed loop offline, as fast as the machine allows. "
                    "Metrics: settle_s = time of the last exit from +-2 % of v_ref; ss_error = "
                    "mean |v - v_ref| over the last 10 %; hold_max_dev_pct = max |v - v_ref| / "
                    "v_ref for t >= 50 ms, hold_max_dev_t_s when it happened, hold_outside_band_s "
                    "the time outside +-2 % from 50 ms on; rms/max du/dt of the applied command; "
                    "rms_tracking_error = rms(y_z - y_ref) on the true state; "
                    "feasibility_violations = excursions of the outgoing interaction variable "
                    "from the window's incoming range; diverged = v left v_ref +- acceptance.diverge_dev_pct "
                    "(25 %), where the run stops; accepted = the scenario's acceptance criteria held. The band "
                    "(+-2 %) and where it must hold (from 50 ms on) are the scenario's [acceptance] keys. A network "
                    "scenario (kind = \"network\") prints its sources, buses and events instead. "
                    + ACCEPTANCE_HELP)
    s.add_argument("scenario", help="scenario TOML file (see scenarios/)")
    add_scenario_set(s)
    s.add_argument("--controller", choices=CONTROLLERS, help="override controller.kind")
    s.add_argument("--out", metavar="FILE.mcap", help="write measurements, commands, estimates to MCAP")
    s.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    add_core(s)
    s.set_defaults(func=run)
    return s


def overrides(args: argparse.Namespace) -> list[str]:
    """--set, then --controller as controller.kind."""
    ovs = list(getattr(args, "set", None) or [])
    if getattr(args, "controller", None):
        ovs.append(f'controller.kind="{args.controller}"')
    return ovs


def run(args: argparse.Namespace) -> int:
    from service.sim import run as simulate

    if is_network_file(args.scenario):
        return run_network_scenario(args)
    scn = load(args.scenario, overrides(args))
    t0 = time.perf_counter()
    res = simulate(scn, impl=args.core)
    wall = time.perf_counter() - t0
    if args.out:
        from service.logio.mcapfile import write_sim_mcap

        write_sim_mcap(args.out, res, prefix=f"energyctl/{scn.name}")
    m = dict(res.metrics)
    m["wall_s"] = wall
    m["violations"] = [v.__dict__ for v in res.violations[:20]]
    if res.forecasts:
        m["forecasts"] = [f.as_dict() for f in res.forecasts]
    if args.json:
        print(json.dumps({"scenario": scn.name, "controller": scn.controller.kind, **m}))
    else:
        print(f"scenario {scn.name}: controller {scn.controller.kind} ({scn.controller.mapping} mapping), "
              f"{scn.timing.control_rate_hz:g} Hz control, {scn.timing.delay_samples} samples delay, "
              f"{scn.timing.duration_s:g} s simulated in {wall:.2f} s")
        print(metrics_table([([scn.name, scn.controller.kind], res.metrics)], ["scenario", "controller"]))
        W = scn.feasibility.window_s
        for k, f in enumerate(res.forecasts):  # the check made before each window ran
            verdict = (f"feasible: forecast Qdot^r,out [{f.Qdot_lo:.4g}, {f.Qdot_hi:.4g}] W/s inside Qdot^r,in "
                       f"[{f.z_in[2]:.4g}, {f.z_in[3]:.4g}] W/s" if f.feasible else f"INFEASIBLE: {f.reason}")
            print(f"feasibility ahead of window {k} ({k * W:g} s): {verdict}")
        for v in res.violations[:5]:
            print(f"feasibility: {v.element} left [{v.lo:.4g}, {v.hi:.4g}] at t = {v.t:.4f} s (value {v.value:.4g})")
        if args.out:
            print(f"wrote {args.out}")
        print_verdict(f"{scn.name} ({scn.controller.kind})", res.metrics)
    return 0 if res.metrics["accepted"] else 1


def print_verdict(label: str, m: dict) -> None:
    """The acceptance verdict under the tables: each failed criterion, or that the run was accepted."""
    lines = failure_lines(label, m)
    print("\n".join(lines) if lines else f"accepted: {label} met its acceptance criteria")


def run_network_scenario(args: argparse.Namespace) -> int:
    """sim on a network scenario (kind = "network"): every source's controller, the layer, the events."""
    from schemas.network import load_network
    from schemas.scenario import ScenarioError
    from service.network.netsim import run_network

    if args.controller:
        raise ScenarioError("--controller: a network has a controller per source; use --set "
                            "sources.NAME.controller.kind=...")
    net = load_network(args.scenario, args.set or [])
    t0 = time.perf_counter()
    res = run_network(net, impl=args.core)
    wall = time.perf_counter() - t0
    m = {**res.metrics, "wall_s": wall}
    if args.out:
        from service.logio.mcapfile import write_network_mcap

        write_network_mcap(args.out, res)
    if args.json:
        print(json.dumps({"scenario": net.name, **m}))
        return 0 if m["accepted"] else 1
    print(f"network {net.name}: {len(net.sources)} sources, {len(net.buses)} buses, {len(net.lines)} lines, "
          f"layer {net.layer.mode} (window {net.layer.window_s * 1e3:g} ms), "
          f"{net.timing.control_rate_hz:g} Hz control, {net.timing.delay_samples} samples delay, "
          f"{net.timing.duration_s:g} s simulated in {wall:.2f} s"
          + (f"; DIVERGED at {m['diverged_at_s']:.4f} s" if m["diverged"] else ""))
    print(network_tables(m))
    if args.out:
        print(f"wrote {args.out}: replay a source with energyctl replay {args.out} --component "
              f"{' | '.join(net.sources)}")
    print_verdict(net.name, m)
    return 0 if m["accepted"] else 1
