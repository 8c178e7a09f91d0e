"""``fleetmap router``: a zenoh router in Python, for multi-host and access-controlled fleets."""

from __future__ import annotations

import argparse
import logging
import sys

from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import DEFAULT_ENDPOINT, OPEN_FLEET, describe, is_open, zenoh_config
from fleetmap.zenoh_args import add_zenoh_arguments, stop_on_signals, zenoh_options_from_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "router",
        help="run a zenoh router (no zenohd needed)",
        description="A zenoh session in router mode: agents, the merger and the recorder connect to it "
        f"(clients, or peers). Listens on {DEFAULT_ENDPOINT} unless --listen says otherwise (use "
        "--listen tcp/0.0.0.0:7447 to serve other hosts); --zenoh-config gives it authentication and "
        "access control. Runs until SIGINT or SIGTERM.",
    )
    add_zenoh_arguments(p, mode=False, fleet=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = zenoh_options_from_args(args).with_mode("router")
    config = zenoh_config(options)
    with ZenohBus.open(config) as bus, stop_on_signals() as stop:
        described = describe(config)
        print(f"zenoh router {bus.session.zid()} listening on {described.get('listen/endpoints')}", file=sys.stderr)
        if is_open(config):
            log.warning("%s", OPEN_FLEET)
        while not stop.wait(0.5):
            continue
    print("zenoh router stopped")
    return 0
