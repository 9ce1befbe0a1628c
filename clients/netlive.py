"""A network scenario live on one machine: the rig, the coordinator and one daemon per source as separate processes
on a free loopback port (energyctl demo --network, the live-network tests and benches).

The rig listens; the others connect to it as Zenoh peers (they find each other through it, over loopback only,
multicast scouting off). Every process reads the same scenario file with the same ``--set`` overrides. Each writes
its stdout and stderr to WORKDIR/NAME.out and .err, and its log to WORKDIR/logs/. ``close()`` stops every process
it started (SIGTERM, then SIGKILL), also on failure.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

from clients.live import Processes
from schemas.network import load_network
from service.daemon.bus import free_tcp_port


class LiveNetwork:
    """See the module docstring. ``realtime``: wall-clock pacing (else lockstep); ``connect_at``: per source, its
    --connect-at (default: the scenario's connect event)."""

    def __init__(self, scenario: str | Path, workdir: str | Path, sets: list[str] | None = None,
                 realtime: bool = False, connect_at: dict[str, float] | None = None, prefix: str = "energyctl",
                 nice: int | None = None):
        self.scenario = str(scenario)
        self.sets = list(sets or [])
        self.net = load_network(self.scenario, self.sets)
        self.workdir = Path(workdir)
        self.logs = self.workdir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.realtime = realtime
        self.connect_at = dict(connect_at or {})
        self.prefix = prefix
        self.nice = nice
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.procs = Processes(self.workdir)
        self.by_name: dict = {}
        self.restarts: dict[str, int] = {}

    # ---------------------------------------------------------------- processes
    def _set_args(self) -> list[str]:
        return [a for s in self.sets for a in ("--set", s)]

    def _start(self, name: str, args: list[str]):
        n = self.restarts.get(name, 0)
        self.restarts[name] = n + 1
        tag = name if n == 0 else f"{name}.{n}"
        p = self.procs.start(tag, args)
        self.by_name[name] = p
        return p

    def start_rig(self) -> None:
        args = ["plant", "--config", self.scenario, *self._set_args(), "--listen", self.endpoint, "--json",
                "--out", str(self.logs / "rig.mcap"), "--prefix", self.prefix,
                "--pacing", "realtime" if self.realtime else "lockstep"]
        self._start("rig", args)

    def start_coordinator(self, out: str | None = None) -> None:
        n = self.restarts.get("coordinator", 0)
        out = out or str(self.logs / ("coordinator.mcap" if n == 0 else f"coordinator.{n}.mcap"))
        args = ["coordinator", self.scenario, *self._set_args(), "--connect", self.endpoint, "--out", out,
                "--prefix", self.prefix, *(["--realtime"] if self.realtime else [])]
        self._start("coordinator", args)

    def start_source(self, name: str, connect_at: float | None = None) -> None:
        at = connect_at if connect_at is not None else self.connect_at.get(name)
        n = self.restarts.get(name, 0)
        args = ["run", "--network", self.scenario, *self._set_args(), "--source", name, "--connect", self.endpoint,
                "--log-dir", str(self.logs), "--prefix", self.prefix,
                "--stats-out", str(self.workdir / (f"{name}.status.json" if n == 0 else f"{name}.{n}.status.json")),
                *(["--realtime"] if self.realtime else []), *(["--connect-at", str(at)] if at is not None else [])]
        self._start(name, args)

    def start(self, sources: list[str] | None = None) -> None:
        """The rig first (it listens), then the coordinator and every source (or those named)."""
        self.start_rig()
        self.start_coordinator()
        for s in sources if sources is not None else self.net.sources:
            self.start_source(s)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        p = self.by_name[name]
        if p.poll() is None:
            os.kill(p.pid, sig)
            p.wait(10)

    def alive(self, name: str) -> bool:
        p = self.by_name.get(name)
        return p is not None and p.poll() is None

    # ---------------------------------------------------------------- waiting and asking
    def wait_rig(self, timeout_s: float) -> dict:
        """The rig's result (its --json line) once it ends; raises if it did not end in time or failed."""
        p = self.by_name["rig"]
        try:
            p.wait(timeout_s)
        except Exception as e:  # noqa: BLE001 - TimeoutExpired: say what the processes said
            raise RuntimeError(f"the rig did not finish within {timeout_s:g} s; {self.tails()}") from e
        n = self.restarts.get("rig", 1) - 1
        text = (self.workdir / ("rig.out" if n == 0 else f"rig.{n}.out")).read_text()
        lines = [ln for ln in text.splitlines() if ln.startswith("{")]
        if p.returncode != 0 or not lines:
            raise RuntimeError(f"the rig failed (exit {p.returncode}); {self.tails()}")
        return json.loads(lines[-1])

    def end_rig(self, timeout_s: float) -> dict:
        """Ask the rig to end now (SIGINT: it stops sampling, writes its log and its result as at the end of its
        duration); its result (wait_rig). For a test that has seen what it waits for before the run's end."""
        p = self.by_name["rig"]
        if p.poll() is None:
            os.kill(p.pid, signal.SIGINT)
        return self.wait_rig(timeout_s)

    def tails(self, n: int = 6) -> str:
        out = []
        for f in sorted(self.workdir.glob("*.err")):
            lines = f.read_text(errors="replace").splitlines()[-n:]
            if lines:
                out.append(f"{f.name}: " + " | ".join(lines))
        return "; ".join(out)

    def session(self):
        """A Zenoh session of this process on the network (to query it)."""
        from schemas.component import ZenohConfig
        from service.daemon.bus import open_session

        return open_session(ZenohConfig(mode="peer", connect=[self.endpoint]))

    def query(self, session, component: str, what: str = "status", timeout_s: float = 2.0) -> dict:
        from clients.query import ask

        return ask(session, self.prefix, component, what, timeout_s=timeout_s)

    def wait_until(self, session, component: str, pred, timeout_s: float, what: str = "status") -> dict:
        """Poll a component's status until pred(status) holds; the status, or raises with the last one."""
        deadline = time.monotonic() + timeout_s
        last: dict | Exception = {}
        while time.monotonic() < deadline:
            rig = self.by_name.get("rig")
            if rig is not None and rig.poll() is not None and component != "rig":
                raise RuntimeError(f"the rig ended (exit {rig.returncode}) before {component} {what} came true; "
                                   f"{self.tails()}")
            try:
                last = self.query(session, component, what, timeout_s=1.0)
                if pred(last):
                    return last
            except Exception as e:  # noqa: BLE001 - not up yet: ask again
                last = e
            time.sleep(0.05)
        raise TimeoutError(f"{component} {what}: condition not met within {timeout_s:g} s; last: {last!r:.600}")

    def daemon_logs(self, source: str) -> list[Path]:
        return sorted(self.logs.glob(f"{source}-*.mcap"))

    def close(self) -> dict:
        return self.procs.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
