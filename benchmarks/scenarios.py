"""Benchmark: every bundled scenario scored against its ground truth (run on demand, not in CI).

1. **Laser**: milliseconds per 181-beam scan in each world (the scenario simulator's cost), against
   casting every beam on every wall.
2. **Integration**: every robot's scans are simulated and extracted; each pair of consecutive
   scans (same leg: not across a kidnap) is integrated with no prior (fleetmap.shared.core.integration)
   and compared with the true relative pose. A pair is *right* within (0.10 m, 2 deg). Pairs
   across a kidnap should all come out invalid.
3. **Merge** (:func:`merge_section`): the unknown-order merge of the robots' local maps with
   fleetmap.merger, scored with fleetmap.scenarios.metrics; skipped where it cannot be imported.

    python benchmarks/scenarios.py                          # everything
    python benchmarks/scenarios.py --scenarios department   # one scenario
    python benchmarks/scenarios.py --no-merge --heuristic consecutive
    python benchmarks/scenarios.py --write-results          # and write its result (benchmarks/results/)
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from fleetmap.scenarios.fleet import Scenario, plan
from fleetmap.scenarios.laser import LaserParams, cast_rays, true_ranges
from fleetmap.scenarios.loader import list_scenarios, load_scenario
from fleetmap.scenarios.metrics import map_error, pose_error, score_map, world_from_global
from fleetmap.scenarios.stream import SimulatedScan, robot_stream
from fleetmap.scenarios.truth import ground_truth
from fleetmap.scenarios.worlds import WORLDS, get_world
from fleetmap.shared.config import FleetmapConfig, IntegrationParams
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.integration import integrate
from fleetmap.shared.core.segmap import SegmentMap
from results import markdown_table, write_result

from fleetmap.config_args import add_config_arguments, config_from_args

RIGHT_TRANSLATION = 0.10
RIGHT_ROTATION_DEG = 2.0


@dataclass(frozen=True)
class ScanMap:
    truth: SimulatedScan
    map: SegmentMap


def laser_row(world_name: str, laser: LaserParams, repeats: int) -> list[str]:
    """One world's walls, its scans timed and their milliseconds (mean / max), both ways of casting."""
    world = get_world(world_name)
    poses = [
        (s.pose.x, s.pose.y, s.pose.theta)
        for name in list_scenarios()
        if (sc := load_scenario(name)).world.name == world_name
        for r in sc.robots
        for s in plan(sc, r.id)
    ]
    fast, full = [], []
    for pose in poses:
        start = time.perf_counter()
        for _ in range(repeats):
            true_ranges(world.walls, pose, laser)
        fast.append((time.perf_counter() - start) / repeats)
        start = time.perf_counter()
        for _ in range(repeats):
            cast_rays(world.walls, np.array(pose[:2]), laser.beam_angles() + pose[2])
        full.append((time.perf_counter() - start) / repeats)
    return [
        world_name,
        str(len(world.walls)),
        str(len(poses)),
        f"{1000 * np.mean(fast):.2f} / {1000 * max(fast):.2f} ms",
        f"{1000 * np.mean(full):.2f} / {1000 * max(full):.2f} ms",
    ]


def laser_section(repeats: int) -> str:
    """Milliseconds per scan in every world, at the poses the bundled scenarios drive: a paragraph and a table."""
    laser = LaserParams()
    rows = [laser_row(world_name, laser, repeats) for world_name in WORLDS]
    return (
        f"Laser: {laser.beams} beams, {laser.max_range:g} m: ms per scan at the scenarios' poses (mean / max),\n"
        "casting on the walls in reach (the simulator) and on every wall.\n\n"
        + markdown_table(["world", "walls", "scans timed", "walls in reach", "every wall"], rows)
    )


def simulate(sc: Scenario, config: FleetmapConfig) -> dict[str, list[ScanMap]]:
    out: dict[str, list[ScanMap]] = {}
    for r in sc.robots:
        out[r.id] = [
            ScanMap(s, SegmentMap(extract_segments(s.scan, config.extraction), ordered=True, oriented=True))
            for s in robot_stream(sc, r.id)
        ]
    return out


@dataclass(frozen=True)
class PairResult:
    right: bool
    valid: bool
    translation: float
    rotation_deg: float
    seconds: float
    across_kidnap: bool


def integration_section(scans: dict[str, list[ScanMap]], config: FleetmapConfig) -> list[PairResult]:
    """Every pair of consecutive scans of every robot, integrated and compared with the truth."""
    results = []
    for robot_scans in scans.values():
        for a, b in itertools.pairwise(robot_scans):
            if len(a.map) == 0 or len(b.map) == 0:
                continue
            r = integrate(a.map, b.map, config.integration)
            truth = a.truth.pose.inverse().compose(b.truth.pose)
            dt, dr = r.transform.distance(truth)
            right = dt < RIGHT_TRANSLATION and math.degrees(dr) < RIGHT_ROTATION_DEG
            results.append(PairResult(right, r.valid, dt, math.degrees(dr), r.seconds, a.truth.leg != b.truth.leg))
    return results


def integration_row(name: str, results: list[PairResult]) -> list[str]:
    same = [r for r in results if not r.across_kidnap]
    kidnap = [r for r in results if r.across_kidnap]
    right = [r for r in same if r.right]
    valid_right = sum(r.valid for r in right)
    valid_wrong = sum(r.valid and not r.right for r in same)
    errors = [(r.translation, r.rotation_deg) for r in right]
    med = (
        f"{100 * statistics.median(e[0] for e in errors):.1f} cm {statistics.median(e[1] for e in errors):.2f} deg"
        if errors
        else "-"
    )
    ms = 1000 * statistics.median(r.seconds for r in same) if same else math.nan
    kid = f"{sum(r.valid for r in kidnap)}/{len(kidnap)}" if kidnap else "-"
    return [
        name,
        str(len(same)),
        f"{100 * len(right) / max(len(same), 1):.0f} %",
        f"{100 * valid_right / max(len(same), 1):.0f} %",
        str(valid_wrong),
        med,
        f"{ms:.0f} ms",
        kid,
    ]


def local_maps(
    robot: str, robot_scans: list[ScanMap], config: FleetmapConfig, builder: Callable[[IntegrationParams], Any]
) -> list[tuple[str, ScanMap, SegmentMap]]:
    """A robot's local maps ``(robot/epoch, first scan, map)``: the pivot method over its scans,
    a new map when a scan does not integrate with the last one."""
    out: list[tuple[str, ScanMap, SegmentMap]] = []
    current, first = None, None
    for s in robot_scans:
        if len(s.map) == 0:
            continue
        if current is not None and current.add(s.map).pose is not None:
            continue
        if current is not None and first is not None:
            out.append((f"{robot}/{len(out)}", first, current.map))
        current, first = builder(config.integration), s
        current.add(s.map)
    if current is not None and first is not None:
        out.append((f"{robot}/{len(out)}", first, current.map))
    return out


def merge_section(sc: Scenario, scans: dict[str, list[ScanMap]], config: FleetmapConfig) -> list[str] | None:
    """The unknown-order merge of the robots' local maps, scored against the truth.

    Local maps as an agent builds them: the pivot method over a robot's scans, a new local map
    (epoch) when a scan does not integrate with the last one. A local map's frame is its first
    scan's, so that scan's true pose is the map's true pose. Returns a table row, or None when
    fleetmap.merger cannot be imported.
    """
    try:
        from fleetmap.merger.posegraph import PoseGraph
        from fleetmap.shared.core.pivotmap import PivotMapBuilder
    except ImportError:
        print("merge: not available yet")
        return None
    start = time.perf_counter()
    local = [m for robot, robot_scans in scans.items() for m in local_maps(robot, robot_scans, config, PivotMapBuilder)]
    true_pose = {key: first.truth.pose for key, first, _ in local}
    graph = PoseGraph(config.integration, config.merge)
    for key, _, m in sorted(local, key=lambda x: x[1].truth.stamp):
        graph.add_map(key, m)
    result = graph.solve()
    largest = result.components[0]
    world_global = world_from_global(true_pose[largest.anchor], largest.poses[largest.anchor])
    truth = ground_truth(sc)
    score = score_map(largest.segments, world_global, sc.world.walls, truth.visible)
    errors = [pose_error(largest.poses[k], true_pose[k], world_global) for k in largest.members]
    wrong = sum(e.translation_m > 0.3 or e.rotation_deg > 5.0 for e in errors)
    worst = max(errors, key=lambda e: e.translation_m)
    # The local maps themselves, each put at its true pose: what a perfect merge would score.
    at_truth = map_error(np.vstack([true_pose[k].apply(m.segments) for k, _, m in local]), sc.world.walls)
    return [
        sc.name,
        str(len(local)),
        f"{100 * at_truth.mean:.1f} cm",
        str(len(largest.members)),
        str(wrong),
        f"{100 * score.error.mean:.1f} cm",
        f"{100 * score.error.p95:.1f} cm",
        f"{100 * score.coverage:.0f} %",
        f"{100 * worst.translation_m:.1f} cm {worst.rotation_deg:.2f} deg",
        f"{time.perf_counter() - start:.0f} s",
    ]


TITLE = "Bundled scenarios against their ground truth (`benchmarks/scenarios.py`)"
INTEGRATION_HEADER = [
    "scenario",
    "pairs",
    "right",
    "right and valid",
    "valid but wrong",
    "median error (right)",
    "median time",
    "valid across a kidnap",
]
MERGE_HEADER = [
    "scenario",
    "local maps",
    "at true poses",
    "in largest",
    "wrong",
    "map error mean",
    "p95",
    "coverage",
    "worst pose",
    "time",
]


def tables(integration_rows: list[list[str]], merge_rows: list[list[str]], config: FleetmapConfig) -> str:
    """The integration table and (where the merge ran) the merge table, each after its paragraph."""
    text = (
        f"Consecutive scans integrated with no prior (heuristic {config.integration.heuristic}); right: within\n"
        f"({RIGHT_TRANSLATION} m, {RIGHT_ROTATION_DEG} deg) of the truth. Across a kidnap every pair should be "
        "invalid.\n\n" + markdown_table(INTEGRATION_HEADER, integration_rows)
    )
    if not merge_rows:
        return text
    return text + (
        "\n\nUnknown-order merge of the local maps (pivot method per robot, new map on a failed integration).\n"
        "At true poses: the mean error of the local maps each placed at its true pose (a perfect merge).\n"
        "Wrong: placed more than 0.3 m or 5 deg off. Error and coverage: the largest component.\n\n"
        + markdown_table(MERGE_HEADER, merge_rows)
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default=",".join(list_scenarios()), help="comma-separated (default: all bundled)")
    ap.add_argument("--laser-repeats", type=int, default=20, help="timing repeats per pose (0: skip the laser)")
    ap.add_argument("--no-merge", action="store_true", help="skip the merge section")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    add_config_arguments(ap, ["extraction", "integration", "merge"])
    args = ap.parse_args()
    config = config_from_args(args)
    laser = laser_section(args.laser_repeats) if args.laser_repeats > 0 else ""
    if laser:
        print(laser)
        print()
    integration_rows, merge_rows = [], []
    for name in args.scenarios.split(","):
        sc = load_scenario(name)
        start = time.perf_counter()
        scans = simulate(sc, config)
        results = integration_section(scans, config)
        integration_rows.append(integration_row(name, results))
        print(f"{name}: {len(results)} pairs in {time.perf_counter() - start:.0f} s", flush=True)
        if not args.no_merge:
            row = merge_section(sc, scans, config)
            if row is not None:
                merge_rows.append(row)
    text = tables(integration_rows, merge_rows, config)
    print()
    print(text)
    if args.write_results:
        write_result("scenarios", TITLE, "\n\n".join(t for t in (laser, text) if t), config=config)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
