"""Benchmark: the fleet with and without known start poses (run on demand, not in CI).

Dugarjav & Lee (2015) merge robots whose start poses are known from those poses, and align them
again where their maps meet; their score is the RMS distance of the merged map to the true map
(Table I). Each bundled scenario runs as ``benchmarks/offline.py`` runs it (every robot's agent on
its scans, their messages in stamp order through one merger, no processes or bus), the agents
once and the merger four times:

- **none**: no start poses (the paper's pose-free merge, fleetmap's default);
- **true**: every robot's true start pose (its first submap's frame in the world);
- **3 m off**: the same, with the second robot's start pose 3 m east of the truth;
- **3 m off, tight**: that, with ``start_pose_sigma_translation`` 0.1 m instead of the default.

Per run: the RMS and mean distance of the global map (the largest component, placed in the world
by its anchor's true pose) to the true walls, the robots placed, the maps placed more than 1 m or
10 degrees off (``maps_merged_wrongly``), the error of the second robot's first submap, and the
scenario second of the first global map that holds every robot's first epoch.

    python benchmarks/start_poses.py                      # every bundled scenario
    python benchmarks/start_poses.py office department
    python benchmarks/start_poses.py --write-results      # and write its result (benchmarks/results/)
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from typing import Any

import numpy as np
from fleetmap.scenarios import load_scenario
from fleetmap.scenarios.loader import list_scenarios
from fleetmap.scenarios.metrics import map_error, world_from_global
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.messages import LocalMap, Message
from offline import run_agents, run_merger
from results import markdown_table, write_result

from fleetmap.report import SessionLog, Truth, build_report, make_truth, true_frame

SHIFT_M = 3.0
TIGHT_M = 0.1


def true_start_poses(messages: list[tuple[float, int, Message]], truth: Truth) -> dict[str, Transform2D]:
    """Each robot's start pose in the world: the true laser pose of its first submap's frame scan."""
    out: dict[str, Transform2D] = {}
    for _, _, m in messages:
        if isinstance(m, LocalMap) and m.epoch == 0 and m.submap == 0 and m.frame_scan is not None:
            pose = truth.scan_pose(m.robot, m.frame_scan)
            if pose is not None:
                out.setdefault(m.robot, pose)
    return out


def placed_at(log: SessionLog, robots: list[str]) -> float | None:
    """The stamp of the first global map whose largest component holds every robot's first epoch."""
    for g in log.global_maps:
        if g.components and {f"{r}/0" for r in robots} <= {"/".join(k.split("/")[:2]) for k in g.components[0].members}:
            return g.stamp
    return None


def score(log: SessionLog, truth: Truth, robots: list[str], second: str) -> dict[str, Any]:
    """What a run is scored by (see the module docstring)."""
    report = build_report(log, truth)
    final = log.final
    rms = mean = math.nan
    if final is not None and final.components:
        main = final.components[0]
        true = true_frame(log, truth, main.anchor)
        if true is not None and len(main.segments):
            world = world_from_global(true, main.poses[main.anchor])
            err = map_error(world.apply(np.asarray(main.segments)), np.asarray(truth.scenario.world.walls))
            rms, mean = err.rms, err.mean
    first = report["maps"].get(f"{second}/0/0", {})
    return {
        "rms": rms,
        "mean": mean,
        "placed": f"{report['robots_placed']} / {report['robots_total']}",
        "wrong": len(report["maps_merged_wrongly"] or []),
        "second": first.get("error_m"),
        "all_at": placed_at(log, robots),
    }


def run(name: str, config: FleetmapConfig, step: float) -> list[list[str]]:
    scenario = load_scenario(name)
    truth = make_truth(scenario)
    assert truth is not None
    messages, _ = run_agents(name, scenario, config)
    robots = list(scenario.robot_ids)
    second = robots[1]
    true = true_start_poses(messages, truth)
    off = dict(true)
    off[second] = Transform2D(SHIFT_M, 0.0, 0.0).compose(true[second])
    tight = replace(config, merge=replace(config.merge, start_pose_sigma_translation=TIGHT_M))
    runs: list[tuple[str, FleetmapConfig, dict[str, Transform2D] | None]] = [
        ("none", config, None),
        ("true", config, true),
        (f"{SHIFT_M:g} m off", config, off),
        (f"{SHIFT_M:g} m off, tight ({TIGHT_M:g} m)", tight, off),
    ]
    rows = []
    for label, c, poses in runs:
        log, seconds = run_merger(list(messages), c, step, poses)
        s = score(log, truth, robots, second)
        at = "never" if s["all_at"] is None else f"{s['all_at']:.1f} s"
        err = "-" if s["second"] is None else f"{s['second']:.3f} m"
        row = [name, label, f"{s['rms']:.3f} m", f"{s['mean']:.3f} m", s["placed"], str(s["wrong"]), err, at]
        rows.append([*row, f"{seconds:.1f} s"])
        print(" | ".join(rows[-1]), flush=True)
    return rows


HEADER = [
    "scenario",
    "start poses",
    "map RMS",
    "mean",
    "robots placed",
    "maps merged wrongly",
    "second robot's first submap off by",
    "every robot in the global map at",
    "merger",
]
EXPLAINED = (
    "Dugarjav & Lee's score, the RMS distance of the merged map to the true walls, on every bundled scenario "
    "without and with known start poses (each robot's first submap's true frame; then the second robot's 3 m "
    f"east of it, with the default `start_pose_sigma_translation` and with {TIGHT_M:g} m). The agents run once "
    "per scenario, the merger once per row, as `benchmarks/offline.py` runs them. *Every robot in the global map "
    "at*: the scenario second of the first global map whose largest component holds every robot's first epoch."
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="*", help=f"bundled names (default: all of {', '.join(list_scenarios())})")
    ap.add_argument("--step", type=float, default=1.0, help="scenario seconds between merger steps")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = ap.parse_args()
    config = FleetmapConfig()
    rows = [row for name in args.scenarios or list_scenarios() for row in run(name, config, args.step)]
    table = markdown_table(HEADER, rows)
    print(table)
    if args.write_results:
        write_result(
            "start_poses",
            "Known start poses (`benchmarks/start_poses.py`)",
            EXPLAINED + "\n\n" + table,
            config=config,
            varied=[f"merge.start_pose_sigma_translation={config.merge.start_pose_sigma_translation:g},{TIGHT_M:g}"],
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
