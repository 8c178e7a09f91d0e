"""Each component's poses refined together: robust least squares over SE(2) with GTSAM.

Links weigh as their covariance says, integrations by how firmly their walls fix them (with a share
of their value in every direction) through a Cauchy loss, the component's anchor fixed
(:meth:`RefinedGraph.edge_noise`, :meth:`RefinedGraph._optimized`). The refinement starts where the
last solve left each submap if it hangs from the same anchor by the same integrations
(:meth:`RefinedGraph._initial_poses`); where the descent from there leaves a link bent beyond its
covariance's chi-square bound (a fold the last solve left, which the descent cannot undo), it is
made from the spanning tree's poses too, and the one that ends lower is kept. A component whose
submaps and edges are as the last solve had them keeps its poses. An integration the refined poses
disagree with by more than one integration's base tolerance is handed back, for the solve to leave
out, the grossest first (:meth:`RefinedGraph._grossest`). The same graph at the refined poses
gives each submap's pose covariance (:meth:`RefinedGraph.pose_covariances`), with which the global
map's walls may be fused (Ballesta et al. 2009, Section 4).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import gtsam
import numpy as np
from fleetmap.merger.consistency import CONSISTENT_CHI2
from fleetmap.merger.graph import (
    EDGE_SIGMA_ROTATION,
    EDGE_SIGMA_TRANSLATION,
    Component,
    Edge,
    _bfs_order,
    _disagreement,
)
from fleetmap.merger.spanning import ForestBuilder, _tree_poses
from fleetmap.shared.core.geometry import Array, Transform2D, pose_information_in_own_frame

log = logging.getLogger(__name__)

ROBUST_SCALE = 2.0
"""The Cauchy loss of an integration in the refinement, in standard deviations of its information
(docs/decisions/002-pose-graph.md: Gaussian first, then Cauchy from there)."""
ISOTROPIC_SHARE = 0.01
"""The share of the value-based weight an integration with known information keeps: no direction is
entirely free (0: the scenarios within 3 mm; kept as a floor, 002)."""


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


class RefinedGraph(ForestBuilder):
    """Submaps, links and integrations, their spanning forest, and each component's refined poses."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # as ChainGraph's
        super().__init__(*args, **kwargs)
        self._solution: dict[str, tuple[str, tuple[object, ...], Transform2D]] = {}
        """The last solve's pose of every placed node, with its component's anchor (a warm start)."""
        self._refined_now: dict[tuple[object, ...], tuple[dict[str, Transform2D], list[Edge]]] = {}
        """Each component's refined poses and the edges they disagree with, by its anchor, members
        and edges, from the last solve (:meth:`_refined_components`)."""
        self._last_refined = self._refined_now

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._solution.pop(key, None)

    def _begin_refinement(self) -> None:
        """A whole solve starts: the refinements it makes are kept for the next, the last solve's
        looked up (:meth:`_refined_components`)."""
        self._last_refined, self._refined_now = self._refined_now, {}

    def _refined_components(self, tree: list[Edge], loops: list[Edge]) -> tuple[list[Component], list[Edge]]:
        """Each component's poses refined together (walls not fused yet; in the order of their
        first submaps), and the integrations they disagree with."""
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
            if held is not None:
                poses, disagreeing = dict(held[0]), held[1]
                paths = _joins_above(anchor, order, adjacency)
                for k in order:
                    self._solution[k] = (anchor, paths[k], poses[k])
            else:
                poses, disagreeing = self._refined(anchor, order, adjacency, edges, bool(cycle_edges))
            self._refined_now[signature] = (dict(poses), disagreeing)
            off += disagreeing
            out.append(Component(anchor, tuple(order), poses, np.zeros((0, 4))))
        return out, off

    def _refined(
        self, anchor: str, order: list[str], adjacency: dict[str, list[Edge]], edges: list[Edge], cycles: bool
    ) -> tuple[dict[str, Transform2D], list[Edge]]:
        """One component's poses, refined if its edges make ``cycles``, and the integrations they
        disagree with by more than one integration's base tolerance."""
        paths = _joins_above(anchor, order, adjacency)
        poses, disagreeing = self._initial_poses(anchor, order, adjacency, paths), []
        if cycles:
            tree = _tree_poses([anchor], adjacency)
            warm = any(poses[k] != tree[k] for k in order)
            poses = self._optimized(anchor, poses, edges)
            if warm and self._folded_link(poses, edges):
                # a start from the last solve can hold a fold that the tree's poses do not: the
                # descent that ends lower, from either start (docs/decisions/039)
                fresh = self._optimized(anchor, tree, edges)
                lower, held = self._objective(anchor, fresh, edges), self._objective(anchor, poses, edges)
                log.debug(
                    "component of %s: a link bent beyond its covariance from the last solve's poses"
                    " (objective %.1f); from the tree's, %.1f",
                    *(anchor, held, lower),
                )
                if lower < held:
                    poses = fresh
            tol_t, tol_r = self._tolerance(1)
            disagreeing = [e for e in edges if not e.link and not self._agrees(e, poses, tol_t, tol_r)]
        for k in order:
            self._solution[k] = (anchor, paths[k], poses[k])
        return poses, disagreeing

    def _grossest(self, components: list[Component], off: list[Edge]) -> list[Edge]:
        """Of the integrations the refined poses disagree with, those to leave out this round: the
        ones that disagree by at least half as much as the worst (each in units of one integration's
        base tolerance, its translation or its heading, whichever is more). A wrong integration far
        off bends the compromise the refinement makes, and right ones near it then disagree with
        the bent poses too: left out together, a loop that corrects a long chain's drift is lost
        with the wrong one and never found again, since the poses solved without it stay as far
        from it as the drift (freiburg-campus-corrected cut in 4: 79 integrations at once, some of
        them 11-141 m off the truth, and with them the two right loops that close its revisit,
        2.6 m apart; docs/decisions/086). The grossest first, each round a halving, as one at a time
        but at a bounded number of refinements."""
        at = {k: pose for c in components for k, pose in c.poses.items()}
        tol_t, tol_r = self._tolerance(1)
        times = []
        for e in off:
            dt, dr = _disagreement(at[e.a].inverse().compose(at[e.b]), e.transform)
            times.append(max(dt / tol_t, dr / tol_r))
        worst = max(times)
        return [e for e, t in zip(off, times, strict=True) if t >= worst / 2.0]

    def _folded_link(self, poses: dict[str, Transform2D], edges: list[Edge]) -> bool:
        """Whether the refined poses bend a link beyond :data:`CONSISTENT_CHI2` of its covariance
        (its squared Mahalanobis distance): a link the tracking measured that far off is not a
        drift a loop corrects, but a descent that settled in another minimum."""
        for e in edges:
            if not e.link or e.information is None:
                continue
            factor = gtsam.BetweenFactorPose2(0, 1, _pose2(e.transform), self.edge_noise(e, robust=False))
            values = gtsam.Values()
            values.insert(0, _pose2(poses[e.a]))
            values.insert(1, _pose2(poses[e.b]))
            if 2.0 * factor.error(values) > CONSISTENT_CHI2:  # gtsam's error: half the squared distance
                return True
        return False

    def _objective(self, anchor: str, poses: dict[str, Transform2D], edges: list[Edge]) -> float:
        """The refinement's last, robust round's objective at ``poses``."""
        ids, values = _ids_and_values(poses)
        return float(self._factor_graph(anchor, poses, ids, edges, robust=True).error(values))

    @staticmethod
    def _agrees(e: Edge, poses: dict[str, Transform2D], tol_t: float, tol_r: float) -> bool:
        dt, dr = _disagreement(poses[e.a].inverse().compose(poses[e.b]), e.transform)
        return dt <= tol_t and dr <= tol_r

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
        sigma_t, sigma_r = EDGE_SIGMA_TRANSLATION, EDGE_SIGMA_ROTATION
        iso = np.diag([w2 / sigma_t**2, w2 / sigma_t**2, w2 / sigma_r**2])
        information = iso
        if given is not None:
            candidate = given / sigma_t**2 + ISOTROPIC_SHARE * iso
            if np.isfinite(candidate).all() and np.linalg.eigvalsh(candidate).min() > 0:
                information = candidate
        gaussian = gtsam.noiseModel.Gaussian.Information(information)
        if not robust:
            return gaussian
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(ROBUST_SCALE), gaussian)

    def _optimized(self, anchor: str, poses: dict[str, Transform2D], edges: list[Edge]) -> dict[str, Transform2D]:
        """The component's poses refined together (Levenberg-Marquardt over SE(2), anchor fixed),
        in two rounds, a graduated non-convexity in its simplest form: every edge as a Gaussian
        first (each integration here agreed with its cycle, so the least-squares solution spreads
        what a loop corrects along the chain), then from there with the integrations' Cauchy loss
        (an integration the others outvote weighs little). Started at the spanning tree's poses
        with the robust loss at once, a loop that corrects a long chain's drift starts far off,
        weighs next to nothing, and is never taken (docs/decisions/002-pose-graph.md)."""
        ids, values = _ids_and_values(poses)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-6)
        for robust in (False, True):
            graph = self._factor_graph(anchor, poses, ids, edges, robust)
            values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return {k: _transform(values.atPose2(i)) for k, i in ids.items()}

    def _factor_graph(
        self, anchor: str, poses: dict[str, Transform2D], ids: dict[str, int], edges: list[Edge], robust: bool
    ) -> gtsam.NonlinearFactorGraph:
        """The component's factors: the anchor fixed, every edge a between factor weighed by
        :meth:`edge_noise`."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.NonlinearEqualityPose2(ids[anchor], _pose2(poses[anchor])))
        for e in edges:  # each as measured (a's frame to b's): the forest keeps them so
            graph.add(gtsam.BetweenFactorPose2(ids[e.a], ids[e.b], _pose2(e.transform), self.edge_noise(e, robust)))
        return graph

    def pose_covariances(
        self, anchor: str, poses: dict[str, Transform2D], edges: list[Edge]
    ) -> dict[str, Array] | None:
        """Each submap's pose covariance ``(3, 3)`` on (x, y, theta) in the anchor's frame: the
        marginals of the component's graph at its poses, its edges weighed as the refinement's
        last, robust round weighs them (an integration the others outvote counts little). For a
        component solved as a tree (no cycles, every edge at zero residual) that is its edges'
        covariances composed along the tree from the anchor. None where the graph does not
        determine them."""
        ids, values = _ids_and_values(poses)
        graph = self._factor_graph(anchor, poses, ids, edges, robust=True)
        try:
            marginals = gtsam.Marginals(graph, values)
        except RuntimeError as err:  # an indeterminant system: no weights for this component
            log.warning("no pose covariances for the component of %s: %s", anchor, err)
            return None
        out: dict[str, Array] = {}
        for k, i in ids.items():
            # gtsam gives it in the pose's own frame (its tangent space): turned into the anchor's
            c, s = math.cos(poses[k].theta), math.sin(poses[k].theta)
            turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            out[k] = turn @ marginals.marginalCovariance(i) @ turn.T
        return out


def _ids_and_values(poses: dict[str, Transform2D]) -> tuple[dict[str, int], gtsam.Values]:
    """The poses as gtsam's numbered values."""
    ids = {k: i for i, k in enumerate(poses)}
    values = gtsam.Values()
    for k, pose in poses.items():
        values.insert(ids[k], _pose2(pose))
    return ids, values
