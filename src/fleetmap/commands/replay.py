"""``fleetmap replay``: a recorded session through a fresh merger, writing the same outputs as a run."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.replay import ReplayOptions, replay
from fleetmap.report import summary_table
from fleetmap.shared.errors import BadInput


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "replay",
        help="replay a recorded session offline to the same map",
        description="Feed the local maps of SESSION.mcap through a fresh merger (following the live merger's "
        "recorded steps, so the map is identical), as fast as possible or at --speed, and write global_map.json, "
        "global_map.png, map.pgm + map.yaml "
        "(the occupancy grid map_server loads) and report.json into --out. "
        "--from/--to (seconds from the start of the recording) and "
        "--robots replay part of it. A recording cut short by a crash replays up to its last complete chunk.",
    )
    p.add_argument("session", metavar="SESSION.mcap")
    p.add_argument("--out", required=True, metavar="DIR", help="the output folder (made if needed)")
    p.add_argument("--speed", type=float, default=0.0, help="0 (default): as fast as possible; 1: recorded pace")
    p.add_argument("--from", dest="start", type=float, default=None, metavar="T", help="seconds from the start")
    p.add_argument("--to", dest="stop", type=float, default=None, metavar="T", help="seconds from the start")
    p.add_argument("--robots", default=None, help="comma-separated robot names, e.g. r1,r3")
    p.add_argument("--json", action="store_true", help="print report.json instead of the summary")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_arguments(p, ["integration", "merge"])
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not (args.speed >= 0 and math.isfinite(args.speed)):
        raise BadInput("--speed", f"must be 0 (as fast as possible) or a positive factor, got {args.speed}")
    for flag, seconds in (("--from", args.start), ("--to", args.stop)):
        if seconds is not None and not (seconds >= 0 and math.isfinite(seconds)):
            raise BadInput(flag, f"must be a number of seconds from the start, 0 or more, got {seconds}")
    if args.start is not None and args.stop is not None and args.stop < args.start:
        raise BadInput("--to", f"{args.stop} is before --from {args.start}")
    robots = frozenset(r.strip() for r in args.robots.split(",") if r.strip()) if args.robots else None
    overridden = args.config is not None or any(k.startswith("cfg__") and v is not None for k, v in vars(args).items())
    options = ReplayOptions(args.speed, args.start, args.stop, robots, config_from_args(args) if overridden else None)
    bars: list[object] = []

    def progress(done: int, total: int) -> None:
        # Created on the first step, once the recording has been read: bad input prints one line only.
        if args.no_progress:
            return
        if not bars:
            from tqdm import tqdm

            bars.append(tqdm(desc="replay", unit="step", total=total, leave=False))
        bar = bars[0]
        bar.n = done  # type: ignore[attr-defined]
        bar.refresh()  # type: ignore[attr-defined]

    try:
        result = replay(args.session, args.out, options, progress)
    finally:
        for bar in bars:
            bar.close()  # type: ignore[attr-defined]
    if result.warning:
        print(f"warning: {result.warning}")
    if args.json:
        print(json.dumps(result.report, indent=2))
    else:
        info = result.report["replay"]
        same = {True: "identical to the live map", False: "DIFFERS from the live map", None: "partial replay"}
        restarts = info["merger_restarts"]
        through = f" (through {restarts} merger restart{'s' * (restarts > 1)})" if restarts else ""
        print(
            f"replayed {info['local_maps_fed']} local maps in {info['steps']} steps: {same[info['matches_live']]}"
            f"{through}"
        )
        print(summary_table(result.report))
        print(f"outputs in {Path(args.out)}/")
    return 0
