"""``fleetmap map``: real logs and ROS 2 bags mapped offline in one command (fleetmap.mapping)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from fleetmap.commands import add_no_return_reading
from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.executor_args import add_executor_arguments, executor_from_args
from fleetmap.merger.executor import WORKER_NICENESS
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.startposes import read_start_poses

CONFIG_SECTIONS = ["extraction", "integration", "tracking", "merge"]
"""The config sections ``fleetmap map`` takes options of (offline preset)."""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "map",
        help="map CARMEN logs, ROS 2 bags or ranges JSONL files offline, each one robot",
        description="Map real logs offline, in one command, with the same agent and merger code as the live "
        "services: each INPUT is one robot (a CARMEN log, plain or .gz; a ROS bag: a rosbag2 directory, .mcap "
        "or .db3 file, or a ROS 1 .bag; a "
        "ranges JSONL file); --split K cuts each input into K robots' consecutive pieces that run side by side, "
        "their clocks starting together. The same inputs give the same outputs. Writes global_map.json, "
        "global_map.png, map.pgm + map.yaml "
        "(the occupancy grid map_server loads), report.json, poses.csv "
        "(robot,stamp,component,x,y,theta: every scan that got a pose, "
        "its stamp as the input gives it) and one TUM trajectory per robot (<robot>.tum) into --out.",
    )
    given = p.add_argument_group("input")
    given.add_argument("inputs", nargs="+", metavar="INPUT", help="a CARMEN log, a ROS bag or a ranges JSONL file")
    given.add_argument("--split", type=int, default=1, metavar="K", help="cut each input into K robots (default 1)")
    given.add_argument(
        "--topic",
        default=None,
        help="ROS bags: the sensor_msgs/LaserScan topic (default: the bag's one LaserScan topic, /scan if several)",
    )
    given.add_argument(
        "--odometry-topic",
        default=None,
        metavar="TOPIC",
        help="ROS bags: the nav_msgs/Odometry topic (default: the first one, else tf odom -> base_link)",
    )
    given.add_argument(
        "--start-poses",
        metavar="POSES.csv",
        help="robot,x,y,theta lines: robots' laser poses when they start, in one frame (a header line allowed): each "
        "is placed from its first submap, and corrected where its map meets the others' (robots are named as "
        "poses.csv names them)",
    )
    add_no_return_reading(given)
    made = p.add_argument_group("output")
    made.add_argument("--out", required=True, metavar="DIR", help="the output directory (created if needed)")
    made.add_argument("--json", action="store_true", help="print report.json's map section instead of the table")
    made.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_executor_arguments(p)
    add_config_arguments(p, CONFIG_SECTIONS, "offline")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fleetmap.mapping import map_logs, read_inputs

    config = config_from_args(args)
    start_poses = read_start_poses(args.start_poses) if args.start_poses else None
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise BadInput(str(out), "exists and is not a directory (--out)")
    pieces = read_inputs(args.inputs, args.split, args.topic, args.no_return_reading, args.odometry_topic)
    bars: list[object] = []

    def progress(done: int, total: int) -> None:
        if args.no_progress:
            return
        if not bars:
            from tqdm import tqdm

            bars.append(tqdm(desc="map", unit="scan", total=total, leave=False))
        bar = bars[0]
        bar.n = done  # type: ignore[attr-defined]
        bar.refresh()  # type: ignore[attr-defined]

    executor = executor_from_args(args, WORKER_NICENESS)  # the agents track beside its workers
    try:
        result = map_logs(pieces, out, config, progress, executor, start_poses=start_poses)
    finally:
        executor.close()
        for bar in bars:
            bar.close()  # type: ignore[attr-defined]
    summary = result.report["map"]
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(table(summary))
    print(f"outputs in {out}/")
    return 0


def table(summary: dict[str, Any]) -> str:
    """One line per robot, then the totals. A robot's maps are named as poses.csv names them
    (``#0`` is the largest merged map); ``-`` where none of its scans got a pose. The odometry
    column says whether the tracking used the input's odometry: ``used``, ``not used``
    (``--odometry off``) or ``none`` (the input has none)."""
    rows = [("robot", "scans", "placed", "epochs", "in map", "odometry")]
    for r in summary["robots"]:
        comps = ",".join(f"#{c}" for c in r["components"]) or "-"
        rows.append(
            (
                r["robot"],
                str(r["scans"]),
                str(r["scans_placed"]),
                str(r["epochs"]),
                comps,
                "used" if r.get("odometry_used", r["odometry"]) else "not used" if r["odometry"] else "none",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)) for row in rows]
    share, duration = summary["time_share"], summary["duration_s"]
    split = duration is not None and summary["session_s"] < duration
    lines.append(
        f"{summary['submaps']} submaps in {summary['components']} merged map(s) "
        f"(#0, the largest, holds {summary['largest_component_submaps']}); "
        f"{summary['integrations']} integrations ({summary['integrations_near']} near a prediction, "
        f"{summary['integrations_idle']} while idle); "
        f"{summary['seconds']:.1f} s for "
        + (f"{duration:.0f} s of log" if duration is not None else "a log whose stamps are not times")
        + (f" ({share:.2f} of its duration)" if share is not None else "")
        + (f", played as a {summary['session_s']:.0f} s session" if split else "")
    )
    return "\n".join(lines)
