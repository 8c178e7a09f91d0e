"""Benchmark: the global map's walls fused unweighted and weighted (run on demand, not in CI).

The paper's Algorithm 5 fuses the copies of a wall that several submaps see by their length;
Ballesta et al. (2009, Section 4) weigh each copy by its covariance (``[merge] wall_fusion =
"weighted"``: its submap's pose covariance in the solved graph and its segment fit). Two scores,
each fusion against the other:

- **scenarios**: every bundled scenario as ``benchmarks/offline.py`` runs it (the agents once, the
  merger once per fusion, a step, and the walls fused, every scenario second, as live); the RMS and
  mean distance of the global map (the largest component, placed in the world by its anchor's true
  pose) to the true walls, Dugarjav & Lee's score, and the seconds the fusion took: in all the
  steps, and the most one step took;
- **real logs** (``--logs``): ``fleetmap map LOG`` in this process, and the final graph's largest
  component fused both ways (the same graph: only the walls differ); its walls' length, the length
  of wall with a parallel copy facing the same way less than ``THICK_M`` away beside it (a wall
  drawn twice: a thick wall), and the seconds of that final fusion.

    python benchmarks/fusion.py                              # the scenarios
    python benchmarks/fusion.py --logs aces,fr079,mit-csail  # and the real logs ($FLEETMAP_DATA)
    python benchmarks/fusion.py --logs aces,fr079,mit-csail --write-results
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from fleetmap.merger import engine, posegraph
from fleetmap.scenarios import load_scenario
from fleetmap.scenarios.loader import list_scenarios
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Array
from offline import run_agents, run_merger
from results import markdown_table, write_result
from start_poses import score

from fleetmap import cli
from fleetmap.report import make_truth

FUSIONS = ("unweighted", "weighted")
THICK_M = 0.2
"""Two parallel copies of one wall closer than this (m) draw it thick."""
PARALLEL_RAD = 0.1
"""Copies within this of one direction (rad) are parallel (``WallMap``'s angle tolerance)."""
NO_RETURN = {"aces": "50", "fr079": "81.91"}
"""The logs' no-return readings (README)."""


class FusionClock:
    """The seconds :meth:`PoseGraph._walls` takes, per call (timing wrapped round the method)."""

    def __init__(self) -> None:
        self.calls: list[float] = []
        self._walls: Callable[..., Array] = posegraph.PoseGraph._walls

    def __enter__(self) -> FusionClock:
        walls = self._walls

        def timed(graph: posegraph.PoseGraph, *args: Any) -> Array:
            t0 = time.perf_counter()
            out = walls(graph, *args)
            self.calls.append(time.perf_counter() - t0)
            return out

        posegraph.PoseGraph._walls = timed  # type: ignore[method-assign]
        return self

    def __exit__(self, *_: object) -> None:
        posegraph.PoseGraph._walls = self._walls  # type: ignore[method-assign]


def thick_length(segments: Array) -> float:
    """The length (m) of ``segments`` with a parallel copy facing the same way less than
    ``THICK_M`` away beside it (overlapping along it), each segment's covered stretch counted once."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    u = (seg[:, 2:4] - seg[:, 0:2]) / np.maximum(length, 1e-12)[:, None]
    total = 0.0
    for i in range(len(seg)):
        a, d = seg[i, 0:2], u[i]
        near = (u @ d >= math.cos(PARALLEL_RAD)) & (np.arange(len(seg)) != i)
        if not near.any():
            continue
        ends = np.stack([seg[near, 0:2], seg[near, 2:4]], axis=1) - a  # (k, 2, 2)
        along = ends @ d
        across = ends @ np.array([-d[1], d[0]])
        beside = (np.abs(across) < THICK_M).all(axis=1)
        lo = np.clip(along.min(axis=1), 0.0, length[i])[beside]
        hi = np.clip(along.max(axis=1), 0.0, length[i])[beside]
        covered, reach = 0.0, 0.0
        for start, stop in sorted(zip(lo.tolist(), hi.tolist(), strict=True)):
            start = max(start, reach)
            if stop > start:
                covered += stop - start
                reach = stop
        total += covered
    return total


def scenario_rows(name: str, config: FleetmapConfig) -> list[list[str]]:
    scenario = load_scenario(name)
    truth = make_truth(scenario)
    assert truth is not None
    messages, _ = run_agents(name, scenario, config)
    robots = list(scenario.robot_ids)
    rows = []
    for fusion in FUSIONS:
        c = replace(config, merge=replace(config.merge, wall_fusion=fusion))
        with FusionClock() as clock:
            log, seconds = run_merger(list(messages), c, 1.0)
        s = score(log, truth, robots, robots[1])
        rows.append(
            [
                name,
                fusion,
                f"{s['rms']:.4f} m",
                f"{s['mean']:.4f} m",
                s["placed"],
                str(s["wrong"]),
                f"{sum(clock.calls):.2f} s",
                f"{1000 * max(clock.calls, default=0.0):.0f} ms",
                f"{seconds:.1f} s",
            ]
        )
        print(" | ".join(rows[-1]), flush=True)
    return rows


def log_rows(name: str, data: Path, config: FleetmapConfig) -> list[list[str]]:
    """``fleetmap map LOG`` in this process, its final graph's largest component fused both ways."""
    mergers: list[engine.Merger] = []
    made = engine.Merger

    class Kept(made):  # type: ignore[misc, valid-type]
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            mergers.append(self)

    import fleetmap.mapping as mapping

    mapping.Merger = Kept  # type: ignore[misc]
    try:
        with tempfile.TemporaryDirectory() as out:
            extra = ["--no-return-reading", NO_RETURN[name]] if name in NO_RETURN else []
            args = ["map", str(data / name / f"{name}.clf.gz"), "--out", out, "--no-progress", *extra]
            assert cli.main(args) == 0
    finally:
        mapping.Merger = made  # type: ignore[misc]
    graph = mergers[-1].graph
    rows = []
    for fusion in FUSIONS:
        graph.merge = replace(config.merge, wall_fusion=fusion)
        graph._walls_now = {}  # nothing held from the last fusion
        with FusionClock() as clock:
            walls = np.asarray(graph.solve().components[0].segments)
        total = float(np.hypot(walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1]).sum())
        thick = thick_length(walls)
        rows.append(
            [
                name,
                fusion,
                str(len(walls)),
                f"{total:.0f} m",
                f"{thick:.0f} m ({100 * thick / total:.1f} %)",
                f"{1000 * sum(clock.calls):.0f} ms",
            ]
        )
        print(" | ".join(rows[-1]), flush=True)
    return rows


SCENARIO_HEADER = [
    "scenario",
    "fusion",
    "map RMS",
    "mean",
    "robots placed",
    "maps merged wrongly",
    "fusion, all steps",
    "slowest step's fusion",
    "merger",
]
LOG_HEADER = ["log", "fusion", "walls", "wall length", f"with a copy < {THICK_M:g} m beside it", "final fusion"]
EXPLAINED = (
    "The global map's walls fused by the paper's Algorithm 5 (each copy of a wall by its length) and weighted "
    'as Ballesta et al. (2009, Section 4) fuse landmarks (`[merge] wall_fusion = "weighted"`: each copy also '
    "by its submap's pose covariance in the solved graph and its segment fit; docs/decisions/012). Scenarios: "
    "the agents once per scenario, the merger once per fusion, as `benchmarks/offline.py` runs them (a step, "
    "walls fused, every scenario second); the RMS and mean distance of the global map to the true walls "
    "(placed by its anchor's true pose), and the seconds spent fusing walls."
)
LOGS_EXPLAINED = (
    "Real logs: `fleetmap map LOG` once, its final graph's largest component fused both ways (the same poses: "
    f"only the walls differ); the length of wall with a parallel copy facing the same way less than {THICK_M:g} m "
    "beside it (a wall drawn thick), and the seconds of that final fusion."
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="*", help=f"bundled names (default: all of {', '.join(list_scenarios())})")
    ap.add_argument("--logs", default="", help="comma-separated logs under $FLEETMAP_DATA (aces,fr079,mit-csail)")
    ap.add_argument("--no-scenarios", action="store_true", help="the real logs only")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = ap.parse_args()
    config = FleetmapConfig()
    text = EXPLAINED
    if not args.no_scenarios:
        rows = [row for name in args.scenarios or list_scenarios() for row in scenario_rows(name, config)]
        text += "\n\n" + markdown_table(SCENARIO_HEADER, rows)
    if args.logs:
        data = Path(os.environ.get("FLEETMAP_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
        rows = [row for name in args.logs.split(",") for row in log_rows(name, data, config)]
        text += "\n\n" + LOGS_EXPLAINED + "\n\n" + markdown_table(LOG_HEADER, rows)
    print(text)
    if args.write_results:
        write_result(
            "fusion",
            "Uncertainty-weighted wall fusion (`benchmarks/fusion.py`)",
            text,
            config=config,
            varied=[f"merge.wall_fusion={','.join(FUSIONS)}"],
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
