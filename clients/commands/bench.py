"""energyctl bench WHAT: one bench per name (BENCHES), each a small function from the options to its result."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import NamedTuple

from clients.bench.realtime import BAND_PCT, LIMIT_PCT
from clients.commands.common import DEMO_SCENARIO, load
from clients.commands.demo import (
    DEMO_REALTIME_DELAY,
    DEMO_REALTIME_HZ,
    DEMO_REALTIME_SETS,
    REALTIME_STACK_NOTE,
)
from clients.options import add_cpus, add_nice, add_scenario_set


def _scenario(args: argparse.Namespace) -> str:
    return args.scenario or str(DEMO_SCENARIO)


def _sim(args: argparse.Namespace) -> dict:
    from clients.bench.sim import bench_sim

    scn = load(_scenario(args), [*(args.set or []), "timing.duration_s=1.0", "timing.plant_step_s=1e-5",
                                 "timing.control_rate_hz=10000.0"])
    return bench_sim(scn, args.repeat)


def _core(args: argparse.Namespace) -> dict:
    from clients.bench.core import bench_core

    return bench_core(load(_scenario(args), [*(args.set or []), "timing.duration_s=0.5"]), args.repeat)


def _tick(args: argparse.Namespace) -> dict:
    from clients.bench.tick import bench_tick

    return bench_tick(_scenario(args), n=args.n or 20_000)


def _latency(args: argparse.Namespace) -> dict:
    from clients.bench.latency import bench_latency

    return bench_latency(n=args.n or 3000, wait=args.wait or "block", cpus=(args.cpus or {}).get("controller"))


def _recorder(args: argparse.Namespace) -> dict:
    from clients.bench.recorder import bench_recorder
    from service.priority import set_nice

    refused = set_nice(args.nice)  # the loop thread (and the writer it spawns, which drops below it)
    if refused:
        print(f"energyctl bench: {refused}", file=sys.stderr)
    cpus = [int(x) for x in args.writer_cpus.split(",")] if args.writer_cpus else None
    res = bench_recorder(seconds=args.seconds or 10.0, writer_cpus=cpus)
    res["nice"] = args.nice
    res["writer_cpus"] = cpus
    return res


def _replay(args: argparse.Namespace) -> dict:
    from clients.bench.tick import bench_replay

    return bench_replay(_scenario(args), seconds=args.seconds or 10.0)


def _realtime(args: argparse.Namespace) -> dict:
    from clients.bench.realtime import bench_realtime, progress_line

    # with demo --realtime's settings unless --set says otherwise
    path = _scenario(args)
    scn = load(path, [*DEMO_REALTIME_SETS, *(args.set or [])])
    versus = load(path, [*DEMO_REALTIME_SETS, *(args.set or []), *args.versus]) if args.versus else None
    rates = [float(r) for r in (args.rates or "1000,2000,5000,10000").split(",")]
    delays = (args.delays or "1,2,3,8ms").split(",")  # samples, or a time: 8ms is 8 samples at 1 kHz, 16 at 2
    loop = {k: v for k, v in (("wait", args.wait), ("catch_up", args.catch_up)) if v is not None}
    return bench_realtime(scn, rates, delays, args.seconds or 2.0, loop=loop, nice=args.nice,
                          repeats=args.runs, scn_versus=versus, cpus=args.cpus,
                          progress=lambda r: print(progress_line(r), file=sys.stderr, flush=True))


def _soak(args: argparse.Namespace) -> dict:
    from clients.bench.soak import bench_soak

    # the realtime stack of demo --realtime and bench realtime, under the user's --set
    return bench_soak(args.minutes, rate_hz=args.rate, cpus=args.cpus, sets=[*DEMO_REALTIME_SETS, *(args.set or [])])


def _recovery(args: argparse.Namespace) -> dict:
    from clients.bench.recovery import recovery

    rt = args.realtime
    scn = load(_scenario(args), [*(DEMO_REALTIME_SETS if rt else []), *(args.set or [])])
    return recovery(scn, progress=lambda m: print(m, file=sys.stderr, flush=True), realtime=rt,
                    rate_hz=DEMO_REALTIME_HZ, controller_delay=DEMO_REALTIME_DELAY)


def _wake(args: argparse.Namespace) -> dict:
    from clients.bench.wake import bench_wake
    from schemas.component import ComponentConfig

    return bench_wake(slack_ns=ComponentConfig.model_fields["timer_slack_ns"].default, n=args.n or 20_000)


def _middleware(args: argparse.Namespace) -> dict:
    from clients.bench.middleware import bench_middleware

    return bench_middleware(n=args.n or 3000, progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _foxglove(args: argparse.Namespace) -> dict:
    from clients.bench.foxglove import bench_foxglove

    realtime = args.realtime
    sets = [*(DEMO_REALTIME_SETS if realtime else []), *(args.set or [])]
    return bench_foxglove(load(_scenario(args), sets), seconds=args.seconds or 2.0, pairs=args.runs,
                          lockstep=not realtime, rate_hz=float(args.rates) if (realtime and args.rates) else
                          (DEMO_REALTIME_HZ if realtime else None),
                          delay=DEMO_REALTIME_DELAY if realtime else None,
                          progress=lambda r: print(f"  {json.dumps(r)[:300]}", file=sys.stderr, flush=True))


def _observer(args: argparse.Namespace) -> dict:
    from clients.bench.observer import bench_observer

    realtime = not args.lockstep
    sets = [*(DEMO_REALTIME_SETS if realtime else []), *(args.set or [])]
    seconds = args.seconds or 14.0
    return bench_observer(load(_scenario(args), sets), lockstep=not realtime,
                          rate_hz=float(args.rates) if args.rates else (DEMO_REALTIME_HZ if realtime else None),
                          delay=DEMO_REALTIME_DELAY if realtime else None, duration_s=seconds,
                          stop_s=max(1.0, seconds - 2.0), pairs=args.runs,
                          progress=lambda r: print(f"  {json.dumps(r)[:400]}", file=sys.stderr, flush=True))


def _network(args: argparse.Namespace) -> dict:
    from clients.bench.network import bench_network

    return bench_network(seconds=args.seconds or 0.2, repeat=args.repeat,
                         progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _network_scale(args: argparse.Namespace) -> dict:
    from clients.bench.network_scale import LIVE_SIZES, OFFLINE_SIZES, bench_network_scale

    live = () if args.offline_only else LIVE_SIZES
    return bench_network_scale(OFFLINE_SIZES, live, seconds=args.seconds or 0.1, repeat=args.repeat,
                               progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _network_live(args: argparse.Namespace) -> dict:
    from clients.bench.network_live import bench_network_live

    rates = [float(r) for r in (args.rates or "1000,1500,2000,3000").split(",")]
    return bench_network_live(args.realtime, rates, args.seconds or 2.0,
                              progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _network_coordinator(args: argparse.Namespace) -> dict:
    from clients.bench.network_live import bench_network_coordinator

    rates = [float(r) for r in (args.rates or "2000,10000").split(",")]
    return bench_network_coordinator(rates, args.seconds or 3.0,
                                     progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _network_rate(args: argparse.Namespace) -> dict:
    from clients.bench.network_rate import bench_network_rate

    return bench_network_rate(float(args.rates) if args.rates else 1000.0, max(args.runs, 1), args.seconds or 2.0,
                              progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _fuzz(args: argparse.Namespace) -> dict:
    from clients.bench.fuzz import bench_fuzz

    return bench_fuzz(frames=args.n or 100_000, progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


def _router_audit(args: argparse.Namespace) -> dict:
    from clients.bench.router_audit import bench_router_audit

    return bench_router_audit(rate_hz=float(args.rates) if args.rates else 10_000.0, seconds=args.seconds or 3.0,
                              pairs=max(args.runs, 2), progress=lambda r: print(f"  {r}", file=sys.stderr, flush=True))


def _attack(args: argparse.Namespace) -> dict:
    from clients.bench.attack import bench_attack

    return bench_attack(flood_s=args.seconds or 10.0, progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))


class Bench(NamedTuple):
    run: Callable[[argparse.Namespace], dict]
    what: str  # what it measures, for --help


BENCHES: dict[str, Bench] = {
    "sim": Bench(_sim, "real-time ratio"),
    "core": Bench(_core, "per-step cost, compiled and Python"),
    "tick": Bench(_tick, "the daemon's whole tick without the network"),
    "latency": Bench(_latency, "daemon round trip vs bare Zenoh echo"),
    "recorder": Bench(_recorder, "10 kHz stream set vs bare writer"),
    "replay": Bench(_replay, "a long 10 kHz daemon log replayed from its tick index and from JSON"),
    "realtime": Bench(_realtime, f"the highest control rate at which v stays within +-{BAND_PCT:g} % of v_ref "
                                 f"from 50 ms on, with loop overruns under {LIMIT_PCT:g} % of ticks and missed or "
                                 f"late commands under {LIMIT_PCT:g} % of samples"),
    "soak": Bench(_soak, "the realtime stack for minutes: RSS, drops, overruns, regulation"),
    "recovery": Bench(_recovery, "kill -9 plant / neighbour, time back to +-2 %"),
    "wake": Bench(_wake, "how late a 60 us timed wait ends at the kernel's default timer slack and at "
                         "timer_slack_ns's"),
    "foxglove": Bench(_foxglove, "the Foxglove bridge's cost to the stack it watches: daemon overruns and the run's "
                                 "wall time without and with it (alternated, --runs pairs), its CPU share "
                                 "(--realtime: wall-clock pacing, --rates one rate)"),
    "observer": Bench(_observer, "a monitor SIGSTOPped beside the realtime stack (--lockstep: the lockstep one): the "
                      "plant's measurement -> command latency and status queries, with it reading and stopped"),
    "network": Bench(_network, "a network's offline cost per source per tick at 2, 4, 8 and 16 sources (radial "
                               "feeders; --seconds simulated each, default 0.2)"),
    "network-scale": Bench(_network_scale, "radial networks offline at 4-64 sources (cost per source per tick) and "
                                           "live in lockstep at 4-32 source daemons on 4 namespace hosts through the "
                                           "secure profile's routers (root): wall time per simulated second, CPU per "
                                           "daemon per sample from /proc, identity with sim per run (--seconds "
                                           "simulated each, default 0.1; --offline-only)"),
    "network-live": Bench(_network_live, "the live network on loopback (rig, coordinator, a daemon per source): time "
                                         "until every bus is back within +-2 % after a plug-in, a daemon killed "
                                         "with SIGKILL and the coordinator lost and restarted (--realtime: at 1 kHz, "
                                         "and the highest of --rates at which two-source regulates, with each "
                                         "process's CPU; default rates 1000,1500,2000,3000, --seconds each)"),
    "network-coordinator": Bench(_network_coordinator, "the coordinator's messages to the sources per second of "
                                                       "sample time and its CPU per sample, two-source in lockstep "
                                                       "at each of --rates (default 2000,10000) for --seconds "
                                                       "(default 3)"),
    "network-rate": Bench(_network_rate, "the realtime two-source network at one rate (--rates, one, default 1000 "
                                         "Hz), --runs runs of --seconds (default 2), each beside a bare Zenoh echo "
                                         "with as many processes: runs passing every check, commands after their "
                                         "period and p99 age against the echo's"),
    "fuzz": Bench(_fuzz, "bad measurement frames (bit flips, boundary values, NaN and inf, cuts) put between the "
                         "samples of the paper's stack in lockstep at 10 kHz: frames counted against sent by reason, "
                         "loop deaths, tracebacks, commands after a bad frame, v's deviation from v_ref (-n frames, "
                         "default 100000)"),
    "router-audit": Bench(_router_audit, "the secure router's CPU with refusal logging on and off while one identity "
                                         "publishes to another at --rates (one rate, default 10000 Hz) for --seconds "
                                         "(default 3), alternated --runs pairs (at least 2); then the refusals it "
                                         "counts for 20 denied config sets and a wrong password"),
    "attack": Bench(_attack, "the realtime stack at 1 kHz under attack (forged measurements, a 10 MB "
                             "config/set, a flood of invalid frames at 27 k/s for --seconds, default 10, the "
                             "controller stopped for 0.6 s), each beside an unattacked control run: time until v is "
                             "back within +-2 % after the attack ends"),
    "middleware": Bench(_middleware, "the Zenoh and MCAP facts the daemon's design rests on, re-measured: put cost, "
                                     "one-way and round-trip latency, callback vs polled receive, query round trip, "
                                     "liveliness loss after kill -9, CPU per message, encoding cost, MCAP writes"),
}


_NAME_W = max(map(len, BENCHES)) + 2  # the listing's name column: the longest bench name and two spaces


def add_parser(subparsers) -> argparse.ArgumentParser:
    listing = ", ".join(f"'{name}' ({b.what})" for name, b in BENCHES.items())
    b = subparsers.add_parser(
        "bench", help="benchmarks: " + listing.replace("%", "%%"),
        description="Runs one benchmark and prints its result, one key: value line per field (--json: one JSON "
                    "object). The options below say which benches they apply to.\n\n"
                    + "\n".join(f"  {name:<{_NAME_W}}{b.what}" for name, b in BENCHES.items()))
    b.add_argument("what", choices=list(BENCHES), help="the bench to run (listed above)")
    b.add_argument("--rates", metavar="HZ,HZ,...",
                   help="realtime: control rates to try (default 1000,2000,5000,10000), with "
                        f"{' '.join(DEMO_REALTIME_SETS)} unless --set says otherwise; {REALTIME_STACK_NOTE}")
    b.add_argument("--delays", metavar="N,N,...",
                   help="realtime: loop-delay schedules to try, in samples or as a time (8ms: 8 samples at 1 kHz, 16 "
                        "at 2 kHz); the controller answers up to that many queued samples after a stall (default "
                        "1,2,3,8ms)")
    b.add_argument("--minutes", type=float, default=10.0, help="soak: duration (default %(default)s)")
    b.add_argument("--rate", type=float, default=10000.0,
                   help="soak: loop and sample rate, Hz (default %(default)s); the stack is bench realtime's (its "
                        "--set defaults, an 8 ms loop-delay schedule), with status queries at 100 Hz")
    b.add_argument("--seconds", type=float, default=None,
                   help="recorder: paced run length (default 10); replay: log length (default 10); realtime: each "
                        "run (default 2); network: simulated time per size (default 0.2); attack: the flood (default "
                        "10)")
    b.add_argument("-n", type=int, default=None,
                   help="latency: round trips per target (default 3000); tick: ticks (default 20000); wake: waits "
                        "per setting (default 20000); middleware: puts and pings (default 3000); fuzz: bad frames "
                        "(default 100000)")
    b.add_argument("--wait", choices=["block", "spin"], default=None,
                   help="latency, realtime: the daemon's wait for samples (default: block)")
    b.add_argument("--runs", type=int, default=1, metavar="N",
                   help="realtime: runs per rate and schedule (default 1); with --versus, N of each, alternated")
    b.add_argument("--versus", action="append", default=[], metavar="dotted.key=value",
                   help="realtime: also run with this override (arm b), alternately with the runs without it (arm "
                        "a); repeatable. The summary counts, per arm, the runs within ±2 %%, diverged and passing")
    b.add_argument("--catch-up", type=int, default=None, metavar="N",
                   help="realtime: answer up to N queued samples in order (loop.catch_up; default: the schedule's "
                        "length)")
    add_nice(b)
    add_cpus(b)
    b.add_argument("scenario", nargs="?", help="scenario (default: the embedded demo)")
    add_scenario_set(b)
    b.add_argument("--writer-cpus", metavar="N,N,...",
                   help="recorder: CPUs the recorder's writer process may run on (as log_writer_cpus; default any)")
    b.add_argument("--lockstep", action="store_true",
                   help="observer: the lockstep stack instead of the realtime one (2 kHz, as the demo's)")
    b.add_argument("--realtime", action="store_true",
                   help=f"recovery: wall-clock pacing with demo --realtime's settings ({DEMO_REALTIME_HZ / 1e3:g} kHz, "
                        f"{DEMO_REALTIME_DELAY}-sample schedule, {' '.join(DEMO_REALTIME_SETS)}) instead of lockstep")
    b.add_argument("--repeat", type=int, default=3, help="sim, core, network: passes (default %(default)s)")
    b.add_argument("--offline-only", action="store_true", help="network-scale: the offline sizes only")
    b.add_argument("--json", action="store_true", help="print one JSON object instead of key: value lines")
    b.set_defaults(func=run)
    return b


def run(args: argparse.Namespace) -> int:
    res = BENCHES[args.what].run(args)
    print(json.dumps(res) if args.json else "\n".join(f"{k}: {v}" for k, v in res.items()))
    return 0
