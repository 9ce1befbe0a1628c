"""The secure profile: a Zenoh router with user/password authentication and an access-control list.

Zenoh's own mechanisms do the work (``transport/auth/usrpwd`` and ``access_control``); this module only
writes their configuration for a set of component ids, so the rules can be reviewed and regenerated
rather than written by hand. ``default_permission`` is ``deny``: every message kind a role needs is
listed, in the router's terms (``ingress``: from that client into the router; ``egress``: from the
router to that client). Roles, each a Zenoh user whose name is its identity:

* controller ``C``: publishes ``C/cmd`` and ``C/z``; receives ``C/meas`` and every ``*/z``; serves
  ``C/status``, ``C/config`` and ``C/config/set``; holds the token ``C/alive``.
* plant (one per controller): publishes ``C/meas``; receives ``C/cmd``.
* load ``L``: publishes ``L/z``; receives ``*/meas`` (lockstep pacing); holds ``L/alive``.
* operator: queries ``*/status``, ``*/config`` and ``*/config/set``; receives ``*/z``.
* monitor: the operator without ``config/set`` (read-only dashboards).

Everyone may watch liveliness tokens. A client without credentials, or with wrong ones, is refused at
connect; a message the ACL denies is dropped by the router (the sender sees no error).

With ``tls=True`` the router listens on ``tls/`` endpoints with mutual TLS: a private CA (made here with the
``openssl`` command) signs the router's certificate and one client certificate per user whose common name
is the user name. A client must then present a certificate of that CA (else the handshake fails) and the
password; each ACL subject names both the user name and the certificate's common name, so a session
counts as an identity only with that identity's password and certificate. The credentials cross the wire
encrypted.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import threading
from pathlib import Path

from schemas.component import ZenohConfig
from schemas.scenario import ScenarioError

ROUTER_FILE = "router.json5"
CREDENTIALS_FILE = "credentials.txt"


def _rule(rid: str, messages: list[str], flow: str, keys: list[str]) -> dict:
    return {"id": rid, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": keys}


def access_control(prefix: str, controllers: list[str], plants: dict[str, str], loads: list[str],
                   operators: list[str], monitors: list[str]) -> dict:
    """The ``access_control`` block. ``plants`` maps a plant user to the controller id it serves."""
    P = prefix
    rules: list[dict] = []
    policies: list[dict] = []
    subjects: list[dict] = []
    live = [f"{P}/*/alive"]

    def role(user: str, rs: list[dict]) -> None:
        for r in rs:
            r["id"] = f"{user}: {r['id']}"
        rules.extend(rs)
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"id": user, "rules": [r["id"] for r in rs], "subjects": [user]})

    def watch_liveliness() -> list[dict]:
        return [_rule("watch liveliness", ["liveliness_query", "declare_liveliness_subscriber"], "ingress", live),
                _rule("see liveliness", ["liveliness_token", "reply"], "egress", live)]

    def token(cid: str) -> list[dict]:
        return [_rule("hold its liveliness token", ["liveliness_token"], "ingress", [f"{P}/{cid}/alive"])]

    for c in controllers:
        served = [f"{P}/{c}/status", f"{P}/{c}/config", f"{P}/{c}/config/set"]
        role(c, [_rule("publish commands and interaction", ["put"], "ingress", [f"{P}/{c}/cmd", f"{P}/{c}/z"]),
                 _rule("learn who subscribes to them", ["declare_subscriber"], "egress",
                       [f"{P}/{c}/cmd", f"{P}/{c}/z"]),
                 _rule("subscribe to measurements and interactions", ["declare_subscriber"], "ingress",
                       [f"{P}/{c}/meas", f"{P}/*/z"]),
                 _rule("receive measurements and interactions", ["put"], "egress", [f"{P}/{c}/meas", f"{P}/*/z"]),
                 _rule("serve status and config", ["declare_queryable"], "ingress", served),
                 _rule("be asked", ["query"], "egress", served),
                 _rule("answer", ["reply"], "ingress", served),
                 *token(c), *watch_liveliness()])
    for user, c in plants.items():
        role(user, [_rule("publish measurements", ["put"], "ingress", [f"{P}/{c}/meas"]),
                    _rule("learn who subscribes to them", ["declare_subscriber"], "egress", [f"{P}/{c}/meas"]),
                    _rule("subscribe to commands", ["declare_subscriber"], "ingress", [f"{P}/{c}/cmd"]),
                    _rule("receive commands", ["put"], "egress", [f"{P}/{c}/cmd"]),
                    *watch_liveliness()])
    for ld in loads:
        role(ld, [_rule("publish its interaction variable", ["put"], "ingress", [f"{P}/{ld}/z"]),
                  _rule("learn who subscribes to it", ["declare_subscriber"], "egress", [f"{P}/{ld}/z"]),
                  _rule("subscribe to measurements", ["declare_subscriber"], "ingress", [f"{P}/*/meas"]),
                  _rule("receive measurements", ["put"], "egress", [f"{P}/*/meas"]),
                  *token(ld), *watch_liveliness()])
    for user, may_set in [(u, True) for u in operators] + [(u, False) for u in monitors]:
        asked = [f"{P}/*/status", f"{P}/*/config"] + ([f"{P}/*/config/set"] if may_set else [])
        role(user, [_rule("query" + (" and set config" if may_set else ""), ["query"], "ingress", asked),
                    _rule("get answers", ["reply"], "egress", asked),
                    _rule("subscribe to interactions", ["declare_subscriber"], "ingress", [f"{P}/*/z"]),
                    _rule("receive interactions", ["put"], "egress", [f"{P}/*/z"]),
                    *watch_liveliness()])
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(listen: list[str], acl: dict, dictionary_file: str = CREDENTIALS_FILE, tls: bool = False) -> dict:
    transport: dict = {"auth": {"usrpwd": {"dictionary_file": dictionary_file}}}
    if tls:  # paths relative to the profile directory (energyctl resolves them; zenohd: run it from there)
        transport["link"] = {"tls": {"listen_certificate": f"{TLS_DIR}/router.pem",
                                     "listen_private_key": f"{TLS_DIR}/router.key",
                                     "root_ca_certificate": f"{TLS_DIR}/ca.pem", "enable_mtls": True}}
        listen = [tls_endpoint(e) for e in listen]
    return {"mode": "router", "listen": {"endpoints": listen}, "scouting": {"multicast": {"enabled": False}},
            "transport": transport, "access_control": acl}


TLS_DIR = "tls"


def tls_endpoint(endpoint: str) -> str:
    """tcp/HOST:PORT -> tls/HOST:PORT (the same address over TLS)."""
    proto, _, addr = endpoint.partition("/")
    if proto not in ("tcp", "tls"):
        raise ScenarioError(f"secure profile: TLS needs a tcp/ or tls/ endpoint, not {endpoint!r}")
    return f"tls/{addr}"


def _openssl(*args: str) -> None:
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        raise ScenarioError("secure profile with TLS: the 'openssl' command is needed to make the certificates")
    r = subprocess.run(["openssl", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise ScenarioError(f"openssl {args[0]} failed: {r.stderr.strip()[-400:]}")


def write_certificates(out: Path, users: list[str], hosts: list[str]) -> None:
    """A private CA (kept if present), the router's certificate for ``hosts`` and one client certificate per
    user (common name = user). Keys are EC P-256, mode 600. Existing certificates are kept."""
    d = out / TLS_DIR
    d.mkdir(parents=True, exist_ok=True)
    ca, ca_key = d / "ca.pem", d / "ca.key"
    if not ca.exists():
        _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout",
                 str(ca_key), "-out", str(ca), "-days", "3650", "-subj", "/CN=energyctl-ca")
    san = ",".join(f"IP:{h}" if h.replace(".", "").isdigit() or ":" in h else f"DNS:{h}" for h in hosts)
    for name in ["router", *users]:
        pem, key = d / f"{name}.pem", d / f"{name}.key"
        if pem.exists() and key.exists():
            continue
        csr, ext = d / f"{name}.csr", d / f"{name}.ext"
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", str(key),
                 "-out", str(csr), "-subj", f"/CN={name}")
        ext.write_text((f"subjectAltName={san}\n" if name == "router" else "")
                       + "extendedKeyUsage=serverAuth,clientAuth\nbasicConstraints=CA:FALSE\n")
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca), "-CAkey", str(ca_key), "-CAcreateserial",
                 "-out", str(pem), "-days", "3650", "-extfile", str(ext))
        csr.unlink()
        ext.unlink()
    for key in d.glob("*.key"):
        key.chmod(0o600)


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)


def _read_credentials(path: Path) -> dict[str, str]:
    if not path.exists():
        return {}
    out = {}
    for line in path.read_text().splitlines():
        if ":" in line and not line.lstrip().startswith("#"):
            u, pw = line.split(":", 1)
            out[u.strip()] = pw.strip()
    return out


def write_profile(out_dir: str | Path, prefix: str = "energyctl", controllers: list[str] | None = None,
                  plants: dict[str, str] | None = None, loads: list[str] | None = None,
                  operators: list[str] | None = None, monitors: list[str] | None = None,
                  listen: list[str] | None = None, tls: bool = False) -> dict[str, Path]:
    """Write ``router.json5``, ``credentials.txt`` and one ``<user>.password`` per user (mode 600); with tls,
    also ``tls/`` (CA, router and per-user certificates and keys).

    Existing passwords and certificates are kept (regenerating the profile never locks anyone out); users
    without them get new ones."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    controllers = controllers or ["source"]
    plants = plants if plants is not None else {"plant": controllers[0]}
    loads = loads if loads is not None else ["load"]
    operators = operators if operators is not None else ["operator"]
    monitors = monitors if monitors is not None else ["monitor"]
    users = [*controllers, *plants, *loads, *operators, *monitors]
    dup = sorted({u for u in users if users.count(u) > 1})
    if dup:
        raise ScenarioError(f"secure profile: each identity needs its own user name; repeated: {dup}")
    for c in plants.values():
        if c not in controllers:
            raise ScenarioError(f"secure profile: plant serves controller {c!r}, which is not a --controller")
    acl = access_control(prefix, controllers, plants, loads, operators, monitors)
    if tls:  # an identity is its user name and its certificate's common name, both
        for sub in acl["subjects"]:
            sub["cert_common_names"] = list(sub["usernames"])
    listen = listen or ["tcp/127.0.0.1:7447"]
    cfg = router_config(listen, acl, tls=tls)
    router = out / ROUTER_FILE
    router.write_text("// energyctl secure profile (energyctl secure-profile); Zenoh JSON5, also for zenohd -c\n"
                      "// (zenohd reads dictionary_file from its working directory, energyctl router from here)\n"
                      + json.dumps(cfg, indent=2) + "\n")
    creds_path = out / CREDENTIALS_FILE
    creds = _read_credentials(creds_path)
    for u in users:
        creds.setdefault(u, secrets.token_urlsafe(24))
    _write_private(creds_path, "".join(f"{u}:{creds[u]}\n" for u in users))
    paths = {"router": router, "credentials": creds_path}
    for u in users:
        paths[u] = out / f"{u}.password"
        _write_private(paths[u], creds[u] + "\n")
    if tls:
        write_certificates(out, users, sorted({e.partition("/")[2].rpartition(":")[0].strip("[]") for e in listen}))
        paths["tls"] = out / TLS_DIR
    return paths


def client_zenoh(endpoint: str, user: str, password_file: str | Path, tls_dir: str | Path | None = None) -> dict:
    """The ``[zenoh]`` table of a component, plant or load that connects to the secure router (over mutual
    TLS when tls_dir, the profile's ``tls/`` directory, is given)."""
    z = {"mode": "client", "connect": [endpoint], "user": user, "password_file": str(password_file)}
    if tls_dir is not None:
        d = Path(tls_dir)
        z.update(connect=[tls_endpoint(endpoint)], tls_root_ca=str(d / "ca.pem"),
                 tls_certificate=str(d / f"{user}.pem"), tls_private_key=str(d / f"{user}.key"))
    return z


def run_router(config_file: str | None, listen: list[str], ready: threading.Event | None = None,
               stop: threading.Event | None = None) -> int:
    """A Zenoh router in this process until SIGINT/SIGTERM (or ``stop``). Prints one line when listening."""
    import sys

    from service.daemon.bus import open_session

    z = ZenohConfig(mode="router", listen=listen, config_file=config_file)
    session = open_session(z)
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    acl = "off"
    if config_file:
        from service.daemon.bus import zenoh_config

        acl = "on" if json.loads(zenoh_config(z).get_json("access_control/enabled")) else "off"
    print(f"energyctl router: listening on {listen or 'the config file endpoints'}, access control {acl}",
          file=sys.stderr, flush=True)
    if ready is not None:
        ready.set()
    try:
        stop.wait()
    finally:
        session.close()
    return 0
