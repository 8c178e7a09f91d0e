"""A fleet's authentication and access control, as zenoh configuration files.

``fleetmap secure`` writes a router config and one client config per role. The router enforces
the rules below; every robot and service runs as a *client* of it with scouting off, because peers
that link to each other directly bypass a router's rules (checked on zenoh 1.x: a router's access
control applies to what passes through it, not to a link two peers open between themselves).

Who may do what (``P`` is ``fleet/<fleet>``; anything not listed is denied):

- robot ``rX``: put on its own keys only, ``P/robots/rX/scan``, ``P/robots/rX/localmap`` and
  ``P/robots/rX/events`` (not its global pose, the merger's, nor any key it makes up); hold the
  liveliness token ``P/alive/rX`` only; read the merger's outputs
  (``P/merger/**``, its own global pose) and the fleet events (``P/events``), and query the
  merger's state (a starting agent begins after the epochs the merger holds of its robot).
- ``merger``: read every robot (``P/robots/**``, ``P/alive/*``) and the fleet events; put under
  ``P/merger/**``, on ``P/events`` and on every robot's global pose ``P/robots/*/pose``; answer
  ``P/merger/state``; hold ``P/services/merger``; ask the recorder for the maps it kept
  (``P/recorder/maps``).
- ``recorder``: read everything under ``P``; answer ``P/recorder/stats`` and ``P/recorder/maps``;
  hold ``P/services/recorder``.
- ``viewer`` (Foxglove bridges, dashboards, ``fleetmap run``'s own watcher): read everything under
  ``P``; query the merger's state and the recorder's statistics.

Everyone may declare on ``fleetmap/barrier/**`` and query and reply there: :class:`ZenohBus`'s
flush before closing (:mod:`fleetmap.shared.io.zenoh_bus`). A client is known by its username (user and
password, ``transport.auth.usrpwd``) and, with TLS, also by its certificate's common name (mutual
TLS); a subject needs both.

Everything here is pure (dicts in, dicts out) except :func:`write_fleet_security`, which writes the
files with owner-only permissions and prints no secret.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys, check_name
from fleetmap.shared.io.zenoh_config import DEFAULT_ENDPOINT, KEEP_ALIVE, LEASE_MS

SERVICES = ("merger", "recorder", "viewer")
"""The roles that are not robots (a robot may not take one of these names)."""
PASSWORD_BYTES = 32
"""Random bytes per password (256 bits, URL-safe base64)."""
CERT_DAYS = 825
"""Validity of generated certificates (the longest most TLS clients accept)."""

ALL_DECLARATIONS = ["declare_subscriber", "declare_queryable", "liveliness_token", "declare_liveliness_subscriber"]
READ = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]


@dataclass(frozen=True)
class TlsFiles:
    """Where a role's TLS material is (paths as written into its config)."""

    ca: str
    certificate: str
    key: str


def check_fleet_roles(fleet: str, robots: list[str]) -> None:
    """BadInput unless ``fleet`` and ``robots`` are valid names, distinct, and no robot takes a
    service's name."""
    check_name(fleet, "--fleet")
    if not robots:
        raise BadInput("--robots", "name at least one robot")
    for robot in robots:
        check_name(robot, "--robots")
        if robot in SERVICES:
            raise BadInput("--robots", f"{robot!r} is a service's name ({', '.join(SERVICES)}); rename the robot")
    duplicated = sorted({r for r in robots if robots.count(r) > 1})
    if duplicated:
        raise BadInput("--robots", f"named twice: {', '.join(duplicated)}")


def _rule(rule_id: str, flow: str, messages: list[str], keys: list[str], permission: str = "allow") -> dict[str, Any]:
    return {"id": rule_id, "permission": permission, "flows": [flow], "messages": messages, "key_exprs": keys}


def access_control(fleet: str, robots: list[str], tls: bool = False) -> dict[str, Any]:
    """The router's ``access_control`` block: default deny, and the rules of the module docstring.

    A router checks a message twice: on the way in from its sender (``ingress``, the sender's
    subject) and on the way out to each receiver (``egress``, the receiver's subject). So "r1 may
    put its scans" is an ingress rule on r1, and "the merger may read them" an egress rule on the
    merger (plus the merger's own declaration of the subscription, on ingress).
    """
    check_fleet_roles(fleet, robots)
    p = FleetKeys(fleet).prefix
    rules = [*_everyone_rules(p), *_robots_rules(p), *_merger_rules(p), *_recorder_rules(p), *_viewer_rules(p)]
    subjects = [_subject(role, tls) for role in [*robots, *SERVICES]]
    policies = _role_policies(rules, robots, subjects)
    for robot in robots:
        own = _robot_own_rules(p, robot)
        rules += own
        policies.append({"id": f"robot-{robot}", "rules": [r["id"] for r in own], "subjects": [robot]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _everyone_rules(p: str) -> list[dict[str, Any]]:
    """What every client of the fleet may do (``p``: the fleet's key prefix)."""
    return [
        # the flush barrier of every bus
        _rule("barrier-in", "ingress", ["declare_queryable", "query", "reply"], ["fleetmap/barrier/**"]),
        _rule("barrier-out", "egress", ["declare_queryable", "query", "reply"], ["fleetmap/barrier/**"]),
        # who subscribes and who is alive may be known to everyone of the fleet: declarations carry no data
        _rule("declarations-out", "egress", ALL_DECLARATIONS, [f"{p}/**"]),
    ]


def _robots_rules(p: str) -> list[dict[str, Any]]:
    """What every robot may do beyond its own keys (:func:`_robot_own_rules`)."""
    return [
        # robots read the merger's outputs and the fleet events, and ask its state (a starting agent
        # begins after the epochs the merger holds of its robot)
        _rule("robot-read-in", "ingress", ["declare_subscriber"], [f"{p}/merger/**", f"{p}/events"]),
        _rule("robot-read-out", "egress", ["put"], [f"{p}/merger/**", f"{p}/events"]),
        _rule("robot-state-in", "ingress", ["query"], [f"{p}/merger/state"]),
        _rule("robot-state-out", "egress", ["reply"], [f"{p}/merger/state"]),
        # a robot's global pose is the merger's to say (an explicit deny outranks the robot's own keys)
        _rule("robot-no-pose", "ingress", ["put"], [f"{p}/robots/*/pose"], permission="deny"),
    ]


def _merger_rules(p: str) -> list[dict[str, Any]]:
    """What the merger may do."""
    return [
        _rule(
            "merger-read-in",
            "ingress",
            READ,
            [f"{p}/robots/**", f"{p}/events", f"{p}/alive/**"],
        ),
        _rule("merger-read-out", "egress", ["put"], [f"{p}/robots/**", f"{p}/events"]),
        _rule("merger-write", "ingress", ["put"], [f"{p}/merger/**", f"{p}/events", f"{p}/robots/*/pose"]),
        _rule("merger-state-in", "ingress", ["declare_queryable", "reply"], [f"{p}/merger/state"]),
        _rule("merger-state-out", "egress", ["query"], [f"{p}/merger/state"]),
        _rule("merger-token", "ingress", ["liveliness_token"], [f"{p}/services/merger"]),
        # a restarted merger recalls the maps the recorder kept (robots that finished while it was down)
        _rule("merger-recall-in", "ingress", ["query"], [f"{p}/recorder/maps"]),
        _rule("merger-recall-out", "egress", ["reply"], [f"{p}/recorder/maps"]),
    ]


def _recorder_rules(p: str) -> list[dict[str, Any]]:
    """What the recorder may do."""
    return [
        _rule("recorder-read-in", "ingress", READ, [f"{p}/**"]),
        _rule("recorder-read-out", "egress", ["put"], [f"{p}/**"]),
        _rule(
            "recorder-stats-in",
            "ingress",
            ["declare_queryable", "reply"],
            [f"{p}/recorder/stats", f"{p}/recorder/maps"],
        ),
        _rule("recorder-stats-out", "egress", ["query"], [f"{p}/recorder/stats", f"{p}/recorder/maps"]),
        _rule("recorder-token", "ingress", ["liveliness_token"], [f"{p}/services/recorder"]),
    ]


def _viewer_rules(p: str) -> list[dict[str, Any]]:
    """What a viewer may do."""
    return [
        _rule("viewer-read-in", "ingress", READ, [f"{p}/**"]),
        _rule("viewer-read-out", "egress", ["put"], [f"{p}/**"]),
        _rule("viewer-query-in", "ingress", ["query"], [f"{p}/merger/state", f"{p}/recorder/stats"]),
        _rule("viewer-query-out", "egress", ["reply"], [f"{p}/merger/state", f"{p}/recorder/stats"]),
    ]


def _role_policies(
    rules: list[dict[str, Any]], robots: list[str], subjects: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Which subjects the shared rules apply to: everyone, every robot, and each service its own."""
    return [
        {
            "id": "everyone",
            "rules": ["barrier-in", "barrier-out", "declarations-out"],
            "subjects": [s["id"] for s in subjects],
        },
        {
            "id": "robots-read",
            "rules": ["robot-read-in", "robot-read-out", "robot-state-in", "robot-state-out", "robot-no-pose"],
            "subjects": robots,
        },
        {
            "id": "merger",
            "rules": [r["id"] for r in rules if r["id"].startswith("merger-")],
            "subjects": ["merger"],
        },
        {
            "id": "recorder",
            "rules": [r["id"] for r in rules if r["id"].startswith("recorder-")],
            "subjects": ["recorder"],
        },
        {"id": "viewer", "rules": [r["id"] for r in rules if r["id"].startswith("viewer-")], "subjects": ["viewer"]},
    ]


def _robot_own_rules(p: str, robot: str) -> list[dict[str, Any]]:
    """What robot ``robot`` alone may do: put on its own keys, and hear its global pose."""
    return [
        # a robot's own keys: its scans, local maps and events, and its presence
        _rule(
            f"robot-{robot}-write",
            "ingress",
            ["put"],
            [f"{p}/robots/{robot}/{leaf}" for leaf in ("scan", "localmap", "events")],
        ),
        _rule(f"robot-{robot}-token", "ingress", ["liveliness_token"], [f"{p}/alive/{robot}"]),
        # ... and where the merger puts it
        _rule(f"robot-{robot}-pose-in", "ingress", ["declare_subscriber"], [f"{p}/robots/{robot}/pose"]),
        _rule(f"robot-{robot}-pose-out", "egress", ["put"], [f"{p}/robots/{robot}/pose"]),
    ]


def _subject(role: str, tls: bool) -> dict[str, Any]:
    subject: dict[str, Any] = {"id": role, "usernames": [role]}
    if tls:
        subject["cert_common_names"] = [role]
    return subject


def _scouting_off() -> dict[str, Any]:
    return {"multicast": {"enabled": False}, "gossip": {"enabled": False}}


def _link(tls: TlsFiles | None, side: str) -> dict[str, Any]:
    """``transport.link``: the lease (a robot that stops answering is seen leaving within it) and,
    with ``tls``, the role's certificate for the ``listen`` (router) or ``connect`` (client) side."""
    link: dict[str, Any] = {"tx": {"lease": LEASE_MS, "keep_alive": KEEP_ALIVE}}
    if tls is not None:
        link["tls"] = {
            "root_ca_certificate": tls.ca,
            f"{side}_certificate": tls.certificate,
            f"{side}_private_key": tls.key,
            "enable_mtls": True,
        }
    return link


def router_config(
    fleet: str, robots: list[str], users_file: str, listen: list[str], tls: TlsFiles | None = None
) -> dict[str, Any]:
    """The router's zenoh config: users and passwords from ``users_file``, the access control of
    :func:`access_control`, and, with ``tls``, mutual TLS (a client without a certificate signed by
    the fleet's CA is refused before it can log in)."""
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": _scouting_off(),
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}, "link": _link(tls, "listen")},
        "access_control": access_control(fleet, robots, tls=tls is not None),
    }


def client_config(user: str, password: str, connect: list[str], tls: TlsFiles | None = None) -> dict[str, Any]:
    """A robot's or service's zenoh config: a client of the router, scouting off, its credentials."""
    return {
        "mode": "client",
        "connect": {"endpoints": connect},
        "scouting": _scouting_off(),
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}, "link": _link(tls, "connect")},
    }


def new_password() -> str:
    return secrets.token_urlsafe(PASSWORD_BYTES)


def endpoint_host(endpoint: str) -> str:
    """The host of ``proto/host:port`` (brackets of an IPv6 address removed)."""
    try:
        _, address = endpoint.split("/", 1)
        host, port = address.rsplit(":", 1)
        int(port)
    except ValueError:
        raise BadInput(endpoint, "expected an endpoint proto/host:port, e.g. tcp/10.0.0.5:7447") from None
    return host.strip("[]")


# --- files ---


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` readable by its owner only (created so, never world-readable)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, data)
    finally:
        os.close(fd)


def _json5(config: dict[str, Any], role: str) -> bytes:
    head = f"// fleetmap secure: zenoh config of {role}. Holds secrets: keep it readable by its owner only.\n"
    return (head + json.dumps(config, indent=2) + "\n").encode()


def write_fleet_security(
    out: Path,
    fleet: str,
    robots: list[str],
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    tls: bool = False,
) -> list[Path]:
    """Write ``router.json5``, ``users.txt`` and one ``<role>.json5`` per robot and service into
    ``out`` (and, with ``tls``, a CA and one key and certificate per role under ``out/tls``); the
    paths written, every file owner-only. Paths inside the configs are absolute (a container
    mounts ``out`` at the same path)."""
    check_fleet_roles(fleet, robots)
    scheme = "tls" if tls else "tcp"
    default = DEFAULT_ENDPOINT.replace("tcp/", f"{scheme}/")
    listen = listen or [default]
    # a router listening on every interface is reached on loopback, at its port, unless --connect says
    connect = connect or [e.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:") for e in listen]
    for endpoint in [*listen, *connect]:
        endpoint_host(endpoint)
        if tls != endpoint.startswith("tls/"):
            raise BadInput(endpoint, f"{'--tls needs tls/ endpoints' if tls else 'a tls/ endpoint needs --tls'}")
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    roles = [*robots, *SERVICES]
    passwords = {role: new_password() for role in roles}
    written: list[Path] = []
    users = out / "users.txt"
    _write_private(users, "".join(f"{role}:{passwords[role]}\n" for role in roles).encode())
    written.append(users)
    tls_files: dict[str, TlsFiles] = {}
    if tls:
        hosts = sorted({"localhost", "127.0.0.1", *(endpoint_host(e) for e in [*listen, *connect])} - {"0.0.0.0"})
        tls_files, pem_paths = _write_certificates(out / "tls", ["router", *roles], hosts)
        written += pem_paths
    router = out / "router.json5"
    _write_private(router, _json5(router_config(fleet, robots, str(users), listen, tls_files.get("router")), "router"))
    written.append(router)
    for role in roles:
        path = out / f"{role}.json5"
        _write_private(path, _json5(client_config(role, passwords[role], connect, tls_files.get(role)), role))
        written.append(path)
    return written


def _write_certificates(folder: Path, roles: list[str], hosts: list[str]) -> tuple[dict[str, TlsFiles], list[Path]]:
    """A fleet CA and one certificate per role, its common name the role (the router's also names
    ``hosts``, so clients can verify it)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    now = datetime.datetime.now(datetime.UTC)
    until = now + datetime.timedelta(days=CERT_DAYS)

    def name(common: str) -> x509.Name:
        return x509.Name(
            [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "fleetmap"), x509.NameAttribute(NameOID.COMMON_NAME, common)]
        )

    def pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
        return key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name("fleetmap fleet CA")
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )  # key_cert_sign, crl_sign
        .sign(ca_key, hashes.SHA256())
    )
    ca_path = folder / "ca.pem"
    _write_private(ca_path, ca.public_bytes(serialization.Encoding.PEM))
    written = [ca_path]
    files: dict[str, TlsFiles] = {}
    for role in roles:
        key = ec.generate_private_key(ec.SECP256R1())
        alt: list[x509.GeneralName] = [x509.DNSName(role)]
        if role == "router":
            for host in hosts:
                try:
                    alt.append(x509.IPAddress(ipaddress.ip_address(host)))
                except ValueError:
                    alt.append(x509.DNSName(host))
        cert = (
            x509.CertificateBuilder()
            .subject_name(name(role))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now)
            .not_valid_after(until)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .sign(ca_key, hashes.SHA256())
        )
        cert_path, key_path = folder / f"{role}.pem", folder / f"{role}.key"
        _write_private(cert_path, cert.public_bytes(serialization.Encoding.PEM))
        _write_private(key_path, pem_key(key))
        written += [cert_path, key_path]
        files[role] = TlsFiles(str(ca_path), str(cert_path), str(key_path))
    return files, written
