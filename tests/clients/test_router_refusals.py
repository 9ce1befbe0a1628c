"""The secure router logs and counts what it refuses (failed logins, access-control denials), from Zenoh's own log:
the line classifier on Zenoh 1.10's lines, and ``energyctl router`` as a process (loopback, a free port, multicast
scouting off by the profile, the process stopped even on failure)."""

from __future__ import annotations

import io
import os
import subprocess
import sys

from conftest import ROOT

from clients.live import stop_process, wait_until
from clients.query import query
from clients.refusals import RefusalLog
from clients.secure import client_zenoh, write_profile
from schemas.component import ZenohConfig
from service.daemon.bus import free_tcp_port, open_session

ACL = "TRACE  rx-1 ThreadId(9) zenoh::net::routing::interceptor::access_control: "
Z, SUBJ = "d3c53e73222f08be", "Interface(lo)+Username(monitor)+Transport(Tcp)+d3c53e73222f08be"
KINDS = ["Query", "Reply", "Put", "Delete", "Declare/Undeclare Subscriber", "Declare/Undeclare Queryable",
         "Declare/Undeclare Liveliness Token", "Liveliness Query", "Declare Liveliness Subscriber"]


def test_refusals_are_told_from_cache_fills_and_allowed_messages():
    """Zenoh writes a decision line per message kind when it caches a key (what the subject could do: not a
    refusal), a line per allowed message, and one per denied one; only the last are counted, repeats are printed
    at most every every_s with how many they stand for."""
    out, now = io.StringIO(), [0.0]
    log = RefusalLog(out=out, every_s=10.0, clock=lambda: now[0])
    fill = [f"{ACL}ACL (ingress): caching permissions for `energyctl/source/cmd` ..."]
    fill += [f"{ACL}{Z} on {SUBJ} is unauthorized to {k} (ingress) on energyctl/source/cmd" for k in KINDS]
    assert [log.feed(x) for x in fill] == ["dropped"] * len(fill)
    denied = f"{ACL}Using cached result: {Z} is unauthorized to Put (ingress) on energyctl/source/cmd"
    allowed = f"{ACL}Using cached result: {Z} is authorized to Put (egress) on energyctl/source/z"
    direct = f"{ACL}{Z} on {SUBJ} is unauthorized to Query (ingress) on energyctl/source/config/set"
    assert [log.feed(x) for x in (denied, allowed, denied, direct)] == ["denied", "dropped", "denied", "denied"]
    login = ("DEBUG acc-0 ThreadId(05) zenoh_transport::unicast::establishment::accept: UsrPwd extension - Recv "
             "OpenSyn. Invalid password. at io/zenoh-transport/src/unicast/establishment/ext/auth/usrpwd.rs:424.")
    accepted = ("DEBUG acc-0 ThreadId(05) zenoh_transport::unicast::establishment::accept: New transport link "
                "accepted from 1 to 2")
    assert [log.feed(login), log.feed(accepted), log.feed("WARN net: something else")] == ["login", "dropped",
                                                                                          "passed"]
    st = log.status()
    assert st["acl_denied"] == 3 and st["logins_refused"] == 1
    assert st["acl_denied_by"] == {"monitor: Put (ingress) on energyctl/source/cmd": 2,
                                   "monitor: Query (ingress) on energyctl/source/config/set": 1}
    printed = out.getvalue().splitlines()
    assert sum("denied monitor: Put (ingress)" in x for x in printed) == 1  # the repeat held back
    assert "refused a login: UsrPwd: Invalid password" in printed[-2] and printed[-1] == "WARN net: something else"
    now[0] = 11.0
    log.feed(denied)
    assert out.getvalue().splitlines()[-1].endswith("(3 times) [and 1 more since the last of these]")


def test_energyctl_router_logs_and_counts_refused_logins_and_denied_messages(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    paths = write_profile(tmp_path / "secure", listen=[ep])
    err = tmp_path / "router.err"
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    env["PYTHONPATH"] = str(ROOT)
    p = subprocess.Popen([sys.executable, "-m", "clients.cli", "router", "--config", str(paths["router"])],
                         stdout=subprocess.DEVNULL, stderr=err.open("w"), env=env, cwd=ROOT)
    try:
        assert wait_until(lambda: "listening" in err.read_text() or p.poll() is not None, 30.0)
        assert p.poll() is None, err.read_text()
        bad = tmp_path / "wrong.password"
        bad.write_text("not-the-password\n")
        bad.chmod(0o600)
        try:
            open_session(ZenohConfig(**client_zenoh(ep, "operator", bad))).close()
            raise AssertionError("a wrong password was let in")
        except ConnectionError:
            pass
        mon = ZenohConfig(**client_zenoh(ep, "monitor", paths["monitor"]))
        s = open_session(mon)
        try:
            for _ in range(3):  # the monitor may not set config: the router drops the query
                list(s.get("energyctl/source/config/set", payload=b'{"set": ["controller.K_per_s=1"]}', timeout=0.3))
            list(s.liveliness().get("energyctl/*/alive", timeout=2.0))  # all of it through the router
        finally:
            s.close()
        want = {"monitor: Query (ingress) on energyctl/source/config/set": 3}
        seen = {}

        def counted() -> bool:
            seen.update(query(mon, "energyctl", "router", "status", timeout_s=5.0)["refusals"])
            return seen["acl_denied"] >= 3 and seen["logins_refused"] >= 1

        assert wait_until(counted, 20.0), seen
        assert seen["acl_denied_by"] == want and seen["logins_refused"] == 1, seen
        text = err.read_text()
        assert "refused a login: UsrPwd: Invalid password" in text
        assert "access control denied monitor: Query (ingress) on energyctl/source/config/set" in text
    finally:
        stop_process(p)
    assert "refused 1 login(s), denied 3 message(s)" in err.read_text()
