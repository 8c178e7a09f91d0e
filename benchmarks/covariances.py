"""Benchmark: are the pose graph's uncertainties honest, and do the integrations that agree tell right from wrong?

Each corrected log (``../shared/data/corrected``: poses a SLAM system corrected, given to no
algorithm) is mapped as ``fleetmap map LOG --split K`` maps it; then, against the corrected poses
(each submap's true frame its frame scan's corrected pose):

- **links**: each robot's link between consecutive submaps, its error normalised by the link's
  covariance (the tracking's). Honest covariances give a chi-square with three degrees of freedom:
  median 2.37, 99 % within 11.34;
- **integrations**: every valid integration between two robots' submaps, wrong where it is more
  than 1 m or 10 degrees off (issue 49's bound), and the right ones' errors normalised by the
  cycle tolerance (its base, 0.30 m and 5 degrees, as three standard deviations: what
  ``merger/consistency.py`` takes), by the refinement's information (``merger/refinement.py``), and
  by that information's covariance plus half of each submap's tracking drift over its way (what
  docs/decisions/055 found honest, and the merger does not weigh by yet);
- **consistent sets**: for each two robots, the integrations between them, which pairs agree
  through the robots' links (``merger/consistency.py``), and whether the heaviest set that agrees
  holds a wrong integration.

    python benchmarks/covariances.py [--logs aces,csail,...] [--splits 4,8] [--write-results]
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import networkx as nx
import numpy as np
from fleetmap.merger.consistency import CONSISTENT_CHI2
from fleetmap.merger.executor import make_executor
from fleetmap.merger.forest import RootedForest
from fleetmap.merger.graph import EDGE_SIGMA_ROTATION, EDGE_SIGMA_TRANSLATION, Edge
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.refinement import ISOTROPIC_SHARE
from fleetmap.shared.core.geometry import Transform2D, wrap_scalar
from fleetmap.shared.core.mapgrid import viewpoints_of
from fleetmap.shared.core.tracking import drift_covariance
from fleetmap.shared.io.logs import read_carmen
from results import markdown_table, write_result
from tracking import CORRECTED, data_folder
from wrong_relations import frame_truth

from fleetmap.config_args import preset
from fleetmap.mapping import map_logs, read_inputs

HEADER = [
    "log",
    "K",
    "links",
    "link NEES median / within 99 %",
    "cross integrations (wrong)",
    "right NEES, cycle tolerance",
    "right NEES, refinement's information",
    "right NEES, the same plus half each submap's drift",
    "robot pairs",
    "heaviest set holds a wrong one",
]


def _error(estimate: Transform2D, truth: Transform2D) -> np.ndarray:
    return np.array([estimate.x - truth.x, estimate.y - truth.y, wrap_scalar(estimate.theta - truth.theta)])


def _nees(r: np.ndarray, cov: np.ndarray) -> float:
    return float(r @ np.linalg.solve(cov, r))


def _information_cov(e: Edge) -> np.ndarray:
    """The covariance the refinement weighs an integration by (``Refinement.edge_noise``, in a's frame)."""
    w = max(e.value, 1e-3)
    iso = np.diag([w / EDGE_SIGMA_TRANSLATION**2, w / EDGE_SIGMA_TRANSLATION**2, w / EDGE_SIGMA_ROTATION**2])
    info = ISOTROPIC_SHARE * iso
    if e.information is not None:
        given = np.asarray(e.information).reshape(3, 3) / EDGE_SIGMA_TRANSLATION**2 + info
        if np.isfinite(given).all() and np.linalg.eigvalsh(given).min() > 0:
            info = given
    return np.linalg.inv(info)


def _drift_cov(e: Edge, graph: PoseGraph) -> np.ndarray:
    """The refinement's covariance plus half of each submap's tracking drift over the way of its
    viewpoints: what its walls may be bent by (docs/decisions/055; not what the merger weighs by)."""

    def way(key: str) -> float:
        vp = viewpoints_of(graph._nodes[key].map)
        return float(np.hypot(*np.diff(vp[:, 0:2], axis=0).T).sum()) if len(vp) > 1 else 0.0

    return _information_cov(e) + 0.5 * (drift_covariance(way(e.a)) + drift_covariance(way(e.b)))


def _chain(key: str) -> str:
    return key.rsplit("/", 1)[0]


def run(job: tuple[str, int, Path]) -> list[str]:
    name, split, data = job
    path = data / "corrected" / f"{name}-corrected.log.gz"
    truth = [Transform2D(*s.odometry) for s in read_carmen(path) if s.odometry is not None]
    executor = make_executor("local")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            result = map_logs(read_inputs([str(path)], split), Path(tmp) / "out", preset("offline"), executor=executor)
    finally:
        executor.close()
    merger = result.merger
    assert merger is not None
    graph = merger.graph
    frames = {key: frame_truth(m, truth) for key, m in merger.submaps.items()}
    at = {key: t for key, t in frames.items() if t is not None}  # each submap's frame: its frame scan's truth
    links = [e for e in graph.links if e.a in at and e.b in at]
    covariances = graph._link_covariances
    link_nees = [_nees(_error(e.transform, at[e.a].inverse().compose(at[e.b])), covariances[(e.a, e.b)]) for e in links]
    base_t, base_r = graph._tolerance(1)
    cycle_cov = np.diag([(base_t / 3) ** 2, (base_t / 3) ** 2, (base_r / 3) ** 2])
    by_pair: dict[tuple[str, str], list[tuple[Edge, bool]]] = defaultdict(list)
    right_cycle, right_information, right_drift = [], [], []
    for e in graph.edges:
        if e.link or not e.valid or e.a not in at or e.b not in at or _chain(e.a) == _chain(e.b):
            continue
        r = _error(e.transform, at[e.a].inverse().compose(at[e.b]))
        wrong = math.hypot(r[0], r[1]) > 1.0 or abs(r[2]) > math.radians(10.0)
        if not wrong:
            right_cycle.append(_nees(r, cycle_cov))
            right_information.append(_nees(r, _information_cov(e)))
            right_drift.append(_nees(r, _drift_cov(e, graph)))
        f = e if _chain(e.a) < _chain(e.b) else e.reversed()
        by_pair[(_chain(f.a), _chain(f.b))].append((f, wrong))
    adjacency: dict[str, list[Edge]] = {k: [] for k in graph.keys}
    for e in graph.links:
        adjacency[e.a].append(e)
        adjacency[e.b].append(e.reversed())
    forest = RootedForest(graph.keys, adjacency, covariances)
    held_wrong = 0
    for candidates in by_pair.values():
        consistent = nx.Graph()
        consistent.add_nodes_from(range(len(candidates)))
        for i, (f, _) in enumerate(candidates):
            implied = forest.at[f.a].compose(f.transform).compose(forest.at[f.b].inverse())
            for j in range(i + 1, len(candidates)):
                g = candidates[j][0]
                same_trees = forest.root[g.a] == forest.root[f.a] and forest.root[g.b] == forest.root[f.b]
                if same_trees and graph._agree(f, g, implied, forest):
                    consistent.add_edge(i, j)
        chosen = max(nx.find_cliques(consistent), key=lambda c: sum(candidates[i][0].value for i in c))
        held_wrong += len(chosen) > 1 and any(candidates[i][1] for i in chosen)
    wrong = sum(w for c in by_pair.values() for _, w in c)

    def median(xs: list[float]) -> str:
        return f"{statistics.median(xs):.2f}" if xs else "-"

    within = sum(x <= CONSISTENT_CHI2 for x in link_nees) / len(link_nees) if link_nees else math.nan
    return [
        name,
        str(split),
        str(len(links)),
        f"{median(link_nees)} / {100 * within:.0f} %",
        f"{sum(len(c) for c in by_pair.values())} ({wrong})",
        median(right_cycle),
        median(right_information),
        median(right_drift),
        str(len(by_pair)),
        str(held_wrong),
    ]


def rows_by_log(
    doc: str, splits: str, run_one: Callable[[tuple[str, int, Path]], list[str]]
) -> tuple[list[list[str]], bool]:
    """The command line of a benchmark over the corrected logs cut in K (``--logs``, ``--splits``,
    ``--workers``, ``--write-results``; ``splits`` the default K): each log and K's row from
    ``run_one((name, K, data folder))``, in order, and whether to write the result."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", default=",".join(CORRECTED), help="corrected logs (comma-separated)")
    ap.add_argument("--splits", default=splits, help="values of K (comma-separated)")
    ap.add_argument("--workers", type=int, default=2, help="maps at once (default 2)")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = ap.parse_args()
    names = [n for n in args.logs.split(",") if n]
    unknown = [n for n in names if n not in CORRECTED]
    if unknown:
        raise SystemExit(f"unknown corrected log {unknown[0]!r} (known: {', '.join(CORRECTED)})")
    data = data_folder()
    jobs = [(n, int(k), data) for n in names for k in args.splits.split(",")]
    with ProcessPoolExecutor(args.workers) as pool:
        return list(pool.map(run_one, jobs)), args.write_results


def main() -> int:
    rows, write = rows_by_log(__doc__ or "", "4,8", run)
    table = markdown_table(HEADER, rows)
    print(table)
    if write:
        body = (
            "Errors against the corrected poses, normalised: a chi-square with three degrees of freedom "
            "has median 2.37 and 99 % within 11.34. Wrong: more than 1 m or 10 degrees off.\n\n" + table
        )
        write_result(
            "covariances",
            "Uncertainties and consistent sets (`benchmarks/covariances.py`)",
            body,
            config=preset("offline"),
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
