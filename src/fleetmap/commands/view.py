"""``fleetmap view``: the fleet live in Foxglove, over its WebSocket protocol."""

from __future__ import annotations

import argparse
import logging
import sys
import time

from fleetmap.merger.view import DEFAULT_PORT, GRID_PERIOD, FoxgloveServer, LiveView, ViewService
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.zenoh_args import add_zenoh_arguments, stop_on_signals, zenoh_options_from_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "view",
        help="serve the fleet live to Foxglove (WebSocket)",
        description="Serve the fleet live over the Foxglove WebSocket protocol: open ws://HOST:PORT in Foxglove "
        "(Open connection, Foxglove WebSocket) and watch the fleet as it maps. The channels are a recording's "
        "(scene line lists of scans, submaps and the global map, laser scans, robot paths, fleet events, one "
        "TF tree from the root frame 'fleet') and the occupancy grid of the largest merged map, redrawn every "
        f"{GRID_PERIOD:g} s while the global map changes. Runs until SIGINT or SIGTERM (or --duration).",
    )
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"WebSocket port (default {DEFAULT_PORT})")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1: this machine only; 0.0.0.0 serves other hosts)",
    )
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    add_zenoh_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 0 <= args.port <= 65535:
        raise BadInput("--port", f"must be a port number, got {args.port}")
    if args.duration is not None and not args.duration > 0:
        raise BadInput("--duration", f"must be a positive number of seconds, got {args.duration}")
    options = zenoh_options_from_args(args)
    with ZenohBus.open(options) as bus:
        try:
            server = FoxgloveServer(args.host, args.port)
        except RuntimeError as exc:  # the port taken, the address not this host's
            said = str(exc).removeprefix("FoxgloveError: ")
            raise BadInput(f"{args.host}:{args.port}", f"cannot serve there: {said}") from None
        view = LiveView(server, options.keys)
        started = time.monotonic()
        try:
            with ViewService(bus, view, server, options.keys), stop_on_signals() as stop:
                print(
                    f"serving {options.keys.everything} live on ws://{args.host}:{server.port} "
                    "(open it in Foxglove; Ctrl-C or SIGTERM to stop)",
                    file=sys.stderr,
                )
                while not stop.wait(0.1):
                    if args.duration is not None and time.monotonic() - started >= args.duration:
                        break
        finally:
            server.stop()
    shown = ", ".join(f"{n} {name}" for name, n in sorted(view.published.items())) or "nothing"
    print(f"view stopped after {time.monotonic() - started:.1f} s: {shown}; {view.malformed} malformed")
    return 0
