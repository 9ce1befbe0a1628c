"""What a secure router refused, from Zenoh's own log: failed logins and access-control denials.

Zenoh (1.10) reports both only in its tracing log: a failed user/password handshake at DEBUG on
``zenoh_transport::unicast::establishment::accept`` ("UsrPwd extension - Recv OpenSyn. Invalid password."), and each
access-control decision at TRACE on ``zenoh::net::routing::interceptor::access_control`` ("ZID on SUBJECT is
unauthorized to Put (ingress) on KEY", and for a later message on a key already decided "Using cached result: ZID is
unauthorized to ..."). At TRACE that target also writes a line for every *allowed* message and, when it first meets a
key, one line per message kind it caches a decision for (``caching permissions for `KEY` ...``, then the kinds in a
fixed order, ending with "Declare Liveliness Subscriber"): neither is a refusal.

``RefusalLog.feed`` classifies one log line: a refusal is counted (by subject, message kind and key; a failed login by
its reason) and printed, the first of each kind at once and repeats summarised at most every ``every_s``; allowed
messages and cache fills are dropped; any other line (warnings, errors) is passed on. ``capture_stdout`` feeds it the
process's own stdout, where zenoh-python's log subscriber writes (``zenoh.init_log_from_env_or``), through a pipe whose
write end never blocks the router (a line that does not fit in it is lost). See
docs/decisions/0041-router-refusal-log.md for what this costs.
"""

from __future__ import annotations

import fcntl
import os
import re
import sys
import threading
import time

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
AUTH_TARGET = "zenoh_transport::unicast::establishment::accept"
# the directives energyctl router logs with when RUST_LOG is not set: refusals, and warnings from the rest
DIRECTIVES = f"warn,{AUTH_TARGET}=debug,{ACL_TARGET}=trace"
MAX_KINDS = 200  # distinct (subject, message, key) counted apart; beyond that, under "other"

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_DECISION = re.compile(r"(?:Using cached result: )?(?P<zid>[0-9a-f]+)(?: on (?P<subject>.+?))? is "
                       r"(?P<verdict>un)?authorized to (?P<msg>.+?) on (?P<key>\S+)$")
_CACHING = re.compile(r"caching permissions for `(?P<key>[^`]*)`")
_LAST_KIND = "Declare Liveliness Subscriber"  # the last kind of a cache fill
_USER = re.compile(r"Username\(([^)]*)\)")
_LOGIN = re.compile(r"(?P<ext>UsrPwd|PubKey) extension.*?(?P<why>Invalid [^.]+)")


def _subject_name(subject: str | None, zid: str) -> str:
    """A readable subject: the user name Zenoh matched (Interface(lo)+Username(monitor)+... -> monitor), else the
    subject string, else the session's zid."""
    if not subject:
        return zid
    users = _USER.findall(subject)
    return users[0] if users else subject


class RefusalLog:
    """Counts and prints the refusals in Zenoh's log lines (see the module doc)."""

    def __init__(self, out=None, every_s: float = 10.0, clock=time.monotonic):
        self.out = out if out is not None else sys.stderr
        self.every_s, self.clock = every_s, clock
        self.logins_refused = 0
        self.denied = 0
        self.by_kind: dict[str, int] = {}
        self.last_login = ""
        self.last_denial = ""
        self._subjects: dict[str, str] = {}  # zid -> subject, from lines that name both
        self._filling: dict[str, str] = {}  # thread -> key whose decisions it is caching
        self._shown: dict[str, tuple[float, int]] = {}  # kind -> (time last printed, held since)
        self._lock = threading.Lock()

    def status(self) -> dict:
        with self._lock:
            return {"logins_refused": self.logins_refused, "last_login_refused": self.last_login,
                    "acl_denied": self.denied, "acl_denied_by": dict(self.by_kind),
                    "last_acl_denied": self.last_denial}

    def _print(self, kind: str, text: str) -> None:
        now = self.clock()
        last, held = self._shown.get(kind, (None, 0))
        if last is not None and now - last < self.every_s:
            self._shown[kind] = (last, held + 1)
            return
        self._shown[kind] = (now, 0)
        more = f" [and {held} more since the last of these]" if held else ""
        print(f"energyctl router: {text}{more}", file=self.out, flush=True)

    def feed(self, raw: str) -> str | None:
        """One log line: 'login', 'denied' (counted and printed), 'dropped' (an allowed message, a cache fill, other
        chatter of the two targets), or 'passed' (printed as is)."""
        line = _ANSI.sub("", raw).rstrip("\n")
        if not line.strip():
            return "dropped"
        if ACL_TARGET in line:
            return self._acl(line)
        if AUTH_TARGET in line:
            m = _LOGIN.search(line)
            if m is None:
                return "dropped"  # a link accepted, a handshake step: not a refusal
            why = f"{m.group('ext')}: {m.group('why').strip()}"
            with self._lock:
                self.logins_refused += 1
                self.last_login = why
            self._print(f"login:{why}", f"refused a login: {why} ({self.logins_refused} refused so far)")
            return "login"
        print(line, file=self.out, flush=True)
        return "passed"

    def _acl(self, line: str) -> str:
        msg = line.split(ACL_TARGET + ":", 1)[-1].strip()
        thread = (_THREAD.search(line) or [None, ""])[1]
        c = _CACHING.search(msg)
        if c is not None:
            self._filling[thread] = c.group("key")
            return "dropped"
        d = _DECISION.match(msg)
        if d is None:
            return "dropped"
        zid, key, kind = d.group("zid"), d.group("key"), d.group("msg")
        if d.group("subject"):
            self._subjects[zid] = _subject_name(d.group("subject"), zid)
        cached = msg.startswith("Using cached result")
        if not cached and self._filling.get(thread) == key:  # evaluating what the subject could do, not a message
            if kind.startswith(_LAST_KIND):
                del self._filling[thread]
            return "dropped"
        self._filling.pop(thread, None)
        if not d.group("verdict"):
            return "dropped"
        who = self._subjects.get(zid, zid)
        what = f"{who}: {kind} on {key}"
        with self._lock:
            self.denied += 1
            name = what if what in self.by_kind or len(self.by_kind) < MAX_KINDS else "other"
            self.by_kind[name] = self.by_kind.get(name, 0) + 1
            self.last_denial = what
        self._print(f"acl:{what}", f"access control denied {what} ({self.by_kind[name]} times)")
        return "denied"

    def feed_bytes(self, buf: bytes) -> bytes:
        """Whole lines of buf fed; returns the unfinished tail. A chunk of allowed messages only is skipped
        whole (the common case: no refusal, nothing to print)."""
        *lines, tail = buf.split(b"\n")
        if b"unauthorized" not in buf and b"caching" not in buf and b"Invalid" not in buf and b"WARN" not in buf \
                and b"ERROR" not in buf and b"invalid" not in buf:
            return tail
        for ln in lines:
            self.feed(ln.decode(errors="replace"))
        return tail


def capture_stdout(log: RefusalLog, pipe_bytes: int = 1 << 20) -> threading.Thread:
    """Point this process's fd 1 at a pipe read by a thread that feeds ``log``; the pipe's write end is non-blocking
    (a full pipe loses the line instead of stalling the Zenoh thread that writes it). Returns the thread."""
    r, w = os.pipe()
    try:
        fcntl.fcntl(w, 1031, pipe_bytes)  # F_SETPIPE_SZ (Linux): room for a burst
    except OSError:
        pass
    fcntl.fcntl(w, fcntl.F_SETFL, fcntl.fcntl(w, fcntl.F_GETFL) | os.O_NONBLOCK)
    sys.stdout.flush()
    os.dup2(w, 1)
    os.close(w)
    sys.stdout = sys.stderr  # Python's own prints go to stderr, beside the refusals

    def pump() -> None:
        tail = b""
        while True:
            try:
                chunk = os.read(r, 1 << 16)
            except OSError:
                return
            if not chunk:
                return
            tail = log.feed_bytes(tail + chunk)

    t = threading.Thread(target=pump, name="zenoh-log", daemon=True)
    t.start()
    return t
