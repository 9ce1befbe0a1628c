"""Hosts on one machine: Linux network namespaces joined by veth links to a switch (needs root).

``Hosts(["rig", "S1", ...])`` makes, under unique names (a random tag, so parallel runs do not collide):

* one namespace per host, with ``lo`` up and one interface ``eth0`` carrying the host's address from a private
  /24 (default 10.201.0.0/24: the first host .1, the next .2, ...); the addresses exist only inside the namespaces
  made here;
* a switch namespace holding a bridge, with the other end of each host's veth link as a port (``port(host)``).

``cut(host)`` sets the switch's end of the host's link down (the cable pulled at the switch: the host keeps its
address, every packet between it and the others is lost, no connection is told); ``restore(host)`` sets it up.
``popen(host, argv)`` starts a process inside a host (``ip netns exec``); ``close()`` stops the processes it
started that still run and deletes every namespace (the links and addresses go with them). ``close()`` is
idempotent and never raises: call it in a ``finally`` (``with Hosts(...) as hosts:`` does).

    with Hosts(["a", "b"]) as h:
        h.popen("a", ["python3", "-m", "http.server", "--bind", h.address("a")])
        h.run("b", ["curl", f"http://{h.address('a')}:8000/"])
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import subprocess
import sys
import time


class NetnsUnavailable(RuntimeError):
    """This machine (or this user) cannot create network namespaces: not root, no ``ip`` command, no netns."""


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run(["ip", *args], capture_output=True, text=True)
    if check and r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip() or r.returncode}")
    return r


def unavailable_reason() -> str | None:
    """Why namespaces cannot be made here (None: they can): tried by creating and deleting one."""
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces need root (run as root, or in CI where root is available)"
    if shutil.which("ip") is None:
        return "the 'ip' command (iproute2) is not installed"
    name = f"ecprobe{secrets.token_hex(4)}"
    r = _ip("netns", "add", name, check=False)
    if r.returncode != 0:
        return f"'ip netns add' failed: {r.stderr.strip() or r.returncode}"
    try:
        r = _ip("-n", name, "link", "add", "br0", "type", "bridge", check=False)
        if r.returncode != 0:
            return f"cannot create a bridge inside a namespace: {r.stderr.strip() or r.returncode}"
    finally:
        _ip("netns", "del", name, check=False)
    return None


class Hosts:
    """See the module docstring."""

    def __init__(self, names: list[str], subnet: str = "10.201.0", tag: str | None = None):
        if len(set(names)) != len(names) or not names:
            raise ValueError(f"hosts: give distinct names, got {names}")
        if len(names) > 250:
            raise ValueError("hosts: at most 250 in a /24")
        self.names = list(names)
        self.subnet = subnet
        self.tag = tag or secrets.token_hex(3)
        self.switch = f"ec{self.tag}sw"
        self._ns = {h: f"ec{self.tag}h{i}" for i, h in enumerate(self.names)}
        self._port = {h: f"ec{self.tag}p{i}" for i, h in enumerate(self.names)}
        self._made: list[str] = []  # namespaces created, in order
        self.procs: list[subprocess.Popen] = []

    # ---------------------------------------------------------------- names
    def ns(self, host: str) -> str:
        """The namespace of a host (for ``ip netns exec``)."""
        return self._ns[host]

    def port(self, host: str) -> str:
        """The switch's end of the host's link (in the switch namespace)."""
        return self._port[host]

    def address(self, host: str) -> str:
        return f"{self.subnet}.{self.names.index(host) + 1}"

    # ---------------------------------------------------------------- setup / teardown
    def create(self) -> Hosts:
        try:
            self._add_ns(self.switch)
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge", "stp_state", "0", "forward_delay", "0")
            _ip("-n", self.switch, "link", "set", "br0", "up")
            for h in self.names:
                ns, port, tmp = self._ns[h], self._port[h], f"ec{self.tag}t{self.names.index(h)}"
                self._add_ns(ns)
                # made inside the switch namespace (no name in the root namespace), its peer moved to the host
                _ip("-n", self.switch, "link", "add", port, "type", "veth", "peer", "name", tmp, "netns", ns)
                _ip("-n", ns, "link", "set", tmp, "name", "eth0")
                _ip("-n", ns, "addr", "add", f"{self.address(h)}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "lo", "up")
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", self.switch, "link", "set", port, "master", "br0")
                _ip("-n", self.switch, "link", "set", port, "up")
        except BaseException:
            self.close()
            raise
        return self

    def _add_ns(self, name: str) -> None:
        _ip("netns", "add", name)
        self._made.append(name)

    def close(self) -> None:
        """Stop the processes started here, delete the namespaces made here. Idempotent; never raises."""
        for p in self.procs:
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except OSError:
                    pass
        deadline = time.monotonic() + 5.0
        for p in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                try:
                    p.wait(timeout=2.0)
                except subprocess.TimeoutExpired:
                    pass
        self.procs.clear()
        for name in reversed(self._made):
            _ip("netns", "del", name, check=False)
        self._made.clear()

    def __enter__(self) -> Hosts:
        return self.create()

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- processes
    def argv(self, host: str, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self._ns[host], *argv]

    def popen(self, host: str, argv: list[str], **kw) -> subprocess.Popen:
        """Start argv inside the host (``ip netns exec`` execs it: the Popen's pid is the process's). Stopped by
        close() if still running."""
        p = subprocess.Popen(self.argv(host, argv), **kw)
        self.procs.append(p)
        return p

    def run(self, host: str, argv: list[str], timeout: float = 30.0, **kw) -> subprocess.CompletedProcess:
        kw.setdefault("capture_output", True)
        kw.setdefault("text", True)
        return subprocess.run(self.argv(host, argv), timeout=timeout, **kw)

    # ---------------------------------------------------------------- links
    def cut(self, host: str) -> None:
        """Pull the host's cable at the switch: ``ip link set PORT down`` in the switch namespace."""
        _ip("-n", self.switch, "link", "set", self._port[host], "down")

    def restore(self, host: str) -> None:
        _ip("-n", self.switch, "link", "set", self._port[host], "up")

    def link_up(self, host: str) -> bool:
        r = _ip("-n", self.switch, "-o", "link", "show", self._port[host])
        return "state UP" in r.stdout or ",UP" in r.stdout.split(">")[0]
