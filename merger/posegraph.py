"""The fleet's pose graph: submaps chained by each robot's tracking, joined by the paper's integrations.

Nodes are submaps (``<robot>/<epoch>/<submap>``). Edges are of two kinds:

- **links**: a robot's own chain of consecutive submaps, measured by its tracking, with the
  tracking's covariance (:class:`~fleetmap.shared.io.messages.SubmapLink`); never rejected;
- **integrations**: the paper's pose-free integration (Algorithms 1-4) between submaps of
  different robots, or non-consecutive submaps of one robot (a loop), or, for a submap the fleet
  has placed, its walls registered near where the graph predicts them
  (:func:`~fleetmap.shared.core.integration.align_near`); each with its transformation value, validity
  and how firmly its walls fix it.

The merge order nobody gave is read off the graph: a maximum spanning forest (links first, then
valid integrations by value), every other valid integration checked against its cycle, a tree
integration that more cycles accuse than support rejected. Map files (``fleetmap merge``) are
nodes with no links, solved the same way. The
cycle check allows what the path can have drifted: the base tolerance for each integration on the
path, and three standard deviations of what its links' covariances add up to, so a long loop of a
robot's own submaps closes and a wrong match across a room does not. Each component's poses are
then refined together by robust least squares over SE(2) (GTSAM's Levenberg-Marquardt: links as
their covariance says, integrations through a Cauchy loss, the anchor fixed), and an integration
that still disagrees with the refined poses by more than one integration's base tolerance (no
drift term: the refined poses already spread the drift) is rejected and the
component solved again: only edges that agree with the graph count, so one wrong integration cannot
move a map. Each component is one global map; its walls are the submaps' fused one segment per
stretch of wall (:class:`~fleetmap.shared.core.walls.WallMap`).

How a join of two groups is judged, and the robots' links it is judged through, is
:mod:`fleetmap.merger.joins`; the forest's paths and their drift, :mod:`fleetmap.merger.forest`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import replace

import gtsam
import numpy as np
from fleetmap.merger.forest import RootedForest
from fleetmap.merger.graph import (
    Component,
    Edge,
    MergeResult,
    _bfs_order,
    _culprit,
    _disagreement,
    _unite,
)
from fleetmap.merger.joins import JoinJudge, _chain_of, _map_file, _within
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D, pose_information_in_own_frame
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.validity import is_valid
from fleetmap.shared.core.walls import WallMap

log = logging.getLogger(__name__)


def _tree_poses(keys: Iterable[str], adjacency: dict[str, list[Edge]]) -> dict[str, Transform2D]:
    """Every node's pose in its tree's frame (the first key of each tree at the origin)."""
    poses: dict[str, Transform2D] = {}
    for start in keys:
        if start in poses:
            continue
        poses[start] = Transform2D.identity()
        for k in _bfs_order(adjacency, start):
            for t in adjacency[k]:
                if t.b not in poses:
                    poses[t.b] = poses[k].compose(t.transform)
    return poses


def _pose2(t: Transform2D) -> gtsam.Pose2:
    return gtsam.Pose2(t.x, t.y, t.theta)


def _transform(p: gtsam.Pose2) -> Transform2D:
    return Transform2D.from_array((p.x(), p.y(), p.theta()))


def _joins_above(anchor: str, order: list[str], adjacency: dict[str, list[Edge]]) -> dict[str, tuple[object, ...]]:
    """For each submap of a component, the integrations (not the links) on its spanning-tree path
    from the anchor, each as its two submaps and its transform."""
    paths: dict[str, tuple[object, ...]] = {anchor: ()}
    for k in order:
        for e in adjacency[k]:
            if e.b not in paths:
                paths[e.b] = paths[k] if e.link else (*paths[k], (e.a, e.b, *e.transform.as_array().tolist()))
    return paths


class PoseGraph(JoinJudge):
    """Submaps, their links and their integrations; :meth:`solve` gives the global maps."""

    def __init__(
        self,
        integration: IntegrationParams | None = None,
        merge: MergeParams | None = None,
        tracking: TrackingParams | None = None,
        anchor: str = "first",
    ) -> None:
        super().__init__(integration, merge, tracking, anchor)
        self._solution: dict[str, tuple[str, tuple[object, ...], Transform2D]] = {}
        """The last solve's pose of every placed node, with its component's anchor (a warm start)."""
        self._walls_now: dict[tuple[object, ...], tuple[tuple[SegmentMap, ...], Array]] = {}
        """The walls of each component of the last solve, with its maps (:meth:`_walls`)."""
        self._last_walls = self._walls_now
        self._refined_now: dict[tuple[object, ...], tuple[dict[str, Transform2D], list[Edge]]] = {}
        """Each component's refined poses and the edges they disagree with, by its anchor, members
        and edges, from the last solve (:meth:`_refined_components`)."""
        self._last_refined = self._refined_now

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._solution.pop(key, None)

    def _work(self, key: str, m: SegmentMap) -> SegmentMap:
        # a submap's walls are already one segment per stretch of wall (fleetmap.shared.core.walls);
        # a map file (a pivot local map: many short pieces of each wall) is simplified as the map
        # graph simplifies it
        return super()._work(key, m) if _map_file(key) else m

    def solve(self, fuse_maps: bool = True) -> MergeResult:
        links = [e for e in self._links.values() if e.a in self._nodes and e.b in self._nodes]
        # the links between two robots' first submaps (their known start poses,
        # fleetmap.merger.startposes) are the forest's weakest edges: it takes every integration
        # first, so that a join of two robots is judged as any join is, and a start pose only
        # unites what no integration joins (else it closes a cycle, and weighs in the refinement)
        priors = [e for e in links if _robot_of(e.a) != _robot_of(e.b)]
        links = [e for e in links if _robot_of(e.a) == _robot_of(e.b)]
        order = {k: n.order for k, n in self._nodes.items()}
        valid = [e for e in self._edges.values() if e.valid or self._ambiguous(e)]
        valid.sort(key=lambda e: (-e.value, order[e.a], order[e.b]))
        disagreeing: set[tuple[str, str]] = set()
        self._last_walls, self._walls_now = self._walls_now, {}
        self._last_refined, self._refined_now = self._refined_now, {}
        for _ in range(self.merge.max_rejection_rounds):
            tree, loops, rejected = self._forest(links, [e for e in valid if e.key() not in disagreeing], priors)
            components, off = self._refined_components(tree, loops)
            if not off:
                break
            for e in off:
                log.debug("rejecting edge %s-%s: the refined poses disagree with it", e.a, e.b)
            disagreeing.update(e.key() for e in off)
        rejected += [e for e in valid if e.key() in disagreeing and e.valid]
        if fuse_maps:  # the walls of the final round's components only
            components = [replace(c, segments=self._walls(list(c.members), c.poses)) for c in components]
        poses: dict[str, Transform2D | None] = {k: None for k in self.keys}
        for c in components:
            if len(c.members) > 1:
                poses.update(c.poses)
        return MergeResult(poses, components, tree, loops, rejected)

    def _forest(
        self, links: list[Edge], valid: list[Edge], priors: Sequence[Edge] = ()
    ) -> tuple[list[Edge], list[Edge], list[Edge]]:
        """The spanning forest (links first, ``priors`` last), its loop closures, and the integrations rejected: by
        the cycle check, by the culprit rule (:meth:`_culprit`), and joins that the two groups they
        join do not bear out once the forest is whole (:meth:`_join_holds` on the two sides of the
        tree edge: the forest is built greedily, and a join checked when its groups were small
        may fail against what later joined them)."""
        excluded: set[tuple[str, str]] = set()
        while True:
            tree, loops, conflicts, adjacency, forest = self._kruskal(
                [*links, *(e for e in valid if e.key() not in excluded), *priors]
            )
            culprit = self._culprit(tree, loops, conflicts, adjacency, forest)
            if culprit is None:
                culprit = self._failed_join(tree, adjacency)
                if culprit is not None:
                    log.debug("rejecting edge %s-%s: the maps it joins do not bear it out", culprit.a, culprit.b)
            elif culprit is not None:
                log.debug("rejecting edge %s-%s: the cycles through it disagree", culprit.a, culprit.b)
            if culprit is None:
                break
            excluded.add(culprit.key())
        rejected = conflicts + [e for e in valid if e.key() in excluded]
        return tree, loops, rejected

    def _culprit(
        self,
        tree: list[Edge],
        loops: list[Edge],
        conflicts: list[Edge],
        adjacency: dict[str, list[Edge]],
        forest: RootedForest,
    ) -> Edge | None:
        """The tree integration that more cycles accuse than support (:func:`~fleetmap.merger.graph._culprit`), counting
        only the accusers that the maps they would join bear out: cut the accused edge, and an
        accuser joins its two sides; if :meth:`_join_holds` says the two sides do not bear it out,
        it is no evidence against anything. Two submaps of one robot's chain overlap, so one wrong
        match of a third submap on both is two accusers that agree with each other, and they
        would outvote the one right integration they contradict."""
        joins = [t for t in tree if not t.link]
        void: set[tuple[str, str]] = set()
        poses: dict[str, Transform2D] | None = None
        while True:
            heard = [e for e in conflicts if e.key() not in void]
            culprit = _culprit(joins, loops, heard, forest.path_keys)
            if culprit is None:
                return None
            if poses is None:
                poses = _tree_poses(self.keys, adjacency)
            side_b = set(_bfs_order(adjacency, culprit.b, cut=culprit.key()))
            side_a = [k for k in _bfs_order(adjacency, culprit.a) if k not in side_b]
            voided = False
            for e in heard:
                if culprit.key() not in forest.path_keys(e.a, e.b):
                    continue
                accuser = e if e.a not in side_b else e.reversed()
                if not self._join_holds(accuser, side_a, sorted(side_b), poses, adjacency):
                    log.debug(
                        "edge %s-%s accuses %s-%s, but the maps it joins do not bear it out",
                        e.a,
                        e.b,
                        culprit.a,
                        culprit.b,
                    )
                    void.add(e.key())
                    voided = True
            if not voided:
                return culprit

    def _failed_join(self, tree: list[Edge], adjacency: dict[str, list[Edge]]) -> Edge | None:
        """The weakest integration of the forest whose two sides do not bear it out, if any."""
        joins = sorted((e for e in tree if not e.link), key=lambda e: (e.value, e.key()))
        if not joins:
            return None
        poses = _tree_poses(self.keys, adjacency)
        for e in joins:
            side_b = set(_bfs_order(adjacency, e.b, cut=e.key()))
            side_a = [k for k in _bfs_order(adjacency, e.a) if k not in side_b]
            if not self._join_holds(e, side_a, sorted(side_b), poses, adjacency):
                return e
        return None

    def _kruskal(
        self, edges: Iterable[Edge]
    ) -> tuple[list[Edge], list[Edge], list[Edge], dict[str, list[Edge]], RootedForest]:
        """Maximum spanning forest with the cycle check (links never rejected; see the module).

        An edge whose two submaps the forest already joins changes nothing in the forest, and its
        path through the forest is the same once the forest is whole: the cycle checks are made
        then, on the forest rooted once (:class:`~fleetmap.merger.forest.RootedForest`), in the
        order the edges came."""
        root = {k: k for k in self._nodes}
        rel = {k: Transform2D.identity() for k in self._nodes}
        members = {k: [k] for k in self._nodes}
        tree: list[Edge] = []
        loops: list[Edge] = []
        conflicts: list[Edge] = []
        adjacency: dict[str, list[Edge]] = {k: [] for k in self._nodes}
        edges = list(edges)
        checks: list[tuple[Edge, str]] = []  # joins refused, and edges within one group, in order
        by_node: dict[str, list[Edge]] = {}
        for e in edges:
            if not e.link:
                by_node.setdefault(e.a, []).append(e)
                by_node.setdefault(e.b, []).append(e)
        for e in edges:
            ra, rb = root[e.a], root[e.b]
            if not e.valid:
                # an ambiguous integration: its best alignment and its rivals are hypotheses that a
                # cycle can decide (the one that agrees with the tree, if only one), but it joins no
                # two groups: in a grid of corridors the neighbours of a hypothesis turned round or
                # crosswise bear it out as readily as the right one's (aces cut in 8: all four wrong
                # joins were such hypotheses; docs/decisions/002-pose-graph.md)
                if ra == rb:
                    checks.append((e, "ambiguous"))
                continue
            elif ra != rb and not e.link and not self._join_holds(e, members[ra], members[rb], rel, adjacency):
                checks.append((e, "refused"))
                continue
            elif ra != rb and not e.link:
                rival = self._rival_join(e, members[ra], members[rb], rel, adjacency, by_node)
                if rival is not None:
                    log.debug(
                        "join %s-%s refused: %s-%s puts the two groups %.1f m and %.0f degrees apart from it, and"
                        " they bear that out too",
                        e.a,
                        e.b,
                        rival[0].a,
                        rival[0].b,
                        rival[1],
                        math.degrees(rival[2]),
                    )
                    checks.append((e, "refused"))
                    continue
            if ra != rb:
                _unite(e, root, rel, members, tree, adjacency)
            else:
                checks.append((e, "cycle"))
        forest = RootedForest(self._nodes, adjacency, self._link_covariances)
        for e, kind in checks:
            if kind == "refused":
                conflicts.append(e)
            elif e.link:
                loops.append(e)
            else:
                tol_t, tol_r = self._tolerance_between(forest, e.a, e.b)
                predicted = rel[e.a].inverse().compose(rel[e.b])
                if kind == "cycle":
                    (loops if _within(predicted, e.transform, tol_t, tol_r) else conflicts).append(e)
                    continue
                # an ambiguous integration: the one of its hypotheses that agrees with the tree, if only one
                hypotheses = [e, *(replace(e, transform=t) for t in e.rivals[: self.merge.join_hypotheses - 1])]
                agreeing = [h for h in hypotheses if _within(predicted, h.transform, tol_t, tol_r)]
                if len(agreeing) == 1:
                    loops.append(replace(agreeing[0], valid=True))
        return tree, loops, conflicts, adjacency, forest

    def _tolerance_between(self, forest: RootedForest, a: str, b: str) -> tuple[float, float]:
        """:meth:`_cycle_tolerance` of the forest's path from a to b."""
        joins, drift_t, drift_r = forest.drift(a, b)
        base_t, base_r = self._tolerance(1 + joins)
        return math.hypot(base_t, drift_t), math.hypot(base_r, drift_r)

    def _ambiguous(self, e: Edge) -> bool:
        """Whether an integration is invalid for its rivals alone (its value and free space would
        do): its alignment and its rivals' are hypotheses for a cycle to test."""
        if e.valid or e.link or not e.rivals or e.a not in self._nodes or e.b not in self._nodes:
            return False
        ma, mb = self._nodes[e.a].map, self._nodes[e.b].map
        return is_valid(
            e.value, e.violation, 0.0, ma, mb, self.integration, large=True, solid_violation=e.solid_violation
        )

    def _refined_components(self, tree: list[Edge], loops: list[Edge]) -> tuple[list[Component], list[Edge]]:
        """Each component's poses refined together (walls not fused yet), and the integrations
        they disagree with."""
        adjacency: dict[str, list[Edge]] = {k: [] for k in self._nodes}
        for e in tree:
            adjacency[e.a].append(e)
            adjacency[e.b].append(e.reversed())
        seen: set[str] = set()
        out: list[Component] = []
        off: list[Edge] = []
        for start in self.keys:
            if start in seen:
                continue
            group = _bfs_order(adjacency, start)
            seen.update(group)
            anchor = self._pick_anchor(group)
            order = _bfs_order(adjacency, anchor)
            group_set = set(group)
            cycle_edges = [e for e in loops if e.a in group_set]
            edges = [e for e in tree if e.a in group_set] + cycle_edges
            # a component whose submaps and edges are all as the last solve had them keeps its
            # poses (refinement only where something changed)
            signature = (anchor, tuple(order), tuple(sorted(edges, key=lambda e: e.key())))
            held = self._last_refined.get(signature)
            paths = _joins_above(anchor, order, adjacency)
            if held is not None:
                poses, disagreeing = dict(held[0]), held[1]
            else:
                poses, disagreeing = self._initial_poses(anchor, order, adjacency, paths), []
                if cycle_edges:
                    poses = self._optimized(anchor, poses, edges)
                    for e in edges:
                        if e.link:
                            continue
                        dt, dr = _disagreement(poses[e.a].inverse().compose(poses[e.b]), e.transform)
                        tol_t, tol_r = self._tolerance(1)
                        if dt > tol_t or dr > tol_r:
                            disagreeing.append(e)
            self._refined_now[signature] = (dict(poses), disagreeing)
            off += disagreeing
            for k in order:
                self._solution[k] = (anchor, paths[k], poses[k])
            out.append(Component(anchor, tuple(order), poses, np.zeros((0, 4))))
        # the global map first: the component of the most robots, then of the most robots' epochs,
        # then of the most submaps (one robot's many epochs, a flood of its own key, never outweigh
        # the fleet's map)
        out.sort(
            key=lambda c: (
                -len({_robot_of(k) for k in c.members}),
                -len({_chain_of(k) for k in c.members}),
                -len(c.members),
                -sum(self._nodes[k].map.total_length for k in c.members),
            )
        )
        return out, off

    def _initial_poses(
        self, anchor: str, order: list[str], adjacency: dict[str, list[Edge]], paths: dict[str, tuple[object, ...]]
    ) -> dict[str, Transform2D]:
        """Where the refinement starts: a submap's pose from the last solve where it hangs from the
        same anchor by the same integrations, else the spanning tree's. A join that changed (one
        wrong join replaced by the right one) starts from the new tree: started where the wrong join
        had put them, a robot's submaps sit in a wrong minimum and the right join and its loops read
        as disagreeing (docs/decisions/002-pose-graph.md)."""
        poses = {anchor: Transform2D.identity()}
        for k in order:
            for e in adjacency[k]:
                if e.b in poses:
                    continue
                held = self._solution.get(e.b)
                same = held is not None and held[0] == anchor and held[1] == paths[e.b]
                poses[e.b] = held[2] if held is not None and same else poses[k].compose(e.transform)
        return poses

    def edge_noise(self, e: Edge, robust: bool = True) -> gtsam.noiseModel.Base:
        """How an edge weighs: a link by its covariance; an integration by how firmly its walls fix
        it (with a share of its value in every direction), else by its value alone, through a
        Cauchy loss."""
        # a link's covariance and an integration's information are on b's pose in a's frame; the
        # between factor's error is in b's frame
        given = (
            None
            if e.information is None
            else pose_information_in_own_frame(np.asarray(e.information), e.transform.theta)
        )
        if e.link and given is not None:
            return gtsam.noiseModel.Gaussian.Information(given)
        w2 = max(e.value, 1e-3)
        sigma_t, sigma_r = self.merge.edge_sigma_translation, self.merge.edge_sigma_rotation
        iso = np.diag([w2 / sigma_t**2, w2 / sigma_t**2, w2 / sigma_r**2])
        information = iso
        if given is not None:
            candidate = given / sigma_t**2 + self.merge.isotropic_share * iso
            if np.isfinite(candidate).all() and np.linalg.eigvalsh(candidate).min() > 0:
                information = candidate
        gaussian = gtsam.noiseModel.Gaussian.Information(information)
        if not robust:
            return gaussian
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(self.merge.robust_scale), gaussian
        )

    def _optimized(self, anchor: str, poses: dict[str, Transform2D], edges: list[Edge]) -> dict[str, Transform2D]:
        """The component's poses refined together (Levenberg-Marquardt over SE(2), anchor fixed),
        in two rounds, a graduated non-convexity in its simplest form: every edge as a Gaussian
        first (each integration here agreed with its cycle, so the least-squares solution spreads
        what a loop corrects along the chain), then from there with the integrations' Cauchy loss
        (an integration the others outvote weighs little). Started at the spanning tree's poses
        with the robust loss at once, a loop that corrects a long chain's drift starts far off,
        weighs next to nothing, and is never taken (docs/decisions/002-pose-graph.md)."""
        ids = {k: i for i, k in enumerate(poses)}
        values = gtsam.Values()
        for k, pose in poses.items():
            values.insert(ids[k], _pose2(pose))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-6)
        for robust in (False, True):
            graph = gtsam.NonlinearFactorGraph()
            graph.add(gtsam.NonlinearEqualityPose2(ids[anchor], _pose2(poses[anchor])))
            for e in edges:  # each as measured (a's frame to b's): the forest keeps them so
                graph.add(gtsam.BetweenFactorPose2(ids[e.a], ids[e.b], _pose2(e.transform), self.edge_noise(e, robust)))
            values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return {k: _transform(values.atPose2(i)) for k, i in ids.items()}

    def _walls(self, order: list[str], poses: dict[str, Transform2D]) -> Array:
        """The component's walls: every member's at its pose, one segment per stretch of wall; the
        last solve's where the component is the same (the same maps in the same order at poses
        equal to the bit: a component no step touched)."""
        maps = tuple(self._nodes[k].map for k in order)
        key = tuple((k, id(m), poses[k].x, poses[k].y, poses[k].theta) for k, m in zip(order, maps, strict=True))
        held = self._last_walls.get(key)
        if held is None or not all(a is b for a, b in zip(held[0], maps, strict=True)):
            walls = WallMap(self.integration.simplify_tolerance)
            for k, m in zip(order, maps, strict=True):
                walls.add(poses[k].apply(m.segments))
            held = (maps, walls.segments)
        self._walls_now[key] = held
        return held[1]


def _robot_of(key: str) -> str:
    """The robot a node belongs to: a submap's (``robot/epoch/submap``), else the node itself (a map file)."""
    parts = key.split("/")
    return parts[0] if len(parts) == 3 else key
