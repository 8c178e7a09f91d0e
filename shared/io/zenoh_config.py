"""The zenoh flags every fleetmap service takes, and the zenoh configuration they resolve to.

``--mode peer|client|router``, ``--connect ENDPOINT`` (repeatable), ``--listen ENDPOINT``
(repeatable), ``--zenoh-config FILE`` (json5, zenoh's own format) and ``--fleet NAME``.

Without a config file, a session is a peer on loopback: multicast scouting off (nothing leaves
the machine unless an endpoint says so), a 2 s lease so a hung or cut-off robot is seen leaving
within 2 s (zenoh's default is 10 s), and these endpoints:

- peer: listens where ``--listen`` says; without ``--listen`` on ``tcp/127.0.0.1:0`` (a free
  loopback port) and, without ``--connect`` either, connects to ``tcp/127.0.0.1:7447``. A peer
  given only ``--listen`` is a hub: others connect to it.
- client: connects where ``--connect`` says, or to ``tcp/127.0.0.1:7447``.
- router: listens where ``--listen`` says, or on ``tcp/127.0.0.1:7447``.

So ``fleetmap router``, or any peer started with ``--listen tcp/127.0.0.1:7447``, is the meeting
point on one machine; a peer that finds nobody there keeps trying in the background, and peers
that meet through it link to each other directly (gossip scouting).

With ``--zenoh-config FILE`` the file decides everything it says (security, scouting, lease, ...)
and fleetmap adds no default; ``--mode``, ``--connect`` and ``--listen`` still override it.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import DEFAULT_FLEET, FleetKeys, check_name

MODES = ("peer", "client", "router")
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where a router listens and peers and clients connect when no endpoint is given."""
LOOPBACK_ANY_PORT = "tcp/127.0.0.1:0"
LEASE_MS = 2000
"""A session that stops answering for this long is considered gone (its liveliness tokens leave)."""
KEEP_ALIVE = 4
"""Keep-alive messages per lease period."""
CONNECT_WAIT = 60.0
"""Seconds a service keeps trying its ``--connect`` endpoints at start (``--connect-wait``)."""


@dataclass(frozen=True)
class ZenohOptions:
    """The zenoh flags of a service, as given (None and empty: not given)."""

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    fleet: str = DEFAULT_FLEET
    connect_wait: float = CONNECT_WAIT
    """How long (s) to keep trying the ``connect`` endpoints when none answers at start (a router
    that is not up yet); 0: fail at once."""

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in MODES:
            raise BadInput("--mode", f"expected one of {', '.join(MODES)}, got {self.mode!r}")
        check_name(self.fleet, "--fleet")
        if not (self.connect_wait >= 0 and math.isfinite(self.connect_wait)):
            raise BadInput("--connect-wait", f"must be a number of seconds, 0 or more, got {self.connect_wait}")
        for flag, endpoints in (("--connect", self.connect), ("--listen", self.listen)):
            for endpoint in endpoints:
                _check_port(flag, endpoint)

    @property
    def keys(self) -> FleetKeys:
        return FleetKeys(self.fleet)

    def with_mode(self, mode: str) -> ZenohOptions:
        return ZenohOptions(mode, self.connect, self.listen, self.config_file, self.fleet, self.connect_wait)


def _check_port(flag: str, endpoint: str) -> None:
    """BadInput for an IP endpoint (``tcp/HOST:PORT``, udp, tls, quic, ws) whose port is a number
    no socket has: zenoh accepts its form and fails only when the session opens."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    protocol, _, address = locator.partition("/")
    if protocol not in ("tcp", "udp", "tls", "quic", "ws") or ":" not in address:
        return
    port = address.rsplit(":", 1)[1]
    if port.isdigit() and not 0 <= int(port) <= 65535:
        raise BadInput(f"{flag} {endpoint}", f"port {port} is not a port number (0-65535)")


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, mode: bool = True, fleet: bool = True) -> None:
    """Add the zenoh flags every service shares (``mode``/``fleet`` False leave those out)."""
    group = parser.add_argument_group("zenoh (see fleetmap.shared.io.zenoh_config for the defaults)")
    if mode:
        group.add_argument("--mode", choices=MODES, default=None, help="zenoh session mode (default: peer)")
    group.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable; default {DEFAULT_ENDPOINT})",
    )
    group.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to listen on (repeatable; peers default to {LOOPBACK_ANY_PORT}, routers to {DEFAULT_ENDPOINT})",
    )
    group.add_argument(
        "--connect-wait",
        type=float,
        default=CONNECT_WAIT,
        metavar="S",
        help="keep trying --connect for up to S seconds at start, backing off, while nothing answers (a router "
        f"not up yet); 0: fail at once (default {CONNECT_WAIT:g})",
    )
    group.add_argument("--zenoh-config", metavar="FILE", default=None, help="a zenoh config file (json5)")
    if fleet:
        group.add_argument(
            "--fleet",
            default=DEFAULT_FLEET,
            metavar="NAME",
            help=f"fleet name: keys are fleet/NAME/... (default {DEFAULT_FLEET!r})",
        )


def zenoh_options_from_args(args: argparse.Namespace) -> ZenohOptions:
    return ZenohOptions(
        mode=getattr(args, "mode", None),
        connect=tuple(getattr(args, "connect", ()) or ()),
        listen=tuple(getattr(args, "listen", ()) or ()),
        config_file=getattr(args, "zenoh_config", None),
        fleet=getattr(args, "fleet", DEFAULT_FLEET),
        connect_wait=getattr(args, "connect_wait", CONNECT_WAIT),
    )


def _insert(config: zenoh.Config, key: str, value: Any, source: str) -> None:
    try:
        config.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise BadInput(source, _first_line(exc)) from None


def _first_line(exc: Exception) -> str:
    """zenoh's error text without the Rust source locations it appends."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    inner = re.search(r'msg: "([^"]*)', text)  # a Rust error structure: Json5Err(Message { msg: "..." ... })
    if inner:
        text = inner.group(1)
    return text.split(" at /")[0][:300]


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """The zenoh.Config of ``options`` (see the module docstring for the defaults)."""
    if options.config_file is not None:
        path = Path(options.config_file)
        if not path.is_file():
            raise BadInput(str(path), "no such zenoh config file")
        try:
            config = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise BadInput(str(path), f"not a valid zenoh config: {_first_line(exc)}") from None
    else:
        config = zenoh.Config()
        _insert(config, "scouting/multicast/enabled", False, "scouting")
        _insert(config, "transport/link/tx/lease", LEASE_MS, "lease")
        _insert(config, "transport/link/tx/keep_alive", KEEP_ALIVE, "keep_alive")
    mode = options.mode if options.mode is not None else ("peer" if options.config_file is None else None)
    if mode is not None:
        _insert(config, "mode", mode, "--mode")
    listen, connect = list(options.listen), list(options.connect)
    if options.config_file is None:
        if mode == "router" and not listen:
            listen = [DEFAULT_ENDPOINT]
        elif mode == "client" and not connect:
            connect = [DEFAULT_ENDPOINT]
        elif mode == "peer" and not listen:
            # a peer always listens, so that peers meeting through another one can link directly
            listen = [LOOPBACK_ANY_PORT]
            connect = connect or [DEFAULT_ENDPOINT]
    if listen:
        _insert(config, "listen/endpoints", listen, "--listen " + " ".join(listen))
    if connect:
        _insert(config, "connect/endpoints", connect, "--connect " + " ".join(connect))
    return config


def describe(config: zenoh.Config) -> dict[str, str]:
    """The parts of a resolved config worth recording: mode, endpoints, scouting (no credentials)."""
    out = {}
    for key in (
        "mode",
        "connect/endpoints",
        "listen/endpoints",
        "scouting/multicast/enabled",
        "transport/link/tx/lease",
    ):
        try:
            value = json.loads(config.get_json(key))
        except zenoh.ZError:  # a key this zenoh version does not have
            continue
        out[key] = value if isinstance(value, str) else json.dumps(value)
    return out


OPEN_FLEET = (
    "an OPEN fleet: no logins, no access control; anyone who reaches its router may join as any robot or "
    "service. For one machine (or a network you trust); on several hosts, `fleetmap secure` first "
    "(docker-compose.yml does)"
)
"""What a router or merger without credentials says at start."""


def is_open(config: zenoh.Config) -> bool:
    """Whether a session of ``config`` belongs to an open fleet: it enforces no access control (a
    router) and logs in as nobody (a client; a secured router refuses those)."""
    try:
        guarded = json.loads(config.get_json("access_control/enabled")) is True
        user = json.loads(config.get_json("transport/auth/usrpwd/user"))
    except zenoh.ZError:
        return True
    return not guarded and not user


def endpoints_argv(options: ZenohOptions) -> list[str]:
    """The command-line flags that give a child process the same zenoh options."""
    argv: list[str] = []
    if options.mode is not None:
        argv += ["--mode", options.mode]
    for endpoint in options.connect:
        argv += ["--connect", endpoint]
    for endpoint in options.listen:
        argv += ["--listen", endpoint]
    if options.config_file is not None:
        argv += ["--zenoh-config", options.config_file]
    argv += ["--fleet", options.fleet]
    return argv


def free_loopback_endpoint() -> str:
    """A TCP endpoint on a loopback port that is free now (for tests and ``fleetmap run``).

    The port is found by binding port 0 and closing the socket, so another process may take it
    before zenoh does; callers that start a listener should be ready to retry.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    return f"tcp/127.0.0.1:{port}"
