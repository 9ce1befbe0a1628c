"""The secure profile: a Zenoh router with user/password authentication and an ACL (loopback, free ports)."""

from __future__ import annotations

import threading

import pytest
import zenoh
from conftest import ROOT, SCENARIOS

from clients.cli import main
from clients.live import run_live, wait_until
from clients.query import QueryError, query
from clients.secure import ROUTER_FILE, run_router, tls_endpoint, write_profile
from schemas.codec import CMD, MEAS
from schemas.component import ComponentConfig, ZenohConfig, config_from_dict
from schemas.scenario import ScenarioError, load_scenario
from service.daemon.bus import free_tcp_port, open_session
from service.daemon.daemon import Daemon

P = "energyctl"


@pytest.fixture(params=["tcp", "tls"])
def secure(tmp_path, request):
    """A router enforcing a freshly written profile, over TCP or mutual TLS; yields (endpoint, paths: {user:
    password file, "tls": the certificates' directory when TLS})."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    paths = write_profile(tmp_path / "secure", listen=[ep], tls=request.param == "tls")
    ready, stop = threading.Event(), threading.Event()
    t = threading.Thread(target=run_router, args=(str(paths["router"]), [], ready, stop), daemon=True)
    t.start()
    assert ready.wait(15.0)
    try:
        yield ep, paths
    finally:
        stop.set()
        t.join(5.0)


def login(ep: str, paths, user: str, password_file=None) -> zenoh.Session:
    return open_session(client(ep, user, password_file or paths[user], paths))


def client(ep: str, user: str | None, password_file=None, paths=None, cert_of: str | None = None) -> ZenohConfig:
    """A client config; under TLS (paths has "tls") with the certificate of cert_of (default: user's own; a user
    that does not exist: none, only the CA)."""
    tls = (paths or {}).get("tls")
    z = {"mode": "client", "connect": [ep]}
    if user is not None:
        z.update(user=user, password_file=str(password_file))
    if tls is not None:
        z.update(connect=[tls_endpoint(ep)], tls_root_ca=str(tls / "ca.pem"))
        who = cert_of or user
        if who is not None and (tls / f"{who}.pem").exists():
            z.update(tls_certificate=str(tls / f"{who}.pem"), tls_private_key=str(tls / f"{who}.key"))
    return ZenohConfig(**z)


def round_trip(session: zenoh.Session) -> None:
    """Everything this session sent before has been routed (or dropped) by the router once this returns:
    a link is processed in order, and a liveliness query is answered by the router itself."""
    list(session.liveliness().get(f"{P}/*/alive", timeout=2.0))


def test_no_or_wrong_credentials_are_refused_at_connect(secure, tmp_path):
    ep, paths = secure
    wrong = tmp_path / "wrong.password"
    wrong.write_text("not-the-password\n")
    wrong.chmod(0o600)
    for z in (client(ep, None, paths=paths), client(ep, "operator", wrong, paths),
              client(ep, "mallory", wrong, paths)):
        with pytest.raises(ConnectionError, match="cannot open a Zenoh client session"):
            open_session(z)
    # nor can such a client change a gain through the CLI path
    with pytest.raises(ConnectionError):
        query(client(ep, "operator", wrong, paths), P, "source", "config", sets=["controller.K_per_s=1"])
    # a password file others may read is refused before connecting
    loose = tmp_path / "loose.password"
    loose.write_text(paths["operator"].read_text())
    loose.chmod(0o644)
    with pytest.raises(ScenarioError, match="readable by group or others"):
        open_session(client(ep, "operator", loose, paths))


def test_only_the_controller_commands_and_only_the_plant_measures(secure):
    ep, paths = secure
    sessions = {u: login(ep, paths, u) for u in ("source", "plant", "load", "operator", "monitor")}
    try:
        cmd_rx = sessions["plant"].declare_subscriber(f"{P}/source/cmd", zenoh.handlers.FifoChannel(64))
        meas_rx = sessions["source"].declare_subscriber(f"{P}/source/meas", zenoh.handlers.FifoChannel(64))

        def routed(user, leaf, payload, sub) -> bool:
            """The allowed sender's probe (seq 6) put until it arrives: the subscription has reached the router, so
            a forged frame that does not arrive below was refused, not sent before anyone listened (a loaded CI
            machine once lost the plant's only frame so)."""
            def probe() -> bool:
                sessions[user].put(f"{P}/source/{leaf}", payload)
                got = False
                while (x := sub.try_recv()) is not None:
                    got = got or x.payload.to_bytes() == payload
                return got
            return wait_until(probe, 30.0, every_s=0.1)

        assert routed("source", "cmd", CMD.encode(6, 0.0, 0.0, 0.0, 0), cmd_rx)
        assert routed("plant", "meas", MEAS.encode(6, 0.0, 1.0, 80.0, 0.0, 0.0), meas_rx)
        forged = {"cmd": [], "meas": []}
        for n, user in enumerate(("load", "operator", "monitor")):
            s = sessions[user]
            s.put(f"{P}/source/cmd", CMD.encode(1000 + n, 0.0, 1e6, 0.0, 0))  # a large, wrong command
            s.put(f"{P}/source/meas", MEAS.encode(1000 + n, 0.0, 1.0, 80.0, 0.0, 0.0))
            round_trip(s)
            forged["cmd"].append(1000 + n)
            forged["meas"].append(1000 + n)
        sessions["source"].put(f"{P}/source/cmd", CMD.encode(7, 0.0, 12.5, 0.0, 0))
        sessions["plant"].put(f"{P}/source/meas", MEAS.encode(7, 0.0, 1.0, 80.0, 0.0, 0.0))

        def drain(sub, codec, into):
            while (x := sub.try_recv()) is not None:
                into.append(codec.decode(x.payload.to_bytes())[0])
            return 7 in into

        cmds, meas = [], []
        assert wait_until(lambda: drain(cmd_rx, CMD, cmds), 5.0), "the controller's command did not arrive"
        assert wait_until(lambda: drain(meas_rx, MEAS, meas), 5.0), "the plant's measurement did not arrive"
        assert [c for c in cmds if c != 6] == [7] and [m for m in meas if m != 6] == [7], (cmds, meas)  # no forgery
    finally:
        for s in sessions.values():
            s.close()


def test_only_an_operator_sets_config(secure, tmp_path):
    ep, paths = secure
    comp = {"id": "source", "plant_id": "source", "neighbours": [], "loop": {"trigger": "sample", "rate_hz": 1000.0},
            "zenoh": client(ep, "source", paths["source"], paths).model_dump()}
    d = Daemon(config_from_dict(ComponentConfig, comp))
    d.open()
    loop = threading.Thread(target=d.run_loop, daemon=True)
    loop.start()
    try:
        op = client(ep, "operator", paths["operator"], paths)
        mon = client(ep, "monitor", paths["monitor"], paths)
        assert query(op, P, "source", "config", sets=["controller.K_per_s=900"], timeout_s=5.0)["applied"]
        assert d.core.cfg.K_per_s == 900.0
        for who in ("monitor", "load", "plant"):
            with pytest.raises(QueryError, match="no answer"):
                query(client(ep, who, paths[who], paths), P, "source", "config", sets=["controller.K_per_s=1"],
                      timeout_s=0.5)
        if "tls" in paths:  # the operator's password with the monitor's certificate is neither identity
            with pytest.raises((QueryError, ConnectionError)):
                query(client(ep, "operator", paths["operator"], paths, cert_of="monitor"), P, "source", "config",
                      sets=["controller.K_per_s=1"], timeout_s=0.5)
        # the read-only key refuses a set smuggled in as a parameter, naming where sets go
        s = open_session(mon)
        try:
            (r,) = list(s.get(f"{P}/source/config?set", payload=b'{"set": ["controller.K_per_s=1"]}', timeout=5.0))
            assert r.err is not None and b"config/set" in r.err.payload.to_bytes()
        finally:
            s.close()
        assert d.core.cfg.K_per_s == 900.0 and d.config_version == 1
        # the monitor still reads, also through the CLI (its options carry the same credentials and certificate)
        assert query(mon, P, "source", "config", timeout_s=5.0)["controller"]["K_per_s"] == 900.0
        cli = ["query", "config", "--component", "source", "--json", "--mode", "client", "--connect", mon.connect[0],
               "--user", "monitor", "--password-file", mon.password_file]
        if mon.tls_certificate:
            cli += ["--tls-root-ca", mon.tls_root_ca, "--tls-certificate", mon.tls_certificate,
                    "--tls-private-key", mon.tls_private_key]
        assert main(cli) == 0
        assert query(mon, P, "source", "status", timeout_s=5.0)["id"] == "source"
    finally:
        d.stop()
        loop.join(2.0)
        d.close()


@pytest.mark.parametrize("tls", [False, True])
def test_the_whole_stack_runs_under_the_secure_profile(tmp_path, tls):
    """Plant, load and controller as three authenticated clients of the ACL router (with tls: each also with
    its own certificate, over mutual TLS): lockstep completes, so every message kind they need is allowed."""
    scn = load_scenario(SCENARIOS / "paper-constant-load.toml", ["timing.duration_s=0.03"])
    res = run_live(scn, lockstep=True, rate_hz=None, out=None, duration_s=None, workdir=str(tmp_path), secure=True,
                   tls=tls)
    assert res["counters"]["commands"] == 300 and res["counters"]["timeouts"] == 0
    assert res["daemon"]["neighbours"]["load"]["messages"] > 0


def test_the_shipped_router_profile_is_what_the_generator_writes(tmp_path):
    write_profile(tmp_path)
    shipped = ROOT / "scenarios" / "secure" / ROUTER_FILE
    assert shipped.read_text() == (tmp_path / ROUTER_FILE).read_text(), \
        "regenerate: energyctl secure-profile --out scenarios/secure"


def test_the_shipped_secure_configs_extend_the_live_ones(tmp_path):
    from schemas.component import LoadPeerConfig, PlantPeerConfig, load_config

    for kind, name, user in ((ComponentConfig, "component", "source"), (PlantPeerConfig, "plant", "plant"),
                             (LoadPeerConfig, "load", "load")):
        sec = load_config(kind, SCENARIOS / "secure" / f"{name}.toml")
        live = load_config(kind, SCENARIOS / "live" / f"{name}.toml")
        assert sec.zenoh.mode == "client" and sec.zenoh.user == user
        assert sec.zenoh.password_file == str(SCENARIOS / "secure" / f"{user}.password")
        assert sec.model_dump(exclude={"zenoh"}) == live.model_dump(exclude={"zenoh"})
    (tmp_path / "a.toml").write_text('extends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    with pytest.raises(ScenarioError, match="loops back"):
        load_config(ComponentConfig, tmp_path / "a.toml")


@pytest.mark.parametrize("secure", ["tls"], indirect=True)
def test_mutual_tls_refuses_a_certificate_from_another_ca(secure, tmp_path):
    """Under TLS a client needs a certificate signed by the profile's CA: its own CA's, however named, fails the
    handshake even with the right password."""
    import subprocess

    ep, paths = secure
    key, pem = tmp_path / "evil.key", tmp_path / "evil.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                    "-keyout", str(key), "-out", str(pem), "-days", "2", "-subj", "/CN=operator"],
                   check=True, capture_output=True)
    key.chmod(0o600)
    z = client(ep, "operator", paths["operator"], paths).model_copy(
        update={"tls_certificate": str(pem), "tls_private_key": str(key)})
    with pytest.raises(ConnectionError):
        open_session(z)
    loose = tmp_path / "loose.key"  # and a private key others may read is refused before connecting
    loose.write_text((paths["tls"] / "operator.key").read_text())
    loose.chmod(0o644)
    with pytest.raises(ScenarioError, match="readable by group or others"):
        open_session(client(ep, "operator", paths["operator"], paths).model_copy(
            update={"tls_private_key": str(loose)}))
