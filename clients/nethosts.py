"""A live network across hosts on one machine: Linux network namespaces as hosts (clients.netns), one Zenoh router
per host under the secure profile (clients.secure.write_network_profile: a user and password per process and
router, access control, default deny), the routers linked hub-and-spoke, every process a client of its own host's
router (docs/across-hosts.md). Shared by ``energyctl demo --network --hosts N``, ``energyctl bench network-scale``
and tests/network/test_multihost.py and test_scale.py.

* ``HostedNetwork``: the hosts, the profile, the routers and the processes on the hosts; ``close()`` (or leaving
  its ``with``) stops every process started in a host and deletes every namespace, also on failure.
* ``placement``: the rig and the coordinator on the hub, the sources in contiguous blocks on the other hosts.
* ``run_hosted``: one lockstep run of a scenario across N hosts to its end, with every process's CPU time from
  /proc between the rig's first sample and its last, and the identity check (``identity``) against the offline
  run of the same scenario (``energyctl sim``): every source's v, i, u and command, every bus's v, bit for bit.

Which keys flow between the processes is the secure profile's business (its ACL builder, clients.secure): nothing
here names a key.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from clients.netns import Hosts

ENERGYCTL = [sys.executable, "-m", "clients.cli"]
LOCAL = "tcp/127.0.0.1:7447"  # every host's router, for its own processes (each namespace has its own loopback)
HUB_PORT = 7448  # the hub's router, for the other routers
HUB = "rig"  # the hub host's name: the rig's (and the coordinator's) host
RT_PRIORITY = 10  # SCHED_FIFO priority of the realtime path (routers, rig, daemons) where allowed
NICE = -10  # else this nice value
SAMPLING = "energyctl plant: sampling"  # the rig's stderr line when every process is up and sample 0 goes out
CLK_TCK = os.sysconf("SC_CLK_TCK")
MAX_HOSTS = 64  # demo --hosts
MAX_SOURCES = 64  # demo --sources
STOP_BATCH = 4  # processes stopped at a time at the end of a run


def placement(sources: list[str], n_hosts: int, hub: str = HUB, rig: str = "rig",
              coordinator: str = "coordinator") -> dict[str, list[str]]:
    """{host: identities}: the rig and the coordinator on the hub; the sources in contiguous blocks, in order, on
    hosts h1 .. h(n_hosts - 1), the first blocks one longer when they do not divide evenly (n_hosts = 1: all on the
    hub). A host left without a source is not made."""
    if n_hosts < 1:
        raise ValueError(f"hosts: at least 1, got {n_hosts}")
    place = {hub: [rig, coordinator]}
    spokes = min(n_hosts - 1, len(sources))
    if spokes == 0:
        place[hub] += list(sources)
        return place
    q, r = divmod(len(sources), spokes)
    i = 0
    for h in range(spokes):
        n = q + (1 if h < r else 0)
        place[f"h{h + 1}"] = list(sources[i:i + n])
        i += n
    return place


def realtime_allowed() -> bool:
    """SCHED_FIFO can be set here (root, a kernel that allows it)."""
    import shutil

    return shutil.which("chrt") is not None and subprocess.run(["chrt", "-f", str(RT_PRIORITY), "true"],
                                                              capture_output=True).returncode == 0


def proc_cpu_s(pid: int) -> float | None:
    """CPU time (user + system, s) of a running process from /proc/PID/stat (None: gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime (fields 14 and 15 of stat)


def proc_threads_cpu_s(pid: int) -> dict[str, float]:
    """CPU time (s) of a running process's threads, summed by kind: "python" (the interpreter's threads: the loop,
    queries, recorder; Python does not name them) and Zenoh's runtime threads by their name without the number
    ("rx", "tx", "net", "acc", "app"...). Empty: gone."""
    out: dict[str, float] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                head, rest = f.read().rsplit(")", 1)
        except OSError:
            continue
        name = head.split("(", 1)[1].rstrip("0123456789-_")
        name = "python" if name.startswith("python") else name or "?"
        fields = rest.split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / CLK_TCK
    return out


def proc_ctx_switches(pid: int) -> tuple[int, int]:
    """(voluntary, involuntary) context switches of a running process's threads so far, from /proc (0, 0: gone).
    Involuntary ones are preemptions: a thread taken off its CPU while it had work."""
    vol = invol = 0
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0, 0
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/status") as f:
                for line in f:
                    if line.startswith("voluntary_ctxt_switches:"):
                        vol += int(line.split()[1])
                    elif line.startswith("nonvoluntary_ctxt_switches:"):
                        invol += int(line.split()[1])
        except OSError:
            continue
    return vol, invol


def proc_rss_mb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


class HostedNetwork:
    """The hosts, the secure profile, the routers and the processes on the hosts (see the module docstring).

    ``place``: {host: identities that run there}, the hub among them; ``scenario``: the network scenario file every
    process reads (the profile's identities come from it). ``audit``: the routers log refusals (one line per routed
    message is read: off, ``--no-audit``, where the CPUs are tight). ``wait_before_drop_us``: the profile's Zenoh
    wait before a full send queue drops a message (None: Zenoh's)."""

    def __init__(self, scenario: str | Path, work: str | Path, place: dict[str, list[str]], hub: str = HUB,
                 sets: list[str] | None = None, lease_ms: int = 1000, keep_alive: int = 4, audit: bool = True,
                 energyctl: list[str] | None = None, wait_before_drop_us: int | None = None):
        if hub not in place:
            raise ValueError(f"the hub {hub!r} is not one of the hosts {sorted(place)}")
        self.scenario, self.work, self.place, self.hub = Path(scenario), Path(work), dict(place), hub
        self.sets = list(sets or [])
        self.lease_ms, self.keep_alive, self.audit = lease_ms, keep_alive, audit
        self.wait_before_drop_us = wait_before_drop_us
        self.energyctl = list(energyctl or ENERGYCTL)
        self.work.mkdir(parents=True, exist_ok=True)
        self.hosts = Hosts(list(place))
        self.host_of = {ident: h for h, ids in place.items() for ident in ids}
        self.profile = self.work / "secure"
        self.routers: dict[str, subprocess.Popen] = {}
        self.procs: dict[str, subprocess.Popen] = {}
        self.hub_endpoint = f"tcp/{self.hosts.address(hub)}:{HUB_PORT}"
        self.rt = realtime_allowed()
        self._listening: dict[str, int] = {}  # per host: its router log's "listening" lines before its last start
        from clients.live import child_env

        self.env = child_env()  # this checkout first on the children's path

    # ---------------------------------------------------------------- setup and teardown
    def create(self) -> HostedNetwork:
        self.hosts.create()
        return self

    def close(self) -> None:
        """Every process started in a host, then every namespace (links and addresses with them). Never raises."""
        self.hosts.close()
        self.routers.clear()

    def __enter__(self) -> HostedNetwork:
        return self.create()

    def __exit__(self, *exc) -> None:
        self.close()

    def write_profile(self) -> dict[str, Path]:
        """The secure profile of the network, one router per host (clients.secure.write_network_profile)."""
        from clients.secure import write_network_profile
        from schemas.network import load_network

        net = load_network(self.scenario, self.sets)
        return write_network_profile(self.profile, net, hosts=self.place, hub=self.hub,
                                     hub_endpoints=[self.hub_endpoint], uplink_interface="eth0", listen=[LOCAL],
                                     lease_ms=self.lease_ms, keep_alive=self.keep_alive,
                                     wait_before_drop_us=self.wait_before_drop_us)

    # ---------------------------------------------------------------- Zenoh options of a process
    def zenoh_args(self, user: str) -> list[str]:
        return ["--mode", "client", "--connect", LOCAL, "--user", user, "--password-file",
                str(self.profile / f"{user}.password"), "--zenoh-config", str(self.profile / "client.json5")]

    def zenoh_dict(self, user: str) -> dict:
        return {"mode": "client", "connect": [LOCAL], "user": user,
                "password_file": str(self.profile / f"{user}.password"),
                "config_file": str(self.profile / "client.json5")}

    def hot(self) -> list[str]:
        return ["chrt", "-f", str(RT_PRIORITY)] if self.rt else ["nice", "-n", str(NICE)]

    # ---------------------------------------------------------------- routers
    def _router_log(self, host: str) -> Path:
        return self.work / f"router-{host}.log"

    def start_router(self, host: str, wait: bool = True, timeout_s: float = 20.0, hot: bool = False) -> None:
        """Start a host's router; with ``wait``, wait until it listens and raise it to the realtime path's
        priority (raised from the start, its start-up, mostly imports, took the CPUs from a running realtime
        network). ``hot``: at that priority from the start, as a router restarted beside a running lockstep network
        must be (below the realtime path it took 15-16 s to listen there, the two CPUs busy with the lockstep
        processes at SCHED_FIFO; on a host of its own it would not wait)."""
        log = self._router_log(host)
        n = log.read_text().count("listening") if log.exists() else 0
        with open(log, "a") as f:
            self.routers[host] = self.hosts.popen(
                host, [*(self.hot() if hot else []), *self.energyctl, "router", "--config",
                       str(self.profile / f"router-{host}.json5"), *([] if self.audit else ["--no-audit"])],
                stdout=f, stderr=f, env=self.env)
        self._listening[host] = n
        if wait:
            self.wait_routers([host], timeout_s)

    def start_routers(self, timeout_s: float = 30.0) -> None:
        """Every host's router at once (the spokes retry the hub until it answers), then wait for all."""
        self._listening = {}
        for h in self.place:
            self.start_router(h, wait=False)
        self.wait_routers(list(self.place), timeout_s)

    def wait_routers(self, hosts: list[str], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        left = list(hosts)
        while left:
            for h in list(left):
                p, log = self.routers[h], self._router_log(h)
                if p.poll() is not None:
                    raise RuntimeError(f"the router of {h} exited ({p.returncode}): {log.read_text()[-2000:]}")
                if log.read_text().count("listening") > self._listening.get(h, 0):
                    left.remove(h)
                    self.raise_priority(p.pid)
            if left and time.monotonic() > deadline:
                raise RuntimeError(f"the routers of {left} did not listen within {timeout_s:g} s")
            time.sleep(0.05)

    def raise_priority(self, pid: int, fifo: bool | None = None, priority: int = RT_PRIORITY) -> None:
        """Every thread of pid to the realtime path's priority: SCHED_FIFO ``priority`` where allowed (``fifo`` None
        or True), else (or ``fifo`` False) nice -10."""
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]  # per thread: Zenoh's exist by now
        except OSError:  # it ended
            return
        for tid in tids:
            try:
                if self.rt and fifo is not False:
                    os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
                else:
                    os.setpriority(os.PRIO_PROCESS, tid, NICE)
            except OSError:  # a thread that ended, or no CAP_SYS_NICE: it runs as it is
                pass

    def stop_router(self, host: str) -> None:
        p = self.routers.pop(host)
        p.send_signal(signal.SIGTERM)
        p.wait(10.0)

    # ---------------------------------------------------------------- processes
    def start(self, name: str, host: str, argv: list[str], hot: bool = False) -> subprocess.Popen:
        """``energyctl ARGV`` in a host (stdout to WORK/NAME.out, stderr to WORK/NAME.log); ``hot``: at the
        realtime path's priority."""
        with open(self.work / f"{name}.out", "w") as out, open(self.work / f"{name}.log", "w") as err:
            p = self.hosts.popen(host, [*(self.hot() if hot else []), *self.energyctl, *argv], stdout=out, stderr=err,
                                 env=self.env)
        self.procs[name] = p
        return p

    def log(self, name: str, n: int = 3000) -> str:
        return (self.work / f"{name}.log").read_text(errors="replace")[-n:]

    def set_args(self) -> list[str]:
        return [a for s in self.sets for a in ("--set", s)]

    def start_network(self, sources: list[str], rig_out: Path | None = None, hot: bool = False,
                      source_args: list[str] | None = None) -> subprocess.Popen:
        """The sources' daemons, the coordinator and the rig (last: it waits for the others), lockstep, each on its
        host; the rig's result is its last stdout line (--json); ``hot``: each at the realtime path's priority (in
        lockstep each blocks between samples: it takes the CPU only while a sample is under way). Returns the rig's
        process."""
        scn, sets = str(self.scenario), self.set_args()
        for s in sources:
            self.start(s, self.host_of[s], ["run", "--network", scn, "--source", s, *sets, *(source_args or []),
                                            *self.zenoh_args(s)], hot=hot)
        self.start("coordinator", self.host_of["coordinator"], ["coordinator", scn, *sets,
                                                                *self.zenoh_args("coordinator")], hot=hot)
        return self.start("rig", self.host_of["rig"], [
            "plant", "--config", scn, "--pacing", "lockstep", *sets, "--json",
            *(["--out", str(rig_out)] if rig_out else []), *self.zenoh_args("rig")], hot=hot)

    def stop(self, names: list[str], timeout_s: float = 15.0, batch: int = STOP_BATCH) -> dict[str, int | None]:
        """SIGTERM to each, ``batch`` at a time, each batch waited for: {name: exit code} (None: killed after
        timeout_s). (All 33 of a 32-source run at once did not close their sessions within the daemons' 5 s grace
        on 2 CPUs: SIGALRM ended them, exit -14.)"""
        out: dict[str, int | None] = {}
        for i in range(0, len(names), batch):
            group = names[i:i + batch]
            for n in group:
                if self.procs[n].poll() is None:
                    self.procs[n].send_signal(signal.SIGTERM)
            deadline = time.monotonic() + timeout_s
            for n in group:
                try:
                    out[n] = self.procs[n].wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    self.procs[n].kill()
                    self.procs[n].wait(5.0)
                    out[n] = None
        return out

    def cpu_s(self) -> dict[str, float]:
        """CPU time so far (s) of every running process and router (routers as router-HOST)."""
        out = {}
        for name, p in [*self.procs.items(), *((f"router-{h}", p) for h, p in self.routers.items())]:
            c = proc_cpu_s(p.pid) if p.poll() is None else None
            if c is not None:
                out[name] = c
        return out

    def threads_cpu_s(self, names: list[str]) -> dict[str, dict[str, float]]:
        """proc_threads_cpu_s of each named running process, with its context switches (proc_ctx_switches) as the
        kinds "switches_voluntary" and "switches_involuntary"."""
        out = {}
        for n in names:
            if self.procs[n].poll() is None:
                out[n] = proc_threads_cpu_s(self.procs[n].pid)
                out[n]["switches_voluntary"], out[n]["switches_involuntary"] = proc_ctx_switches(self.procs[n].pid)
        return out

    def rss_mb(self) -> float:
        """Resident memory of every running process and router, MB."""
        return sum(proc_rss_mb(p.pid) or 0.0 for p in [*self.procs.values(), *self.routers.values()]
                   if p.poll() is None)


def last_json(path: Path) -> dict:
    """The JSON line a process printed last on stdout."""
    import json

    lines = [ln for ln in path.read_text().splitlines() if ln.startswith("{")]
    if not lines:
        raise RuntimeError(f"{path.name}: no result line")
    return json.loads(lines[-1])


def identity(rig_log: Path, net) -> dict:
    """The lockstep run in the rig's log against ``energyctl sim`` of the same scenario (service.network.netsim):
    every source's v, i, u and command (du/dt and the planned du/dt it answered each sample with), every bus's v,
    equal bit for bit, and as many samples. ``{"equal": bool, "samples": n, "offline_samples": n, "first":
    [(element, signal, sample, live, offline)], "compared": count of signals}``: the first differing sample of
    each signal that differs."""
    import numpy as np

    from clients.peers.netrig import read_rig_log
    from service.network.netsim import run_network

    live = read_rig_log(str(rig_log))
    off = run_network(net)
    first: list = []
    pairs = [(s, sig, live.sources[s].get(key), off.sources[s][key]) for s in net.sources
             for sig, key in (("v", "v"), ("i", "i"), ("u", "u"), ("cmd du/dt", "cmd_du"),
                              ("cmd du/dt next", "cmd_du_next"))]
    pairs += [(b, "v", live.buses[b], off.buses[b]) for b in net.buses]
    for el, sig, a, b in pairs:
        if a is None:
            first.append((el, sig, 0, "not logged", None))
            continue
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        n = min(len(a), len(b))
        diff = np.nonzero(~((a[:n] == b[:n]) | (np.isnan(a[:n]) & np.isnan(b[:n]))))[0]
        if len(diff):
            k = int(diff[0])
            first.append((el, sig, k, float(a[k]), float(b[k])))
    same_len = len(live.t) == len(off.t)
    return {"equal": same_len and not first, "samples": len(live.t), "offline_samples": len(off.t),
            "compared": len(pairs), "first": first[:10], "differing": len(first)}


def run_hosted(scenario: str | Path, work: str | Path, n_hosts: int, sets: list[str] | None = None,
               progress: Callable[[str], None] | None = None, timeout_s: float | None = None, audit: bool = False,
               wait_before_drop_us: int | None = None, check: bool = True,
               energyctl: list[str] | None = None, idle_probe_s: float = 0.0, hot: bool = True) -> dict:
    """One lockstep run of ``scenario`` across ``n_hosts`` hosts (``placement``), to the rig's end; every process
    and namespace removed afterwards, also on failure or an interrupt (KeyboardInterrupt propagates).

    Returns ``{"ok", "why", "rig": the rig's result, "identity": identity(...), "cpu_s": per process between the
    rig's first sample and its end, "cpu_per_daemon_per_sample_us", "wall_per_sim_s", "startup_s", "wall_s",
    "rss_mb", "place"}``; ``ok``: the rig finished (exit 0, not diverged), no lockstep timeout, every daemon and the
    coordinator stopped on SIGTERM (exit 0, or ended by its shutdown grace: ``ended_by_shutdown_grace``), and
    (``check``) the identity holds. ``energyctl``: the command that starts every
    process (default ``python -m clients.cli``). ``idle_probe_s``: after the rig's end, measure the daemons' CPU for
    this long with no sample coming (``idle_cpu_per_daemon_pct``, % of a CPU). ``hot``: the rig, the coordinator and
    the daemons raised to nice -10 once every one is up, below the routers (SCHED_FIFO where allowed); beside other
    work on the machine a starved sender's queue stayed full past the profile's wait and dropped half a sample's
    burst (decisions/0044)."""
    from schemas.network import load_network

    say = progress or (lambda m: None)
    net = load_network(scenario, sets)
    sources = list(net.sources)
    place = placement(sources, n_hosts)
    work = Path(work)
    duration = net.timing.duration_s
    timeout_s = timeout_s if timeout_s is not None else 120.0 + 400.0 * duration * len(sources)
    t0 = time.monotonic()
    out: dict = {"place": place, "sources": len(sources), "hosts": len(place), "samples_planned":
                 int(round(duration * net.timing.control_rate_hz))}
    with HostedNetwork(scenario, work, place, sets=sets, audit=audit, wait_before_drop_us=wait_before_drop_us,
                       energyctl=energyctl) as hn:
        say(f"{len(place)} hosts (network namespaces): "
            + "; ".join(f"{h}: {', '.join(ids) if len(ids) <= 4 else f'{ids[0]} .. {ids[-1]}'}"
                        for h, ids in place.items()))
        hn.write_profile()
        hn.start_routers()
        say(f"{len(place)} routers listening (secure profile: user/password, access control), "
            f"{time.monotonic() - t0:.1f} s")
        rig = hn.start_network(sources, rig_out=work / "rig.mcap")
        say(f"started {len(sources)} source daemons, the coordinator and the rig; waiting for them to connect")
        rig_log = work / "rig.log"
        deadline = t0 + timeout_s
        cpu0 = None
        last_say = time.monotonic()
        while rig.poll() is None:
            if cpu0 is None and SAMPLING in rig_log.read_text(errors="replace"):
                if hot:  # raised once up (36 start-ups at SCHED_FIFO starved the routers' logins), to nice -10:
                    # raised to SCHED_FIFO (at or below the routers'), the first samples' messages were lost in 2 of
                    # 4 runs under load (decisions/0044)
                    for p in hn.procs.values():
                        hn.raise_priority(p.pid, fifo=False)
                cpu0, th0 = hn.cpu_s(), hn.threads_cpu_s(sources)
                out["startup_s"] = round(time.monotonic() - t0, 1)
                out["rss_mb"] = round(hn.rss_mb())
                say(f"every process up after {out['startup_s']:.1f} s ({out['rss_mb']} MB resident); sampling")
            dead = [n for n, p in hn.procs.items() if n != "rig" and p.poll() is not None]
            if dead:
                raise RuntimeError(f"{dead[0]} exited ({hn.procs[dead[0]].returncode}) before the rig's end: "
                                   f"{hn.log(dead[0], 1500)}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the rig did not finish within {timeout_s:g} s: {hn.log('rig', 1500)}")
            if cpu0 is not None and time.monotonic() - last_say > 10.0:
                last_say = time.monotonic()
                say(f"  sampling, {time.monotonic() - t0:.0f} s")
            time.sleep(0.05)
        cpu1, th1 = hn.cpu_s(), hn.threads_cpu_s(sources)  # the others, idle since the rig's last sample
        out["wall_s"] = round(time.monotonic() - t0, 1)
        if rig.returncode != 0 or SAMPLING not in rig_log.read_text(errors="replace"):
            raise RuntimeError(f"the rig failed (exit {rig.returncode}): {hn.log('rig', 2000)}")
        if cpu0 is None:  # a run shorter than one look at the rig's log: no CPU figures
            cpu0, th0 = {}, {}
            out.setdefault("startup_s", out["wall_s"])
            out.setdefault("rss_mb", None)
        res = last_json(work / "rig.out")
        if idle_probe_s:  # what the daemons use with no sample coming: Zenoh's and their own timers
            t_idle = time.monotonic()
            time.sleep(idle_probe_s)
            cpu2 = hn.cpu_s()
            idle = [(cpu2[s] - cpu1[s]) / (time.monotonic() - t_idle) for s in sources if s in cpu1 and s in cpu2]
            out["idle_cpu_per_daemon_pct"] = round(100.0 * sum(idle) / len(idle), 2) if idle else None
        codes = hn.stop([*sources, "coordinator"])
        out["exit_codes"] = {n: c for n, c in codes.items() if c != 0}
    res.pop("result", None)
    out["rig"] = {k: res[k] for k in ("counters", "samples", "wall_s", "rate_achieved_hz", "cpu", "state")
                  if k in res}
    out["rig"]["diverged"] = res["metrics"]["diverged"]
    samples = res["samples"]
    cpu = {n: cpu1[n] - cpu0[n] for n in cpu1 if n in cpu0}
    if res.get("cpu", {}).get("rig_pct") is not None and res.get("wall_s"):
        cpu["rig"] = res["cpu"]["rig_pct"] / 100.0 * res["wall_s"]
    out["cpu_s"] = {n: round(c, 3) for n, c in cpu.items()}
    daemons = [cpu[s] for s in sources if s in cpu]
    out["cpu_per_daemon_per_sample_us"] = round(sum(daemons) / len(daemons) / samples * 1e6, 1) if daemons else None
    out["cpu_total_per_sample_us"] = round(sum(cpu.values()) / samples * 1e6, 1)
    # where a daemon's CPU goes: its Python threads (the loop first of all) against Zenoh's runtime threads
    kinds: dict[str, float] = {}
    both = [s for s in sources if s in th0 and s in th1]
    for s in both:
        for kind, c in th1[s].items():
            kinds[kind] = kinds.get(kind, 0.0) + c - th0[s].get(kind, 0.0)
    switches = {k: kinds.pop(k, 0.0) for k in ("switches_voluntary", "switches_involuntary")}
    out["cpu_per_daemon_per_sample_by_thread_us"] = {k: round(c / len(both) / samples * 1e6, 1)
                                                     for k, c in sorted(kinds.items())} if both else None
    # how often a daemon's threads were switched per sample: voluntary (waiting), involuntary (preempted)
    out["switches_per_daemon_per_sample"] = {k.split("_")[1]: round(c / len(both) / samples, 2)
                                             for k, c in switches.items()} if both else None
    out["wall_per_sim_s"] = round(res["wall_s"] / (samples / net.timing.control_rate_hz), 2)
    why = []
    if res["metrics"]["diverged"]:
        why.append("the network diverged")
    if res["counters"].get("timeouts"):
        why.append(f"{res['counters']['timeouts']} lockstep timeouts")
    # a daemon whose session close outlasted its 5 s shutdown grace (clients.live.install_stop_handlers) ended by
    # SIGALRM: seen under load from other work on the machine; its run was over, its answers all in the rig's log
    out["ended_by_shutdown_grace"] = sorted(n for n, c in out["exit_codes"].items() if c == -signal.SIGALRM)
    bad = {n: c for n, c in out["exit_codes"].items() if c != -signal.SIGALRM}
    if bad:
        why.append(f"exit codes {bad}")
    if check:
        say("checking against energyctl sim of the same scenario")
        out["identity"] = identity(work / "rig.mcap", net)
        if not out["identity"]["equal"]:
            why.append(f"differs from energyctl sim: {out['identity']['first'][:3]}, samples "
                       f"{out['identity']['samples']} vs {out['identity']['offline_samples']}")
    out["ok"], out["why"] = not why, "; ".join(why)
    return out


RADIAL_DURATION_S = 0.1  # the scale runs' default: 1 000 samples at 10 kHz


def write_radial(path: str | Path, n_sources: int, duration_s: float = RADIAL_DURATION_S) -> Path:
    """clients.bench.network.radial(n_sources, duration_s) written as a scenario file (every process of a live run
    reads the same file), ``# energyctl sim PATH`` runs it offline."""
    from clients.bench.network import radial
    from clients.live import _toml
    from schemas.network import network_from_dict

    data = radial(n_sources, duration_s)
    network_from_dict(data)  # a bad size fails here, naming the field, before anything is written
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# radial({n_sources}) of clients/bench/network.py, {duration_s:g} s (clients.nethosts)\n"
                    + _toml(data))
    return path
