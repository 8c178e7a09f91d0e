"""Key scans registered on the submaps they revisit: the placed scans refined after the merge.

The fleet pose graph (:mod:`fleetmap.merger.posegraph`) holds submaps as rigid nodes joined by
wall-to-wall integrations. A submap bends a little over its 10 m (2.7 cm median on fr079), and a
loop integration between two bent submaps' walls lands a few centimetres from where their scans
say (docs/decisions/002-pose-graph.md: "Where cross-robot relations miss"). Production back ends
constrain one scan, rigid by itself, to a submap instead (Cartographer's scan-to-submap
constraints; Hess et al. 2016, section V). Here, once the submap graph is solved:

- **Nodes** are key scans: the first scan each submap places and then one per
  :data:`SCAN_KEY_SPACING` metres (or :data:`SCAN_KEY_ROTATION`) of the robot's path.
- **Chain edges** join a robot's consecutive key scans by its tracking (their poses in their
  submaps, and the links between submaps), as uncertain as the tracking's drift over the distance
  between them (:func:`fleetmap.shared.core.tracking.drift_covariance`, the random walk a link's
  covariance adds up too).
- **Scan-to-submap edges**: every key scan is registered (:func:`fleetmap.shared.core.tracking.register`,
  the tracker's own point-to-line ICP) on the walls of each other submap of its component that
  has a key scan within :data:`SCAN_SEARCH_RADIUS` of it, its robot's own neighbouring submaps
  aside, starting from where the solved graph puts it. A fit that matches at least
  :data:`SCAN_MIN_MATCHED_SHARE` of the scan's walls, within :data:`SCAN_MAX_CORRECTION` of the start, is
  an edge from that submap's nearest key scan, weighed by how firmly the walls fix each
  direction, through a Cauchy loss.
- **Integrations** the graph kept stay, between key scans of their two submaps, for the pairs of
  submaps no scan-to-submap edge joins (a robot met once).
- All key scans are solved together (Levenberg-Marquardt over SE(2)), the component's anchor's
  first key scan fixed, every edge as a Gaussian first and then from there through its robust
  loss (as the submap graph is solved); a part of the graph that nothing joins to the anchor keeps
  its poses.

Every other scan follows the key scan before it in its submap, by its tracking. What it was
measured to do, and what it leaves: docs/decisions/002-pose-graph.md ("Key scans on the submaps
they revisit").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from fleetmap.merger.refinement import ROBUST_SCALE
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D, pose_information_in_own_frame
from fleetmap.shared.core.tracking import (
    SAMPLE_SPACING,
    VOXEL_SIZE,
    ReferenceMap,
    ScanSamples,
    drift_covariance,
    register,
    sample_segments,
)
from fleetmap.shared.io.keys import parse_submap_key
from scipy.spatial import cKDTree

_Noise = gtsam.noiseModel.Base

SCAN_CONSTRAINTS = True
"""Once the submaps are merged, key scans are registered on the submaps they revisit and every placed
scan's pose is refined with them (a scan is rigid; a submap bends a little): far relations within,
whole logs, aces 52.2 -> 87.8 %, mit-csail 77.5 -> 93.3 % (docs/decisions/002-pose-graph.md)."""
SCAN_KEY_SPACING = 1.0
"""A submap's next key scan is this far (m) along the robot's path from its last ..."""
SCAN_KEY_ROTATION = 0.35
"""... or turned this much from it (rad, 20 degrees); spacing 0.5 or 2 m: within a point (002)."""
SCAN_SEARCH_RADIUS = 2.0
"""A key scan is registered on every submap of its component with a key scan this near (m; 4 m:
within a point, 002) ..."""
SCAN_PRIOR_TRANSLATION = 0.3
"""... from where the merged submaps put it, as uncertain as this (m) ..."""
SCAN_PRIOR_ROTATION = 0.087
"""... and this (rad, 5 degrees), which is also the most the fit may turn it ..."""
SCAN_MAX_CORRECTION = 0.5
"""... and the most (m) it may move it (a scan farther off is not on that submap's walls) ..."""
SCAN_MIN_MATCHED_SHARE = 0.5
"""... and the fit must match at least this share of the scan's walls."""
MIN_STRETCH = 0.1
"""Chain edges shorter than this (m; a robot turning on the spot) drift as much as this length."""


@dataclass(frozen=True)
class KeyScan:
    """A scan the merger keeps to register on other submaps."""

    robot: str
    epoch: int
    index: int
    submap: str
    """The key ``<robot>/<epoch>/<submap>`` of the submap that placed it."""
    pose: Transform2D
    """Its laser pose in that submap's frame."""
    samples: ScanSamples
    """Points along its segments, in the laser's frame."""


@dataclass(frozen=True)
class IntegrationEdge:
    """An integration the solved graph kept: ``transform`` is b's frame in a's."""

    a: str
    b: str
    transform: Transform2D
    gaussian: gtsam.noiseModel.Base
    """How it weighs ..."""
    robust: gtsam.noiseModel.Base
    """... and the same through its robust loss."""


@dataclass
class ScanRefinement:
    poses: dict[tuple[str, int], Transform2D]
    """Each key scan's refined laser pose in the component's frame, by (robot, index)."""
    constraints: int = 0
    """Scan-to-submap edges found."""
    registrations: int = 0
    """Registrations tried."""


def is_key(last: Transform2D | None, pose: Transform2D) -> bool:
    """Whether a scan at ``pose`` (in its submap's frame) is a key scan, the submap's last key scan
    at ``last`` (None: it has none yet)."""
    if last is None:
        return True
    moved = math.hypot(pose.x - last.x, pose.y - last.y)
    turned = abs(math.remainder(pose.theta - last.theta, 2 * math.pi))
    return moved >= SCAN_KEY_SPACING or turned >= SCAN_KEY_ROTATION


def _pose2(t: Transform2D) -> gtsam.Pose2:
    return gtsam.Pose2(t.x, t.y, t.theta)


class _Factors:
    """The between-factors of the key scans' graph, and which scans they join (union-find)."""

    def __init__(self, n: int) -> None:
        self.factors: list[tuple[int, int, Transform2D, _Noise, _Noise]] = []
        self.parent = list(range(n))

    def root(self, i: int) -> int:
        parent = self.parent
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def add(self, i: int, j: int, between: Transform2D, gaussian: _Noise, robust: _Noise) -> None:
        self.factors.append((i, j, between, gaussian, robust))
        self.parent[self.root(i)] = self.root(j)


def refine_key_scans(
    keys: Sequence[KeyScan],
    submap_poses: Mapping[str, Transform2D],
    anchor: str,
    walls: Mapping[str, Array],
    links: Mapping[str, tuple[str, Transform2D]],
    integrations: Sequence[IntegrationEdge],
    tracking: TrackingParams,
) -> ScanRefinement:
    """The refined poses of one component's key scans (see the module docstring).

    ``keys``: the key scans of the component's submaps; ``submap_poses``: the solved submap poses in
    the component's frame, ``anchor`` its anchor; ``walls``: each submap's segments in its own frame;
    ``links``: by the later submap's key, (the earlier submap, its transform)."""
    keys = sorted((k for k in keys if k.submap in submap_poses), key=lambda k: (k.robot, k.epoch, k.index))
    if not keys:
        return ScanRefinement({})
    start = [submap_poses[k.submap].compose(k.pose) for k in keys]
    graph = _Factors(len(keys))

    # chain edges: consecutive key scans of an epoch, by the robot's tracking
    for i in range(len(keys) - 1):
        a, b = keys[i], keys[i + 1]
        if (a.robot, a.epoch) != (b.robot, b.epoch):
            continue
        between = _tracked(a, b, links)
        if between is None:
            continue
        length = max(math.hypot(between.x, between.y), MIN_STRETCH)
        chain = gtsam.noiseModel.Gaussian.Covariance(drift_covariance(length))
        graph.add(i, i + 1, between, chain, chain)

    out = ScanRefinement({})
    joined = _scan_to_submap_edges(keys, start, submap_poses, walls, tracking, graph, out)

    # the integrations of pairs no scan joins
    by_submap: dict[str, list[int]] = {}
    for i, k in enumerate(keys):
        by_submap.setdefault(k.submap, []).append(i)
    for e in integrations:
        if tuple(sorted((e.a, e.b))) in joined or e.a not in by_submap or e.b not in by_submap:
            continue
        i, j = by_submap[e.a][0], by_submap[e.b][0]
        between = keys[i].pose.inverse().compose(e.transform).compose(keys[j].pose)
        graph.add(i, j, between, e.gaussian, e.robust)

    held = [by_submap[anchor][0]] if anchor in by_submap else []
    fixed = {graph.root(i) for i in held}
    for i in range(len(keys)):  # a part nothing joins to the anchor keeps its poses
        if graph.root(i) not in fixed:
            held.append(i)
            fixed.add(graph.root(i))
    solved = _solved(start, held, graph.factors)
    for i, k in enumerate(keys):
        q = solved.atPose2(i)
        out.poses[(k.robot, k.index)] = Transform2D(q.x(), q.y(), q.theta())
    return out


def _scan_to_submap_edges(
    keys: list[KeyScan],
    start: list[Transform2D],
    submap_poses: Mapping[str, Transform2D],
    walls: Mapping[str, Array],
    tracking: TrackingParams,
    graph: _Factors,
    out: ScanRefinement,
) -> set[tuple[str, str]]:
    """Each key scan registered on the other submaps it lies in (not its chain neighbours), the
    fits kept as edges to their nearest key scan (counted in ``out``); the pairs of submaps joined."""
    positions = np.array([[p.x, p.y] for p in start])
    tree = cKDTree(positions)
    references: dict[str, ReferenceMap] = {}
    prior = np.diag([SCAN_PRIOR_TRANSLATION**-2, SCAN_PRIOR_TRANSLATION**-2, SCAN_PRIOR_ROTATION**-2])
    robust = gtsam.noiseModel.mEstimator.Cauchy.Create(ROBUST_SCALE)
    joined: set[tuple[str, str]] = set()
    for i, k in enumerate(keys):
        nearest: dict[str, tuple[float, int]] = {}
        for j in tree.query_ball_point(positions[i], SCAN_SEARCH_RADIUS):
            other = keys[j]
            if other.submap == k.submap or _neighbours(k.submap, other.submap):
                continue
            d = float(np.hypot(*(positions[j] - positions[i])))
            if other.submap not in nearest or (d, j) < nearest[other.submap]:
                nearest[other.submap] = (d, j)
        for submap in sorted(nearest):
            j = nearest[submap][1]
            reference = references.get(submap)
            if reference is None and submap not in walls:
                continue
            if reference is None:
                reference = references[submap] = ReferenceMap(VOXEL_SIZE)
                reference.insert(sample_segments(walls[submap], SAMPLE_SPACING))
            initial = submap_poses[submap].inverse().compose(start[i])
            fit = register(k.samples, reference, initial, initial, prior, tracking)
            out.registrations += 1
            correction = initial.inverse().compose(fit.pose)
            if (
                not fit.converged
                or fit.matched_share < SCAN_MIN_MATCHED_SHARE
                or math.hypot(correction.x, correction.y) > SCAN_MAX_CORRECTION
                or abs(correction.theta) > SCAN_PRIOR_ROTATION
            ):
                continue
            there = keys[j].pose  # the submap's key scan nearest to it, in the submap's frame
            information = pose_information_in_own_frame(fit.scan_information, fit.pose.theta) + np.eye(3) * 1e-6
            gaussian = gtsam.noiseModel.Gaussian.Information(information)
            graph.add(
                j, i, there.inverse().compose(fit.pose), gaussian, gtsam.noiseModel.Robust.Create(robust, gaussian)
            )
            joined.add(tuple(sorted((k.submap, submap))))  # type: ignore[arg-type]
            out.constraints += 1
    return joined


def _solved(
    start: list[Transform2D], held: list[int], factors: list[tuple[int, int, Transform2D, _Noise, _Noise]]
) -> gtsam.Values:
    """The key scans' poses (by number) that best fit the factors, the ``held`` scans where they start."""
    solved = gtsam.Values()
    for i, p in enumerate(start):
        solved.insert(i, _pose2(p))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-6)
    # a graduated non-convexity in its simplest form, as the submap graph's (refinement._optimized):
    # every edge as a Gaussian first, then from there with the Cauchy loss
    for with_loss in (False, True):
        graph = gtsam.NonlinearFactorGraph()
        for i in held:
            graph.add(gtsam.NonlinearEqualityPose2(i, _pose2(start[i])))
        for i, j, between, plain, loss in factors:
            graph.add(gtsam.BetweenFactorPose2(i, j, _pose2(between), loss if with_loss else plain))
        solved = gtsam.LevenbergMarquardtOptimizer(graph, solved, params).optimize()
    return solved


def _neighbours(a: str, b: str) -> bool:
    """Whether two submaps are one epoch's same or consecutive submaps (tracking relates them)."""
    ra, ea, na = parse_submap_key(a)
    rb, eb, nb = parse_submap_key(b)
    return (ra, ea) == (rb, eb) and abs((na or 0) - (nb or 0)) <= 1


def _chain(submap: str, links: Mapping[str, tuple[str, Transform2D]]) -> list[str]:
    """The submaps linked before ``submap``, nearest first, ``submap`` included."""
    out = [submap]
    while out[-1] in links:
        out.append(links[out[-1]][0])
    return out


def _tracked(a: KeyScan, b: KeyScan, links: Mapping[str, tuple[str, Transform2D]]) -> Transform2D | None:
    """b's laser pose in a's by the robot's tracking (None: no links join their submaps)."""
    if a.submap == b.submap:
        return a.pose.inverse().compose(b.pose)
    chain = _chain(b.submap, links)
    if a.submap not in chain:
        return None
    frame = Transform2D(0.0, 0.0, 0.0)  # b's submap's frame in a's submap's frame
    for later in chain[: chain.index(a.submap)]:
        frame = links[later][1].compose(frame)
    return a.pose.inverse().compose(frame).compose(b.pose)


def follow_key_scans(
    placed: Mapping[tuple[str, int], tuple[str, Transform2D]],
    keys: Sequence[KeyScan],
    refined: Mapping[tuple[str, int], Transform2D],
    submap_poses: Mapping[str, Transform2D],
) -> dict[tuple[str, int], Transform2D]:
    """Every placed scan's pose (``placed``: by (robot, index), its submap and its pose in the
    component's frame before the refinement) moved with the key scan before it in its submap (the
    first after it, for scans before a submap's first key scan); scans of a submap with no refined
    key scan keep theirs."""
    ordered: dict[str, list[KeyScan]] = {}
    for k in sorted(keys, key=lambda k: k.index):
        if (k.robot, k.index) in refined and k.submap in submap_poses:
            ordered.setdefault(k.submap, []).append(k)
    indices = {s: np.array([k.index for k in held]) for s, held in ordered.items()}
    out: dict[tuple[str, int], Transform2D] = {}
    for (robot, index), (submap, pose) in placed.items():
        held = ordered.get(submap)
        if not held:
            out[(robot, index)] = pose
            continue
        n = max(int(np.searchsorted(indices[submap], index, side="right")) - 1, 0)
        k = held[n]
        before = submap_poses[submap].compose(k.pose)
        out[(robot, index)] = refined[(k.robot, k.index)].compose(before.inverse().compose(pose))
    return out
