"""Live processes: what energyctl run / plant / load do first (start_process), the configs of a loopback stack
for a scenario, child processes that are always stopped, and the loopback demo that starts all three."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from schemas.component import ComponentConfig, LoadPeerConfig, PlantPeerConfig, config_from_dict
from schemas.scenario import Scenario
from service.priority import STOP_GRACE_S

SHUTDOWN_GRACE_S = STOP_GRACE_S  # service.priority.extend_stop_grace moves it while a stop makes progress
REALTIME_NICE = -10  # realtime stacks: controller, plant and load above everything else on the machine
REALTIME_STEP_V = 20.0  # realtime stacks: the controller's slew limit, V per control period
# realtime stacks: the nested law's rates (1/s), for a schedule of several ms (configs_from_scenario)
REALTIME_NESTED_RATES = {"nested_K_u_per_s": 2000.0, "nested_K_P_per_s": 1000.0, "nested_K_E_per_s": 300.0}


def install_stop_handlers(stop: threading.Event) -> None:
    """SIGINT/SIGTERM ask for a clean stop; if the stop hangs (we saw a plant stuck in Zenoh's session close,
    a GIL/callback deadlock), SIGALRM's default action ends the process after SHUTDOWN_GRACE_S. The alarm is armed
    in C at the signal itself (service._stopsignal), not by the Python handler, which never runs in a process whose
    GIL is held by a deadlocked thread; without the compiled module, by the Python handler. When the alarm fires it
    first prints every thread's stack to stderr (faulthandler's C handler, no GIL needed): what held the stop up,
    where SIGALRM alone would leave only an exit code."""
    import faulthandler

    try:
        from service._stopsignal import arm
    except ImportError:  # built without a C compiler
        arm = None

    def handler(signum, frame):  # noqa: ARG001
        stop.set()
        if arm is None:  # armed in C otherwise, once: a later signal does not move the deadline
            signal.alarm(SHUTDOWN_GRACE_S)

    # the stacks, then SIGALRM's default action (chain): the process still ends at the grace
    faulthandler.register(signal.SIGALRM, all_threads=True, chain=True)
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    if arm is not None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            arm(sig, SHUTDOWN_GRACE_S)


def start_process(cfg, command: str) -> threading.Event:
    """First thing in energyctl run/plant/load: the stop event, its signal handlers, and the configured CPUs,
    priority and timer slack (before any thread exists, so that Zenoh's threads and spawned processes inherit them)
    and mmap threshold (this process's allocator: before Zenoh's threads allocate)."""
    from service.priority import set_cpus, set_mmap_threshold, set_nice, set_timer_slack

    stop = threading.Event()
    install_stop_handlers(stop)
    for refused in (set_cpus(cfg.cpus), set_nice(cfg.nice), set_timer_slack(cfg.timer_slack_ns),
                    set_mmap_threshold(cfg.malloc_mmap_threshold_bytes)):
        if refused:
            print(f"energyctl {command}: {refused}", file=sys.stderr, flush=True)
    return stop


def configs_from_scenario(scn: Scenario, endpoint: str, lockstep: bool, rate_hz: float | None = None,
                          controller_delay: int | None = None, out: str | None = None,
                          duration_s: float | None = None, loop: dict | None = None,
                          nice: int | None = None, cpus: dict[str, list[int]] | None = None
                          ) -> tuple[dict, dict, dict]:
    """Component, plant and load configs (as dicts) for one scenario on one loopback endpoint.

    The controller listens; plant and load connect to it. The controller ticks on each measurement (the
    plant's sampling is the time base, as on a HIL rig). Lockstep: the plant adds the scenario's loop
    delay and the controller compensates exactly that, as in ``energyctl sim``. Realtime: the plant
    applies each command at the sampling instant after it arrives (one sample of delay while the round
    trip is shorter than a period); the controller compensates ``controller_delay`` samples (default 1).
    Realtime also runs controller, plant and load at nice ``nice`` (default REALTIME_NICE), above the background
    processes, the controller blocks on its samples (spinning took a core from the plant), answers up
    to ``controller_delay`` queued samples in order after a stall (loop.catch_up, unless ``loop`` sets it), and it
    falls back to the measured load power while the load has not been heard from. ``cpus``: the CPUs each of
    "controller", "plant" and "load" may run on (their ``cpus`` config; default any).
    """
    tm = scn.timing
    rate = rate_hz or tm.control_rate_hz
    zl = {"mode": "peer", "listen": [endpoint]}
    zc = {"mode": "peer", "connect": [endpoint]}
    comp = {"id": "source", "zenoh": zl, "model": scn.model.model_dump(), "controller": scn.controller.model_dump(),
            "neighbours": ["load"], "plant_id": "source",
            "delay_samples": tm.delay_samples if lockstep else (1 if controller_delay is None else controller_delay),
            "loop": {"rate_hz": rate, "trigger": "sample", "lockstep": lockstep, "wait": "block", **(loop or {})},
            "forecast_window_s": scn.feasibility.window_s, "interaction_rate_hz": 100.0}
    comp["controller"]["delay_compensation_samples"] = None
    if out:
        comp["log_dir"] = str(Path(out).parent)

    plant = {"id": "plant", "controller_id": "source", "wait_for": ["load"], "zenoh": zc,
             "plant": scn.plant.model_dump(),
             "load": scn.load.model_dump(), "sensor": scn.sensor.model_dump(), "sample_rate_hz": rate,
             "plant_step_s": tm.plant_step_s, "delay_samples": tm.delay_samples if lockstep else 0,
             "pacing": "lockstep" if lockstep else "realtime", "duration_s": duration_s or tm.duration_s,
             "seed": scn.seed, "v_ref_V": scn.controller.v_ref_V, "acceptance": scn.acceptance.model_dump(),
             "out": out, "base_dir": scn.base_dir,
             "realtime_apply_delay_samples": max(1, comp["delay_samples"])}
    if scn.disturbance is not None:
        plant["disturbance"] = scn.disturbance.model_dump()
    if not lockstep:
        comp["nice"] = plant["nice"] = REALTIME_NICE if nice is None else nice
        # after a stall, answer the queued samples whose commands can still act (up to the schedule's length) in
        # order, not only the newest: with catch_up 1 the others were lost, most of the controller's misses
        # (docs/decisions)
        comp["loop"].setdefault("catch_up", max(1, comp["delay_samples"]))
        # until the load's first message arrives (it follows the plant's clock, so a few ms after the first
        # sample) and whenever it goes quiet: regulate to the load power measured at the port, not hold du/dt = 0
        # (held, the LC pair rang open loop from i = 1 A and the law took over from 35 A, sometimes diverging)
        comp["local_reference_W"] = "measured"
        # at most REALTIME_STEP_V of source-voltage change per period, as the paper scenario's 2e5 V/s is at 10 kHz:
        # at 1 kHz that slew limit allowed 200 V per period, and one late command during the start-up transient
        # was answered with +-50 kV/s and diverged; 20 V per period regulates as before offline (docs/decisions)
        lim = comp["controller"]["limits"]
        lim["du_dt_max_V_per_s"] = min(lim["du_dt_max_V_per_s"], REALTIME_STEP_V * rate)
        # the load power for the prediction as the load announces it (200 Hz, carried to the sample's time), not
        # v i_load measured: that current's noise was most of the commands' noise, and made every late or lost
        # command cost a few volts over an 8 ms schedule (docs/decisions)
        if "load_power" not in scn.controller.model_fields_set:
            comp["controller"]["load_power"] = "reference"
        # and regulate the stored energy at K_E (default 100/s) instead of the paper's map, whose v converges with
        # C v^2 / P (about 36 ms): a 10 ms stall in the start-up transient left v 5 % low at 50 ms, 1.3 % so
        # (docs/decisions)
        if "regulation" not in scn.controller.model_fields_set:
            comp["controller"]["regulation"] = "energy"
        # the nested law's rates for a realtime schedule: predicting over 8 ms of commands some of which come late
        # or not at all, the 10 kHz rates left v 3.1 % off at 2 kHz with 5 % of the commands lost and 5 % late;
        # these held it within 1.05 % (fblc's figure there: 0.63 %) (docs/decisions)
        for key, value in REALTIME_NESTED_RATES.items():
            if key not in scn.controller.model_fields_set:
                comp["controller"][key] = value
        # no late-command detection (late_detect_V stays as the scenario says, default 0 = off): with plans and the
        # observer it did harm offline under every pattern of late and lost commands tried, up to divergence, and in
        # 28 alternated realtime pairs it made no difference (docs/decisions, late-command detection)
    load = {"id": "load", "zenoh": zc, "load": scn.load.model_dump(), "plant_id": "source",
            "pacing": "lockstep" if lockstep else "realtime", "rate_hz": 200.0,
            "window_s": scn.feasibility.window_s, "forecast_margin": scn.feasibility.forecast_margin,
            "base_dir": scn.base_dir}
    if out:
        load["log_dir"] = str(Path(out).parent)
    if not lockstep:
        # the load too: at 3 kHz, at nice 0 under the other two, its 200 Hz messages came in bursts after silences
        # of up to 56 ms, and the reference carried from its last one drifted 440 W off (docs/decisions)
        load["nice"] = comp["nice"]
    for role, d in (("controller", comp), ("plant", plant), ("load", load)):
        if cpus and role in cpus:
            d["cpus"] = cpus[role]
    # validate here so a bad scenario fails before any process starts
    config_from_dict(ComponentConfig, comp)
    config_from_dict(PlantPeerConfig, plant)
    config_from_dict(LoadPeerConfig, load)
    return comp, plant, load


def _toml(d: dict, prefix: str = "") -> str:
    """Minimal TOML writer for our config dicts (tables, scalars, lists of scalars/lists/tables)."""
    scal, tabs = [], []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, dict):
            tabs.append((k, v))
        else:
            scal.append(f"{k} = {_tv(v)}")
    out = ([f"[{prefix}]"] if prefix and scal else []) + scal
    for k, v in tabs:
        out.append(_toml(v, f"{prefix}.{k}" if prefix else k))
    return "\n".join(out) + "\n"


def _tv(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_tv(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_tv(x)}" for k, x in v.items() if x is not None) + "}"
    raise TypeError(type(v))


def child_env() -> dict:
    """The environment for child ``python -m clients.cli`` processes: this checkout first on the path."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parent.parent) + os.pathsep + env.get("PYTHONPATH", "")
    return env


class Processes:
    """Child processes that are stopped (SIGTERM, then SIGKILL) whatever happens, including a SIGTERM to
    this process (in the main thread it becomes SystemExit, so the ``with`` block still cleans up)."""

    def __init__(self, out_dir: Path | None = None):
        """out_dir: each child writes its stdout and stderr to files there (NAME.out, NAME.err) instead of pipes;
        for runs of minutes, where a pipe that nobody reads fills at 64 KiB and then blocks the child's next
        write (a daemon thread printing a line a window would stall after about ten minutes)."""
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self.out_dir = out_dir
        self._old_term = None
        if threading.current_thread() is threading.main_thread():
            self._old_term = signal.signal(signal.SIGTERM, _exit_on_term)

    def start(self, name: str, args: list[str], **kw) -> subprocess.Popen:
        """``energyctl ARGS`` as a child that ends with this process, even a SIGKILLed one (the child's main asks for
        it: service.priority.die_with_parent_from_env)."""
        from service.priority import parent_env

        cmd = [sys.executable, "-m", "clients.cli", *args]
        kw["env"] = {**(kw.get("env") or os.environ), **parent_env()}
        if self.out_dir is None:
            p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
        else:
            with open(self.out_dir / f"{name}.out", "w") as so, open(self.out_dir / f"{name}.err", "w") as se:
                p = subprocess.Popen(cmd, stdout=so, stderr=se, text=True, **kw)
        self.procs.append((name, p))
        return p

    def _outputs(self, name: str, so: str | None, se: str | None) -> tuple[str, str]:
        if self.out_dir is None:
            return so or "", se or ""
        return tuple((self.out_dir / f"{name}.{ext}").read_text(errors="replace") for ext in ("out", "err"))

    def stop_all(self, timeout_s: float = 30.0) -> dict[str, tuple[int, str, str]]:
        """SIGTERM all, wait up to timeout_s in total, SIGKILL the rest. Never blocks on a pipe that a
        grandchild still holds open. A child of ours that hangs in its stop ends by itself SHUTDOWN_GRACE_S after the
        signal; one whose recorder is still writing the rest of its ring goes on as long as that makes progress
        (5 s of a 2 kHz stack's backlog seen on a loaded machine), so the cap is generous."""
        for _, p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        out = {}
        for name, p in self.procs:
            try:
                so, se = p.communicate(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                try:
                    so, se = p.communicate(timeout=2.0)
                except subprocess.TimeoutExpired:
                    for f in (p.stdout, p.stderr):
                        if f is not None:
                            f.close()
                    p.wait(5.0)
                    so, se = "", ""
            out[name] = (p.returncode, *self._outputs(name, so, se))
        return out

    def __enter__(self):
        return self

    def close(self) -> dict[str, tuple[int, str, str]]:
        out = self.stop_all()
        if self._old_term is not None:
            signal.signal(signal.SIGTERM, self._old_term)
            self._old_term = None
        return out

    def __exit__(self, *exc):
        self.close()


def _exit_on_term(signum, frame):
    raise SystemExit(128 + signum)


def run_live(scn: Scenario, lockstep: bool, rate_hz: float | None, out: str | None, duration_s: float | None,
             controller_delay: int | None = None, workdir: str | None = None, timeout_s: float = 300.0,
             secure: bool = False, tls: bool = False, loop: dict | None = None, nice: int | None = None,
             cpus: dict[str, list[int]] | None = None, extra=None) -> dict:
    """Start controller, load and plant on a free loopback port; wait for the plant; stop the rest.

    ``extra(endpoint, procs, env)``: called after the daemon and the load started and before the plant, to start
    more processes beside them (procs.start; they are stopped with the rest); what it returns is the result's
    "extra", and its processes' outputs are in "extra_outputs" (by name: returncode, stdout, stderr).

    ``secure``: the three connect as Zenoh clients, each with its own credentials, to a router that
    enforces the secure profile (``clients.secure``), written to the work directory first; ``tls``: over
    mutual TLS, each also with its own certificate."""
    from service.daemon.bus import free_tcp_port

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    comp, plant, load = configs_from_scenario(scn, ep, lockstep, rate_hz, controller_delay, out, duration_s, loop,
                                              nice, cpus)
    tmp = Path(workdir or tempfile.mkdtemp(prefix="energyctl-"))
    if secure:
        from clients.secure import client_zenoh, write_profile

        creds = write_profile(tmp / "secure", controllers=["source"], plants={"plant": "source"}, loads=["load"],
                              listen=[ep], tls=tls)
        for d in (comp, plant, load):
            d["zenoh"] = client_zenoh(ep, d["id"], creds[d["id"]], creds.get("tls"))
    paths = {}
    for name, d in (("component", comp), ("plant", plant), ("load", load)):
        paths[name] = tmp / f"{name}.toml"
        paths[name].write_text(_toml(d))
    stats_path = tmp / "daemon-status.json"
    env = child_env()
    with Processes() as procs:
        if secure:
            procs.start("router", ["router", "--config", str(creds["router"])], env=env)
            if not wait_until(lambda: port_open(ep), COME_UP_S):
                raise RuntimeError(f"the router did not listen on {ep} within {COME_UP_S:g} s")
        procs.start("daemon", ["run", "--config", str(paths["component"]), "--stats-out", str(stats_path)], env=env)
        procs.start("load", ["load", "--config", str(paths["load"])], env=env)
        extra_res = extra(ep, procs, env) if extra is not None else None
        p = procs.start("plant", ["plant", "--config", str(paths["plant"]), "--json"], env=env)
        try:
            so, se = p.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"plant did not finish within {timeout_s:g} s") from None
        results = procs.stop_all()
    if p.returncode != 0:
        raise RuntimeError(f"plant failed ({p.returncode}): {se.strip()[-800:]}")
    res = json.loads(so.strip().splitlines()[-1])
    res["daemon"] = json.loads(stats_path.read_text()) if stats_path.exists() else {
        "error": results.get("daemon", (None, "", ""))[2][-800:]}
    res["endpoint"] = ep
    res["daemon_log"] = (res["daemon"].get("logging") or {}).get("path")
    res.setdefault("cpu", {})["controller_pct"] = (res["daemon"].get("loop") or {}).get("cpu_pct")
    res["cpu"]["load_pct"] = _last_json(results.get("load", (None, "", ""))[1]).get("cpu_pct")
    if extra is not None:
        res["extra"] = extra_res
        res["extra_outputs"] = {k: v for k, v in results.items() if k not in ("daemon", "load", "plant", "router")}
    return res


def _last_json(stdout: str) -> dict:
    """A child's result: the last line of its stdout as a JSON object ({} if there is none)."""
    lines = (stdout or "").strip().splitlines()
    try:
        out = json.loads(lines[-1]) if lines else {}
    except json.JSONDecodeError:
        return {}
    return out if isinstance(out, dict) else {}


def port_open(endpoint: str) -> bool:
    """Whether something accepts TCP connections at a ``tcp/HOST:PORT`` endpoint."""
    import socket

    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    try:
        with socket.create_connection((host, int(port)), timeout=0.2):
            return True
    except OSError:
        return False


# how long a process started here may take to come up (interpreter, imports, its Zenoh session, its token): on a
# machine busy with other work (CI beside a CPU-heavy job) 20 s was seen to pass; one that is up sooner costs nothing
COME_UP_S = 60.0


def stop_process(p, grace_s: float = 10.0) -> None:
    """End a process we started (subprocess.Popen): SIGTERM, then SIGKILL if it has not ended within grace_s."""
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(grace_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def wait_until(pred, timeout_s: float, every_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(every_s)
    return pred()
