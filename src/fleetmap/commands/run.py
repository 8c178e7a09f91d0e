"""``fleetmap run``: the main job, a live multi-robot session of a scenario."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.report import summary_table
from fleetmap.runner import Session
from fleetmap.scenarios import DEFAULT_SCENARIO, load_scenario
from fleetmap.scenarios.loader import list_scenarios
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.outputs import output_folder


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "run",
        help="run a live multi-robot session of a scenario (the main job)",
        description="Start a zenoh router, the recorder, the merger and one agent process per robot on "
        "loopback, play the scenario (robots joining, leaving, crashing, kidnapped; merger restarts), and write "
        "DIR/session.mcap, global_map.json, global_map.png, map.pgm + map.yaml "
        "(the occupancy grid map_server loads), report.json, config.toml and scenario.toml.",
    )
    p.add_argument(
        "scenario",
        nargs="?",
        default=DEFAULT_SCENARIO,
        help=f"a bundled scenario ({', '.join(list_scenarios())}) or a scenario .toml (default {DEFAULT_SCENARIO})",
    )
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default runs/<scenario>)")
    p.add_argument("--speed", type=float, default=2.0, help="scenario seconds per wall second (default 2)")
    p.add_argument("--fleet", default="run", help="fleet name on the bus (default 'run')")
    p.add_argument(
        "--secure",
        action="store_true",
        help="with authentication and access control: each process logs in with its own credentials "
        "(fleetmap secure, written into DIR/secure) and may do only what its role may",
    )
    p.add_argument("--tls", action="store_true", help="with --secure: over mutual TLS")
    p.add_argument(
        "--view",
        action="store_true",
        help="serve the session live to Foxglove while it runs (fleetmap view): open ws://127.0.0.1:8765",
    )
    p.add_argument("--view-port", type=int, default=8765, metavar="PORT", help="with --view: its port (default 8765)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print report.json instead of the summary")
    add_config_arguments(p, ["extraction", "integration", "merge"], "live")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    scenario = load_scenario(args.scenario)
    if not args.speed > 0:
        raise BadInput("--speed", f"must be positive, got {args.speed}")
    out = output_folder(Path(args.out) if args.out else Path("runs") / scenario.name, "--out")
    if args.tls and not args.secure:
        raise BadInput("--tls", "goes with --secure")
    session = Session(
        scenario,
        out,
        config,
        speed=args.speed,
        fleet=args.fleet,
        progress=not args.no_progress,
        secure=args.secure,
        tls=args.tls,
        view_port=args.view_port if args.view else None,
    )
    report = session.run()
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"fleetmap run {scenario.name}: {report['seconds']:.1f} s, outputs in {out}/")
        print(summary_table(report))
        print(f"messages: {report['messages_recorded']} recorded of {report['messages_seen']} seen on the bus")
    return 0
