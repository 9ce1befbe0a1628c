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
connect; a message the ACL denies is dropped by the router (the sender sees no error). ``energyctl router`` logs and
counts both from Zenoh's own log (``run_router(audit=True)``, clients/refusals.py).

With ``tls=True`` the router listens on ``tls/`` endpoints with mutual TLS: a private CA (made here with the
``openssl`` command) signs the router's certificate and one client certificate per user whose common name
is the user name. A client must then present a certificate of that CA (else the handshake fails) and the
password; each ACL subject names both the user name and the certificate's common name, so a session
counts as an identity only with that identity's password and certificate. The credentials cross the wire
encrypted.

A live network (``write_network_profile``, ``energyctl secure-profile --network``): one identity per source daemon,
the rig and the coordinator, each with rules for exactly the keys it uses (``network_roles``), and, across hosts, one
router per host linked hub-and-spoke, each with its own identity and a short lease (docs/across-hosts.md).
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
# a lockstep network across hosts: how long a message waits for room in a full send queue before it is dropped (us;
# Zenoh's default 1 000): at 32 daemons a sample's burst overfilled the routers' queues (decisions/0044)
LOCKSTEP_WAIT_BEFORE_DROP_US = 200_000
WAIT_BEFORE_DROP_MAX_US = 1_000_000
CREDENTIALS_FILE = "credentials.txt"


def _rule(rid: str, messages: list[str], flow: str, keys: list[str]) -> dict:
    return {"id": rid, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": keys}


class _Acl:
    """An ``access_control`` block being built: rules, subjects and policies, one policy per identity."""

    def __init__(self, prefix: str):
        self.P = prefix
        self.rules: list[dict] = []
        self.policies: list[dict] = []
        self.subjects: list[dict] = []

    def role(self, user: str, rs: list[dict], subject: dict | None = None) -> None:
        """The rules of one identity; its subject is its user name unless given (``{"zids": ...}``, ...)."""
        for r in rs:
            r["id"] = f"{user}: {r['id']}"
        self.rules.extend(rs)
        self.subjects.append({"id": user, **(subject or {"usernames": [user]})})
        self.policies.append({"id": user, "rules": [r["id"] for r in rs], "subjects": [user]})

    def watch_liveliness(self) -> list[dict]:
        live = [f"{self.P}/*/alive"]
        return [_rule("watch liveliness", ["liveliness_query", "declare_liveliness_subscriber"], "ingress", live),
                _rule("see liveliness", ["liveliness_token", "reply"], "egress", live)]

    def token(self, cid: str) -> list[dict]:
        return [_rule("hold its liveliness token", ["liveliness_token"], "ingress", [f"{self.P}/{cid}/alive"])]

    def publishes(self, what: str, keys: list[str]) -> list[dict]:
        """Put on keys, and learn who subscribes to them (a publisher's matching status)."""
        return [_rule(f"publish {what}", ["put"], "ingress", keys),
                _rule("learn who subscribes to them", ["declare_subscriber"], "egress", keys)]

    def subscribes(self, what: str, keys: list[str]) -> list[dict]:
        return [_rule(f"subscribe to {what}", ["declare_subscriber"], "ingress", keys),
                _rule(f"receive {what}", ["put"], "egress", keys)]

    def serves(self, what: str, keys: list[str]) -> list[dict]:
        """A queryable on keys: declared, asked, answering."""
        return [_rule(f"serve {what}", ["declare_queryable"], "ingress", keys),
                _rule("be asked", ["query"], "egress", keys),
                _rule("answer", ["reply"], "ingress", keys)]

    def asks(self, what: str, keys: list[str]) -> list[dict]:
        return [_rule(f"ask {what}", ["query"], "ingress", keys),
                _rule("get answers", ["reply"], "egress", keys)]

    def operators(self, operators: list[str], monitors: list[str]) -> None:
        P = self.P
        for user, may_set in [(u, True) for u in operators] + [(u, False) for u in monitors]:
            asked = [f"{P}/*/status", f"{P}/*/config"] + ([f"{P}/*/config/set"] if may_set else [])
            self.role(user, [_rule("query" + (" and set config" if may_set else ""), ["query"], "ingress", asked),
                             _rule("get answers", ["reply"], "egress", asked),
                             _rule("subscribe to interactions", ["declare_subscriber"], "ingress", [f"{P}/*/z"]),
                             _rule("receive interactions", ["put"], "egress", [f"{P}/*/z"]),
                             *self.watch_liveliness()])

    def block(self) -> dict:
        return {"enabled": True, "default_permission": "deny", "rules": self.rules, "subjects": self.subjects,
                "policies": self.policies}


def access_control(prefix: str, controllers: list[str], plants: dict[str, str], loads: list[str],
                   operators: list[str], monitors: list[str]) -> dict:
    """The ``access_control`` block. ``plants`` maps a plant user to the controller id it serves."""
    P = prefix
    acl = _Acl(P)
    role, watch_liveliness, token = acl.role, acl.watch_liveliness, acl.token
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
    acl.operators(operators, monitors)
    return acl.block()


# ---------------------------------------------------------------------------------------------- a live network

ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "liveliness_query", "declare_liveliness_subscriber"]


def network_roles(acl: _Acl, net, rig: str, coordinator: str, users: set[str] | None = None) -> None:
    """The rules of a live network's processes (schemas.netlive): the rig, the coordinator, one daemon per source;
    ``users``: only these identities (None: all)."""
    P = acl.P
    sources = list(net.sources)
    lines = {name: (ln.a, ln.b) for name, ln in net.lines.items()}
    want = (lambda u: True) if users is None else (lambda u: u in users)
    if want(rig):
        out = ([f"{P}/{s}/meas" for s in sources] + [f"{P}/{ln}/z/{n}" for ln, ends in lines.items() for n in ends]
               + [f"{P}/{ld}/z" for ld in net.loads] + [f"{P}/{rig}/grid"])
        acl.role(rig, [*acl.publishes("measurements, interaction variables and the grid sample", out),
                       *acl.subscribes("commands", [f"{P}/{s}/cmd" for s in sources]),
                       *acl.serves("breaker commands", [f"{P}/{rig}/breaker"]),
                       *acl.token(rig), *acl.watch_liveliness()])
    if want(coordinator):
        acl.role(coordinator, [
            *acl.subscribes("the grid sample", [f"{P}/{rig}/grid"]),
            *acl.publishes("the layer's window messages", [f"{P}/{s}/window" for s in sources]),
            *acl.serves("status and the plug-in handshake",
                        [f"{P}/{coordinator}/status", f"{P}/{coordinator}/connect"]),
            *acl.asks("the rig's breakers and the sources' configs", [f"{P}/{rig}/breaker"]
                      + [f"{P}/{s}/config" for s in sources]),
            *acl.token(coordinator), *acl.watch_liveliness()])
    for s in sources:
        if not want(s):
            continue
        ends = [f"{P}/{ln}/z/{s}" for ln, ends in lines.items() if s in ends]
        acl.role(s, [*acl.publishes("commands and interaction", [f"{P}/{s}/cmd", f"{P}/{s}/z"]),
                     *acl.subscribes("measurements, the grid sample, window messages and line ends",
                                     [f"{P}/{s}/meas", f"{P}/{rig}/grid", f"{P}/{s}/window", *ends]),
                     *acl.serves("status and config", [f"{P}/{s}/status", f"{P}/{s}/config", f"{P}/{s}/config/set"]),
                     *acl.asks("to connect", [f"{P}/{coordinator}/connect"]),
                     *acl.token(s), *acl.watch_liveliness()])


def network_access_control(prefix: str, net, rig: str = "rig", coordinator: str = "coordinator",
                           operators: list[str] | None = None, monitors: list[str] | None = None,
                           users: set[str] | None = None, peer_routers: dict | None = None) -> dict:
    """The ``access_control`` block of a router of a live network: the rig's, the coordinator's, each source
    daemon's, the operators' and monitors' rules (``users``: only these of the network's processes), and with
    ``peer_routers`` the other routers this one links to: ``{identity: subject}`` (``{"usernames": [...]}`` for a
    router that connects to this one, ``{"zids": [...], ...}`` for one this router connects to), allowed every
    message kind both ways under PREFIX/**."""
    acl = _Acl(prefix)
    network_roles(acl, net, rig, coordinator, users)
    acl.operators(operators if operators is not None else ["operator"],
                  monitors if monitors is not None else ["monitor"])
    for ident, subject in (peer_routers or {}).items():
        acl.role(ident, [_rule("route the network's messages", list(ALL_MESSAGES), "ingress", [f"{prefix}/**"]),
                         _rule("be routed the network's messages", list(ALL_MESSAGES), "egress", [f"{prefix}/**"])],
                 subject)
    return acl.block()


def router_zid(user: str, password: str) -> str:
    """A router's Zenoh id, fixed by its identity (the other routers' ACLs name it): 32 hex digits, not zero."""
    import hashlib

    z = hashlib.sha256(f"energyctl router {user}:{password}".encode()).hexdigest()[:32]
    return z if z[0] != "0" else "1" + z[1:]


def link_timing(lease_ms: int | None, keep_alive: int | None, lease: bool = True) -> dict:
    """The ``transport`` and ``connect`` parts that make a lost link seen within a lease and a restored one
    reconnected within about a lease: retries from a quarter of a lease, growing to half of one, each attempt given
    up after a lease (Zenoh's defaults: 10 s lease; retries every 1 s growing to 4 s; an attempt given up after
    10 s, which on a cut link leaves it to TCP's SYN back-off when a restored link is found).

    The lease a node announces is how long the other end of each of its links waits for a message from it before
    closing the link; it sends keep-alives lease/keep_alive apart. ``lease=False`` (a client): only the reconnection
    timing, the lease stays Zenoh's, so that a process that is slow for a moment is not dropped by its router, and
    every token and declaration of it with it."""
    if lease_ms is None and keep_alive is None:
        return {}
    out: dict = {}
    if lease:
        tx: dict = {}
        if lease_ms is not None:
            tx["lease"] = lease_ms
        if keep_alive is not None:
            tx["keep_alive"] = keep_alive
        out["transport"] = {"link": {"tx": tx}}
    if lease_ms is not None:
        out.setdefault("transport", {})["unicast"] = {"open_timeout": lease_ms}
        out["connect"] = {"retry": {"period_init_ms": max(50, lease_ms // 4), "period_max_ms": max(50, lease_ms // 2),
                                    "period_increase_factor": 2}}
    return out


def _merge(a: dict, b: dict) -> dict:
    """b's keys into a, nested dicts merged (b's values copied: a and b share nothing afterwards); returns a."""
    import copy

    for k, v in b.items():
        if isinstance(v, dict) and isinstance(a.get(k), dict):
            _merge(a[k], v)
        else:
            a[k] = copy.deepcopy(v)
    return a


def write_network_profile(out_dir: str | Path, net, prefix: str = "energyctl", rig: str = "rig",
                          coordinator: str = "coordinator", operators: list[str] | None = None,
                          monitors: list[str] | None = None, listen: list[str] | None = None,
                          hosts: dict[str, list[str]] | None = None, hub: str | None = None,
                          hub_endpoints: list[str] | None = None, uplink_interface: str | None = None,
                          lease_ms: int | None = 1000, keep_alive: int | None = 4,
                          wait_before_drop_us: int | None = None) -> dict[str, Path]:
    """The secure profile of a live network (``net``: its NetworkScenario): one identity per source daemon (its
    source's name), the rig, the coordinator, the operators and monitors.

    Without ``hosts``: one router for all, ``router.json5`` listening on ``listen``. With ``hosts`` (``{host:
    [identities that run there]}``) one router per host, ``router-HOST.json5``, each with its own identity
    ``router-HOST`` (its password in that file; the hub's also a fixed Zenoh id): every router listens on ``listen``
    (default loopback: only its host's processes reach it) and admits only its host's identities and the operators
    and monitors; the hub's router also listens on ``hub_endpoints`` and every other router connects there.
    Routers are linked hub-and-spoke: the hub authenticates each spoke by its user and password; a spoke (which
    makes the connection, and so learns no user of the other side) names the hub by its Zenoh id, and with
    ``uplink_interface`` also by the interface its link leaves on, so that a process of its own host cannot pass as
    the hub.

    Also ``client.json5``, for every process's ``--zenoh-config``: the reconnection timing, and energyctl's
    send-queue size and shared-memory setting (a config file replaces energyctl's defaults for them).
    ``lease_ms``/``keep_alive`` (None: Zenoh's 10 s / 4), the routers': a router link silent for a lease is closed,
    so a cut between hosts is seen within it (see link_timing). ``wait_before_drop_us`` (None: Zenoh's 1000 us): how
    long a message under drop congestion control (every sample and command, service.daemon.bus.publisher) waits
    for room in a full send queue before it is dropped, in every router and process (decisions/0044). Existing
    passwords are kept."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    operators = operators if operators is not None else ["operator"]
    monitors = monitors if monitors is not None else ["monitor"]
    processes = [rig, coordinator, *net.sources]
    users = [*processes, *operators, *monitors]
    listen = listen or ["tcp/127.0.0.1:7447"]
    timing = link_timing(lease_ms, keep_alive)
    if hosts:
        if hub is None or hub not in hosts:
            raise ScenarioError(f"secure profile: the hub must be one of the hosts {sorted(hosts)}, got {hub!r}")
        if not hub_endpoints:
            raise ScenarioError("secure profile: the hub needs an endpoint the other routers connect to "
                                "(--hub HOST=ENDPOINT, e.g. tcp/10.0.0.1:7448)")
        placed = [u for ids in hosts.values() for u in ids]
        unknown = sorted(set(placed) - set(processes))
        if unknown:
            raise ScenarioError(f"secure profile: {unknown} on --host: not a process of network {net.name!r} "
                                f"(its processes: {', '.join(processes)}; operators and monitors may use any host)")
        twice = sorted({u for u in placed if placed.count(u) > 1})
        if twice:
            raise ScenarioError(f"secure profile: {twice} placed on more than one host")
        missing = [u for u in processes if u not in placed]
        if missing:
            raise ScenarioError(f"secure profile: {missing} placed on no host (--host HOST=ID,...)")
        users += [f"router-{h}" for h in hosts]
    dup = sorted({u for u in users if users.count(u) > 1})
    if dup:
        raise ScenarioError(f"secure profile: each identity needs its own user name; repeated: {dup}")
    creds_path = out / CREDENTIALS_FILE
    creds = _read_credentials(creds_path)
    for u in users:
        creds.setdefault(u, secrets.token_urlsafe(24))
    _write_private(creds_path, "".join(f"{u}:{creds[u]}\n" for u in users))
    paths: dict[str, Path] = {"credentials": creds_path}
    for u in users:
        if u.startswith("router-") and hosts:  # a router's password is in its config
            continue
        paths[u] = out / f"{u}.password"
        _write_private(paths[u], creds[u] + "\n")
    from service.daemon.bus import TX_QUEUE_BATCHES

    # a router forwards every sample and command: its send queue as deep as a process's (service.daemon.bus)
    queue = {"transport": {"link": {"tx": {"queue": {"size": {"data": TX_QUEUE_BATCHES}}}}}}
    if wait_before_drop_us is not None:
        queue["transport"]["link"]["tx"]["queue"]["congestion_control"] = {
            "drop": {"wait_before_drop": int(wait_before_drop_us)}}
    head = ("// energyctl secure profile of network {net} (energyctl secure-profile --network){extra}; Zenoh JSON5, "
            "also for zenohd -c\n// (zenohd reads dictionary_file from its working directory, energyctl router from "
            "here)\n")
    if not hosts:
        acl = network_access_control(prefix, net, rig, coordinator, operators, monitors)
        cfg = _merge(_merge(router_config(listen, acl), queue), timing)
        paths["router"] = out / ROUTER_FILE
        paths["router"].write_text(head.format(net=net.name, extra="") + json.dumps(cfg, indent=2) + "\n")
    else:
        hub_user = f"router-{hub}"
        hub_zid = router_zid(hub_user, creds[hub_user])
        for h, ids in hosts.items():
            me = f"router-{h}"
            if h == hub:
                peers = {f"router-{o}": {"usernames": [f"router-{o}"]} for o in hosts if o != hub}
                endpoints = [*listen, *[e for e in hub_endpoints if e not in listen]]
            else:
                peers = {hub_user: {"zids": [hub_zid],
                                    **({"interfaces": [uplink_interface]} if uplink_interface else {})}}
                endpoints = list(listen)
            acl = network_access_control(prefix, net, rig, coordinator, operators, monitors, users=set(ids),
                                         peer_routers=peers)
            cfg = router_config(endpoints, acl)
            if h == hub:  # the spokes' ACLs name it by this id; a spoke keeps a fresh id per start (a restarted one
                # is then a new router to the others, not one whose state they still hold)
                cfg = {"id": hub_zid, **cfg}
            cfg["transport"]["auth"]["usrpwd"].update(user=me, password=creds[me])
            if h != hub:
                cfg["connect"] = {"endpoints": list(hub_endpoints)}
            cfg = _merge(_merge(cfg, queue), timing)
            paths[me] = out / f"{me}.json5"
            _write_private(paths[me], head.format(net=net.name, extra=f", host {h}"
                                                  + (" (the hub)" if h == hub else f" (connects to the hub {hub})"))
                           + json.dumps(cfg, indent=2) + "\n")
    client = _merge(_merge({"transport": {"shared_memory": {"enabled": False}}}, queue),
                    link_timing(lease_ms, keep_alive, lease=False))
    paths["client"] = out / CLIENT_FILE
    paths["client"].write_text("// energyctl secure profile: link timing for every process (--zenoh-config); the "
                               "mode, endpoint and credentials come from the command line\n"
                               + json.dumps(client, indent=2) + "\n")
    return paths


CLIENT_FILE = "client.json5"


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
               stop: threading.Event | None = None, audit: bool = False, status_key: str | None = None) -> int:
    """A Zenoh router in this process until SIGINT/SIGTERM (or ``stop``). Prints one line when listening.

    audit (``energyctl router`` by default; once per process, it takes over the process's stdout): Zenoh's log of
    refused logins and access-control denials (clients/refusals.py) is turned on, with RUST_LOG's directives if
    set, else refusals.DIRECTIVES; each refusal is printed to stderr (repeats summarised) and counted. status_key:
    a queryable there answers those counts (``{"router": ..., "refusals": RefusalLog.status()}``)."""
    import sys

    from service.daemon.bus import open_session, serve_queries

    log = None
    if audit:
        import zenoh

        from clients.refusals import DIRECTIVES, RefusalLog, capture_stdout

        log = RefusalLog()
        capture_stdout(log)
        zenoh.init_log_from_env_or(DIRECTIVES)
    z = ZenohConfig(mode="router", listen=listen, config_file=config_file)
    session = open_session(z)
    served = None
    if status_key:
        import zenoh

        q = session.declare_queryable(status_key, zenoh.handlers.FifoChannel(16))
        body = {"router": str(session.info.zid()), "audit": log is not None}
        served = (q, threading.Thread(target=serve_queries, name="router-status", daemon=True, args=(
            q, status_key, lambda _q: (True, {**body, "refusals": log.status() if log else None}))))
        served[1].start()
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    acl = "off"
    if config_file:
        from service.daemon.bus import zenoh_config

        acl = "on" if json.loads(zenoh_config(z).get_json("access_control/enabled")) else "off"
    print(f"energyctl router: listening on {listen or 'the config file endpoints'}, access control {acl}, "
          f"refusals {'logged' if log else 'not logged'}" + (f", status on {status_key}" if status_key else ""),
          file=sys.stderr, flush=True)
    if ready is not None:
        ready.set()
    try:
        stop.wait()
    finally:
        session.close()  # closes the status channel too: its thread ends
        if log is not None:
            st = log.status()
            print(f"energyctl router: refused {st['logins_refused']} login(s), denied {st['acl_denied']} message(s)",
                  file=sys.stderr, flush=True)
    return 0
