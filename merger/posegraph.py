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

A step costs what it adds (issue 49): the forest, its verdicts and the refined poses are kept
from solve to solve, and a step that only adds submaps, their links and integrations that close
loops or that the groups do not bear out carries them on (:meth:`PoseGraph._kept_solve`); the rest
solves the whole graph again (:meth:`PoseGraph._whole_solve`).

How a join of two groups is judged, and the robots' links it is judged through, is
:mod:`fleetmap.merger.joins`; the forest's paths and their drift, :mod:`fleetmap.merger.forest`.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import replace

import gtsam
import numpy as np
from fleetmap.merger.forest import KeptForest, RootedForest
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
        self._kept: KeptForest | None = None
        """The last solve's forest, for the next to carry on (:meth:`_kept_solve`)."""
        self._with_walls_now: dict[int, tuple[Component, Component]] = {}
        """Each component of the last solve with its walls, by the component without (:meth:`_fused`)."""
        self._with_walls = self._with_walls_now
        self._ranks: dict[int, tuple[Component, tuple[int, int, int]]] = {}
        """Each component's rank for the global map (:meth:`_global_first`), by the component."""
        self._ambiguity: dict[tuple[str, str], tuple[Edge, int, int, bool]] = {}
        """Each invalid integration's :meth:`_ambiguous` at its two submaps' versions."""
        self.whole_solves = 0
        self.kept_solves = 0
        """Solves of the whole graph, and solves that carried the last one on."""

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._solution.pop(key, None)
        self._kept = None
        self._ambiguity = {k: v for k, v in self._ambiguity.items() if key not in k}

    def _work(self, key: str, m: SegmentMap) -> SegmentMap:
        # a submap's walls are already one segment per stretch of wall (fleetmap.shared.core.walls);
        # a map file (a pivot local map: many short pieces of each wall) is simplified as the map
        # graph simplifies it
        return super()._work(key, m) if _map_file(key) else m

    def solve(self, fuse_maps: bool = True) -> MergeResult:
        """The global maps: the forest and the refined poses kept from the last solve where the
        step only added to them (:meth:`_kept_solve`), else found again from the whole graph
        (:meth:`_whole_solve`)."""
        links = [e for e in self._links.values() if e.a in self._nodes and e.b in self._nodes]
        # the links between two robots' first submaps (their known start poses,
        # fleetmap.merger.startposes) are the forest's weakest edges: it takes every integration
        # first, so that a join of two robots is judged as any join is, and a start pose only
        # unites what no integration joins (else it closes a cycle, and weighs in the refinement);
        # a forest with them is solved whole (a later join may take a start pose's place)
        priors = [e for e in links if _robot_of(e.a) != _robot_of(e.b)]
        if priors:
            links = [e for e in links if _robot_of(e.a) == _robot_of(e.b)]
        valid = [e for e in self._edges.values() if e.valid or self._ambiguous(e)]
        self._last_walls, self._walls_now = self._walls_now, {}
        self._with_walls, self._with_walls_now = self._with_walls_now, {}
        kept = self._kept_solve(links, valid) if self._kept is not None and not priors else None
        if kept is None:
            self.whole_solves += 1
            components, tree, loops, rejected = self._whole_solve(links, valid, priors)
        else:
            self.kept_solves += 1
            components, tree, loops, rejected = kept
        if fuse_maps:  # the walls of the final round's components only
            components = [self._fused(c) for c in components]
        poses: dict[str, Transform2D | None] = {k: None for k in self.keys}
        for c in components:
            if len(c.members) > 1:
                poses.update(c.poses)
        return MergeResult(poses, components, tree, loops, rejected)

    def _kept_solve(
        self, links: list[Edge], valid: list[Edge]
    ) -> tuple[list[Component], list[Edge], list[Edge], list[Edge]] | None:
        """The last solve's forest and poses carried on by what this step added, where that alone
        decides the answer (issue 49: a step costs what it adds); None where the whole graph must
        be solved again (:meth:`_whole_solve`).

        Kept, the forest grows as Kruskal's would from its new edges, most valuable first: a new
        submap hangs from its robot's chain by its link (a leaf: the rooted forest grows by one
        node, the chain's refined poses stand and the leaf's follows from its link, exactly the
        least-squares answer), an integration within one tree is checked against the tree's path
        (a loop that closes: the component is refined again from its last poses), and one between
        two trees that the groups do not bear out is refused, as the whole solve would. Everything
        else that could change the answer calls for the whole solve: a submap or an edge gone or
        changed, a join taken, a cycle that does not close, a link between two grown groups, a
        join or a culprit that a grown group may now decide otherwise, an integration the refined
        poses now disagree with or agree with again. A step that adds nothing but new versions of
        submaps changes no pose."""
        kept = self._kept
        assert kept is not None
        if any(k not in self._nodes for k in kept.versions):
            return None
        taken = {e.key(): e for e in links}
        aside = 0
        for e in valid:
            key = e.key()
            if key in kept.aside:
                if kept.aside[key] is not e and kept.aside[key] != e:
                    return None  # integrated again: the whole solve judges it
                aside += 1
                continue
            taken[key] = e
        new: list[Edge] = []
        for key, e in taken.items():
            held = kept.edges.get(key)
            if held is None:
                new.append(e)
            elif held is not e and held != e:
                return None
        if len(taken) - len(new) != len(kept.edges) or aside != len(kept.aside):
            return None  # an edge left
        grown = {k for k, n in self._nodes.items() if kept.versions.get(k) != n.version}
        if not new and not grown:
            return self._kept_result(kept)
        root, rel, members, adjacency, forest = kept.root, kept.rel, kept.members, kept.adjacency, kept.forest
        for k in self._nodes:
            if k not in root:
                root[k], rel[k], members[k], adjacency[k] = k, Transform2D.identity(), [k], []
                forest.add_root(k)
        order = {k: n.order for k, n in self._nodes.items()}
        new.sort(key=lambda e: (-e.value, order[e.a], order[e.b]))
        touched: set[str] = set()  # the groups this step changed
        refine: set[str] = set()  # ... and of those, the ones whose cycles changed
        for e in new:
            ra, rb = root[e.a], root[e.b]
            if ra != rb:
                if not e.valid:
                    kept.apart.append(e)  # an ambiguous integration joins nothing (_kruskal)
                    continue
                if not e.link:
                    if self._join_holds(e, members[ra], members[rb], rel, adjacency):
                        return None  # a join: the whole solve judges it with its rivals
                    kept.conflicts.append(e)
                    kept.rejected.append(e)
                    kept.apart.append(e)
                    continue
                if len(members[ra]) > 1 and len(members[rb]) > 1:
                    return None
                leaf = e if len(members[rb]) == 1 else e.reversed()
                _unite(e, root, rel, members, kept.tree, adjacency)
                forest.add_leaf(leaf, self._link_covariances)
                kept.components.pop(rb if root[e.a] == ra else ra, None)  # the group that joined the other
                touched.add(root[e.a])
                continue
            touched.add(ra)
            if e.link:
                kept.loops.append(e)
                refine.add(ra)
                continue
            tol_t, tol_r = self._tolerance_between(forest, e.a, e.b)
            predicted = rel[e.a].inverse().compose(rel[e.b])
            if e.valid:
                if not _within(predicted, e.transform, tol_t, tol_r):
                    return None  # a cycle that does not close: the culprit rule decides
                kept.loops.append(e)
                refine.add(ra)
                continue
            hypotheses = [e, *(replace(e, transform=t) for t in e.rivals[: self.merge.join_hypotheses - 1])]
            agreeing = [h for h in hypotheses if _within(predicted, h.transform, tol_t, tol_r)]
            if len(agreeing) == 1:
                kept.loops.append(replace(agreeing[0], valid=True))
                refine.add(ra)
        if any(root[e.a] == root[e.b] for e in kept.apart):
            return None  # a new submap's link put two submaps in one tree that an integration did not join
        touched.update(root[k] for k in grown)
        if not self._kept_verdicts_stand(kept, touched):
            return None
        for r in touched:
            if not self._kept_component(kept, r, r in refine):
                return None
        kept.edges.update((e.key(), e) for e in new)
        kept.versions = {k: n.version for k, n in self._nodes.items()}
        return self._kept_result(kept)

    def _kept_verdicts_stand(self, kept: KeptForest, touched: set[str]) -> bool:
        """Whether what the forest decided about the groups this step changed stands: the joins
        it refused still fail, its joins still hold, and no culprit appears (each decided as
        :meth:`_kruskal` and :meth:`_forest` decide it, the verdicts kept where nothing new bears
        on them: :meth:`_kept_verdict`)."""
        root, members, rel, adjacency = kept.root, kept.members, kept.rel, kept.adjacency
        for e in kept.apart:
            ra, rb = root[e.a], root[e.b]
            regrown = ra != rb and (ra in touched or rb in touched)
            if regrown and e.valid and not e.link and self._join_holds(e, members[ra], members[rb], rel, adjacency):
                return False
        for r in touched:
            group = set(members[r])
            joins = [t for t in kept.tree if not t.link and t.a in group]
            if not joins:
                continue
            if self._failed_join(joins, adjacency, rel) is not None:
                return False
            # new loops only add support, and a new leaf is on no cycle: the vote can find a culprit
            # only where the last one had a candidate that its accusers' groups did not bear out
            accusers = [e for e in kept.conflicts if e.a in group and e.b in group] if kept.contested else []
            if accusers:
                loops = [e for e in kept.loops if e.a in group]
                if self._culprit(joins, loops, accusers, adjacency, kept.forest) is not None:
                    return False
        return True

    def _kept_component(self, kept: KeptForest, r: str, cycles_changed: bool) -> bool:
        """Group ``r``'s component after this step: its kept poses, the new leaves' from their
        links, or, where its cycles changed, refined again from them; False where the refined
        poses now disagree with an integration taken or agree with one left out."""
        group = kept.members[r]
        anchor = self._pick_anchor(group)
        order = _bfs_order(kept.adjacency, anchor)
        held = kept.components.get(r)
        if held is not None and held.anchor == anchor and not cycles_changed and len(held.members) == len(order):
            return True  # new versions of its submaps only: the same poses
        if held is not None and held.anchor == anchor and not cycles_changed:
            poses = dict(held.poses)
            for k in order:  # the leaves hung from the chain since: breadth first, parents first
                if k not in poses:
                    parent = kept.forest.parent[k]
                    assert parent is not None
                    poses[k] = poses[parent.a].compose(parent.transform)
        else:
            in_group = set(group)
            tree = [e for e in kept.tree if e.a in in_group]
            cycle_edges = [e for e in kept.loops if e.a in in_group]
            poses, off = self._refined(anchor, order, kept.adjacency, tree + cycle_edges, bool(cycle_edges))
            if off:
                return False
            tol_t, tol_r = self._tolerance(1)
            for e in kept.aside.values():
                if e.a in in_group and e.b in in_group and self._agrees(e, poses, tol_t, tol_r):
                    return False
        kept.components[r] = Component(anchor, tuple(order), poses, np.zeros((0, 4)))
        return True

    def _kept_result(self, kept: KeptForest) -> tuple[list[Component], list[Edge], list[Edge], list[Edge]]:
        # copies: the kept lists grow with the next steps, and a result once given stays as it was
        components = self._global_first(list(kept.components.values()))
        return components, list(kept.tree), list(kept.loops), list(kept.rejected)

    def _whole_solve(
        self, links: list[Edge], valid: list[Edge], priors: Sequence[Edge] = ()
    ) -> tuple[list[Component], list[Edge], list[Edge], list[Edge]]:
        """The forest from every edge, the components refined, and an integration the refined
        poses disagree with left out and all found again (see the module); kept for the next
        solve (:class:`~fleetmap.merger.forest.KeptForest`)."""
        order = {k: n.order for k, n in self._nodes.items()}
        valid = sorted(valid, key=lambda e: (-e.value, order[e.a], order[e.b]))
        disagreeing: set[tuple[str, str]] = set()
        self._last_refined, self._refined_now = self._refined_now, {}
        for _ in range(self.merge.max_rejection_rounds):
            built = self._forest(links, [e for e in valid if e.key() not in disagreeing], priors)
            components, off = self._refined_components(built.tree, built.loops)
            if not off:
                break
            for e in off:
                log.debug("rejecting edge %s-%s: the refined poses disagree with it", e.a, e.b)
            disagreeing.update(e.key() for e in off)
        rejected = built.rejected + [e for e in valid if e.key() in disagreeing and e.valid]
        taken = {e.key(): e for e in (*links, *priors)}
        taken.update((e.key(), e) for e in valid if e.key() not in disagreeing)
        built.aside = {e.key(): e for e in valid if e.key() in disagreeing or e.key() in built.excluded}
        for key in built.aside:
            taken.pop(key, None)
        built.edges = taken
        built.versions = {k: n.version for k, n in self._nodes.items()}
        built.rejected = rejected
        built.components = {built.root[c.anchor]: c for c in components}
        self._kept = built
        return components, list(built.tree), list(built.loops), list(rejected)

    def _forest(self, links: list[Edge], valid: list[Edge], priors: Sequence[Edge] = ()) -> KeptForest:
        """The spanning forest (links first, ``priors`` last), its loop closures, and the integrations rejected: by
        the cycle check, by the culprit rule (:meth:`_culprit`), and joins that the two groups they
        join do not bear out once the forest is whole (:meth:`_join_holds` on the two sides of the
        tree edge: the forest is built greedily, and a join checked when its groups were small
        may fail against what later joined them)."""
        excluded: set[tuple[str, str]] = set()
        while True:
            built = self._kruskal([*links, *(e for e in valid if e.key() not in excluded), *priors])
            tree, loops, conflicts, adjacency = built.tree, built.loops, built.conflicts, built.adjacency
            culprit = self._culprit(tree, loops, conflicts, adjacency, built.forest)
            if culprit is None:
                culprit = self._failed_join(tree, adjacency)
                if culprit is not None:
                    log.debug("rejecting edge %s-%s: the maps it joins do not bear it out", culprit.a, culprit.b)
            elif culprit is not None:
                log.debug("rejecting edge %s-%s: the cycles through it disagree", culprit.a, culprit.b)
            if culprit is None:
                break
            excluded.add(culprit.key())
        built.rejected = conflicts + [e for e in valid if e.key() in excluded]
        built.excluded = excluded
        joins = [t for t in tree if not t.link]
        built.contested = _culprit(joins, loops, conflicts, built.forest.path_keys) is not None
        return built

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

    def _failed_join(
        self, tree: list[Edge], adjacency: dict[str, list[Edge]], poses: dict[str, Transform2D] | None = None
    ) -> Edge | None:
        """The weakest integration of ``tree`` whose two sides do not bear it out, if any (``poses``:
        every submap's in its tree's frame, found along the tree if not given)."""
        joins = sorted((e for e in tree if not e.link), key=lambda e: (e.value, e.key()))
        if not joins:
            return None
        poses = _tree_poses(self.keys, adjacency) if poses is None else poses
        for e in joins:
            side_b = set(_bfs_order(adjacency, e.b, cut=e.key()))
            side_a = [k for k in _bfs_order(adjacency, e.a) if k not in side_b]
            if not self._join_holds(e, side_a, sorted(side_b), poses, adjacency):
                return e
        return None

    def _kruskal(self, edges: Iterable[Edge]) -> KeptForest:
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
        apart = [e for e in edges if not e.link and root[e.a] != root[e.b]]  # refused, or ambiguous
        return KeptForest(tree, loops, conflicts, root, rel, members, adjacency, forest, apart=apart)

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
        na, nb = self._nodes[e.a], self._nodes[e.b]
        held = self._ambiguity.get(e.key())
        if held is not None and held[0] is e and held[1] == na.version and held[2] == nb.version:
            return held[3]
        ambiguous = is_valid(
            e.value, e.violation, 0.0, na.map, nb.map, self.integration, large=True, solid_violation=e.solid_violation
        )
        self._ambiguity[e.key()] = (e, na.version, nb.version, ambiguous)
        return ambiguous

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
        return self._global_first(out), off

    def _refined(
        self, anchor: str, order: list[str], adjacency: dict[str, list[Edge]], edges: list[Edge], cycles: bool
    ) -> tuple[dict[str, Transform2D], list[Edge]]:
        """One component's poses, refined if its edges make ``cycles``, and the integrations they
        disagree with by more than one integration's base tolerance."""
        paths = _joins_above(anchor, order, adjacency)
        poses, disagreeing = self._initial_poses(anchor, order, adjacency, paths), []
        if cycles:
            poses = self._optimized(anchor, poses, edges)
            tol_t, tol_r = self._tolerance(1)
            disagreeing = [e for e in edges if not e.link and not self._agrees(e, poses, tol_t, tol_r)]
        for k in order:
            self._solution[k] = (anchor, paths[k], poses[k])
        return poses, disagreeing

    @staticmethod
    def _agrees(e: Edge, poses: dict[str, Transform2D], tol_t: float, tol_r: float) -> bool:
        dt, dr = _disagreement(poses[e.a].inverse().compose(poses[e.b]), e.transform)
        return dt <= tol_t and dr <= tol_r

    def _global_first(self, components: list[Component]) -> list[Component]:
        """The components, the global map first: the component of the most robots, then of the
        most robots' epochs, then of the most submaps (one robot's many epochs, a flood of its own
        key, never outweigh the fleet's map)."""
        held, self._ranks = self._ranks, {}
        for c in components:  # kept by component: most are as the last solve left them
            rank = held.get(id(c))
            if rank is None or rank[0] is not c:
                robots, chains = {_robot_of(k) for k in c.members}, {_chain_of(k) for k in c.members}
                rank = (c, (-len(robots), -len(chains), -len(c.members)))
            self._ranks[id(c)] = rank
        ranks = Counter(rank for _, rank in self._ranks.values())

        def key(c: Component) -> tuple[int, int, int, float]:
            rank = self._ranks[id(c)][1]
            # the walls' length (their submaps' versions change it) only where the rest ties
            return (*rank, -sum(self._nodes[k].map.total_length for k in c.members) if ranks[rank] > 1 else 0.0)

        return sorted(components, key=key)

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

    def _fused(self, c: Component) -> Component:
        """A component with its walls (:meth:`_walls`): the last solve's same object where neither
        its submaps and poses nor its walls changed."""
        walls = self._walls(list(c.members), c.poses)
        held = self._with_walls.get(id(c))
        if held is None or held[0] is not c or held[1].segments is not walls:
            held = (c, replace(c, segments=walls))
        self._with_walls_now[id(c)] = held
        return held[1]

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
