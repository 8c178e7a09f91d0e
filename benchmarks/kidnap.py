"""Benchmark: kidnapped robots in every bundled world (run on demand, not in CI).

Runs a live session of each ``*-events`` scenario (every one kidnaps a robot into an area another
robot maps) and prints, per kidnap: whether the robot was relocalized, the scans and seconds it
took (from the kidnap, and from when its view first overlapped the mapped area), and the pose
error afterwards; false relocalizations (> 1 m off) are counted. The targets: every kidnap
relocalized within (0.1 m, 2 deg) in at most 10 scans after the overlap, none false in the
warehouse.

    python benchmarks/kidnap.py [--scenarios department-events,office-events,warehouse-events] [--runs 5]
    python benchmarks/kidnap.py --write-results    # and write its result (benchmarks/results/)

A live run depends on how the machine shares its cores between the agents and the merger: with
``--runs N`` each scenario runs N times and the median and range of the scans are printed too.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from fleetmap.scenarios import load_scenario
from fleetmap.shared.config import FleetmapConfig
from results import markdown_table, write_result

from fleetmap.runner import Session

HEADER = ["scenario", "robot", "relocalized", "scans after kidnap", "scans after overlap", "seconds", "error", "false"]
EXPLAINED = (
    "A live session of each `*-events` scenario (`--runs` of each), one row per kidnap. Relocalized: the "
    "merger published a pose of the robot in an epoch begun after the kidnap, in the global map's largest "
    "component (the fleet's map); scans after kidnap and after overlap: its scans from the kidnap, and "
    "from when its view first overlapped the area another robot had mapped, to that pose; seconds: from "
    "the kidnap to that pose; error: that pose's, against the truth; "
    "false: more than 1 m off. Targets: every kidnap relocalized within (0.1 m, 2°) in at most 10 scans "
    "after the overlap, none false in the warehouse."
)


def table(rows: list[tuple[str, dict]]) -> str:
    """The printed table: one row per kidnap of the sessions' reports."""
    cells = []
    for name, k in rows:
        err = "–" if k["pose_error_m"] is None else f"{k['pose_error_m']:.3f} m, {k['pose_error_deg']:.2f}°"
        secs = "–" if k["seconds_to_relocalize"] is None else f"{k['seconds_to_relocalize']:.1f}"
        cells.append(
            [
                name,
                str(k["robot"]),
                str(k["relocalized"]),
                "–" if k["scans_to_relocalize"] is None else str(k["scans_to_relocalize"]),
                "–" if k["scans_after_overlap"] is None else str(k["scans_after_overlap"]),
                secs,
                err,
                str(k["false_relocalization"]),
            ]
        )
    return markdown_table(HEADER, cells)


def medians(rows: list[tuple[str, dict]], names: list[str]) -> list[str]:
    """Per scenario, the median and range of the scans after overlap over its relocalized kidnaps."""
    lines = []
    for name in names:
        scans = [k["scans_after_overlap"] for n, k in rows if n == name and k["scans_after_overlap"] is not None]
        if scans:
            lines.append(
                f"{name}: scans after overlap median {statistics.median(scans):g}, "
                f"{min(scans)}-{max(scans)} over {len(scans)} kidnaps relocalized"
            )
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default="department-events,office-events,warehouse-events")
    ap.add_argument("--speed", type=float, default=3.0)
    ap.add_argument("--runs", type=int, default=1, help="live sessions per scenario")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenarios.split(","):
            for run in range(args.runs):
                out = Path(tmp) / f"{name}-{run}"
                report = Session(load_scenario(name), out, FleetmapConfig(), speed=args.speed, progress=False).run()
                for k in report["kidnaps"]:
                    rows.append((name, k))
                    print(name, k, flush=True)
    text = table(rows)
    print()
    print(text)
    lines = medians(rows, args.scenarios.split(",")) if args.runs > 1 else []
    if args.runs > 1:
        print()
        for line in lines:
            print(line)
    if args.write_results:
        write_result(
            "kidnap",
            "Kidnapped robots (`benchmarks/kidnap.py`)",
            "\n\n".join([EXPLAINED, text, *lines]),
            config=FleetmapConfig(),
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
