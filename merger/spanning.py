"""The merge order nobody gave: the pose graph's maximum spanning forest, its cycles checked.

Kruskal's algorithm over the edges, links first and then valid integrations by transformation
value (:meth:`ForestBuilder._kruskal`); a join of two groups taken only where the groups as wholes
bear it out (:meth:`~fleetmap.merger.joins.JoinJudge._join_holds`) and no rival alignment of them
holds as well; every other integration checked against the forest's path between its submaps
(the cycle tolerance: the base tolerance per integration on it and what its links can have
drifted, :class:`~fleetmap.merger.forest.RootedForest`); a tree integration that more cycles
accuse than support rejected (:meth:`ForestBuilder._culprit`), and a join that its grown groups no
longer bear out (:meth:`ForestBuilder._failed_join`), the forest then built again without it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import Any

from fleetmap.merger.consistency import ConsistencyJudge, integrations_by_node
from fleetmap.merger.forest import KeptForest, RootedForest
from fleetmap.merger.graph import Edge, _bfs_order, _culprit, _unite
from fleetmap.merger.joins import JOIN_HYPOTHESES, _within
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.validity import is_valid

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


class ForestBuilder(ConsistencyJudge):
    """Submaps, links and integrations, and the spanning forest that orders their merge."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # as ChainGraph's
        super().__init__(*args, **kwargs)
        self._ambiguity: dict[tuple[str, str], tuple[Edge, int, int, bool]] = {}
        """Each invalid integration's :meth:`_ambiguous` at its two submaps' versions."""
        self._kept: KeptForest | None = None
        """The last solve's forest, for the next to carry on
        (:meth:`~fleetmap.merger.posegraph.PoseGraph._kept_solve`)."""

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._ambiguity = {k: v for k, v in self._ambiguity.items() if key not in k}
        self._kept = None

    def tree_drift(self, a: str, b: str) -> tuple[float, float] | None:
        """:meth:`~fleetmap.merger.forest.RootedForest.spread` in the last solve's forest."""
        return None if self._kept is None else self._kept.forest.spread(a, b)

    def tree_tolerance(self, a: str, b: str) -> tuple[float, float] | None:
        """How far (m, rad) an integration of a and b may lie from where the last solve's forest
        puts b on a and still close its cycle (:meth:`_tolerance_between`: the base tolerance of
        each integration on the forest's path and of the new one, and its links' drift); an
        integration beyond it is a conflict. None if they are not in one tree."""
        if self._kept is None or self._kept.forest.spread(a, b) is None:
            return None
        return self._tolerance_between(self._kept.forest, a, b)

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
        order the edges came; so is a join refused while its two groups were apart, where a later
        join (not a start pose) united them."""
        self.refused_whole.clear()
        self.outweighed.clear()
        root = {k: k for k in self._nodes}
        rel = {k: Transform2D.identity() for k in self._nodes}
        members = {k: [k] for k in self._nodes}
        tree: list[Edge] = []
        loops: list[Edge] = []
        conflicts: list[Edge] = []
        adjacency: dict[str, list[Edge]] = {k: [] for k in self._nodes}
        edges = list(edges)
        checks: list[tuple[Edge, str]] = []  # joins refused, and edges within one group, in order
        by_node = integrations_by_node(edges)
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
            elif (
                ra != rb
                and not e.link
                and not self._join_accepted(e, members[ra], members[rb], rel, adjacency, by_node)
            ):
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
        priors = _start_poses(edges) if any(kind == "refused" for _, kind in checks) else set()
        for e, kind in checks:
            if kind == "refused" and (root[e.a] != root[e.b] or priors.intersection(forest.path_keys(e.a, e.b))):
                # still apart, or united only through a start pose (which judges no join)
                conflicts.append(e)
            elif e.link:
                loops.append(e)
            else:
                tol_t, tol_r = self._tolerance_between(forest, e.a, e.b)
                predicted = rel[e.a].inverse().compose(rel[e.b])
                if kind != "ambiguous":
                    # a cycle, or a join refused while its groups were apart that a later join united
                    # (a conflict, it voted against the joins it agrees with: docs/decisions/088)
                    (loops if _within(predicted, e.transform, tol_t, tol_r) else conflicts).append(e)
                    continue
                # an ambiguous integration: the one of its hypotheses that agrees with the tree, if only one
                hypotheses = [e, *(replace(e, transform=t) for t in e.rivals[: JOIN_HYPOTHESES - 1])]
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

    def _ambiguity_stands(self, kept: KeptForest) -> bool:
        """Whether every integration that is invalid for its rivals alone is, at its submaps'
        new versions, still as ambiguous as the kept forest took it (or left it out)."""
        for k, node in self._nodes.items():
            if kept.versions.get(k) != node.version:
                for key in self.rivalled.get(k, ()):
                    if self._ambiguous(self._edges[key]) != (key in kept.edges or key in kept.aside):
                        return False
        return True

    def _edges_to_solve(self) -> tuple[list[Edge], list[Edge], list[Edge]]:
        """The robots' links, the known start poses (links between two robots) and the
        integrations the forest may take (valid or ambiguous)."""
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
        return links, priors, valid

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


def _start_poses(edges: list[Edge]) -> set[tuple[str, str]]:
    """The keys of the links between two robots among ``edges``: their known start poses."""
    return {e.key() for e in edges if e.link and _robot_of(e.a) != _robot_of(e.b)}


def _robot_of(key: str) -> str:
    """The robot a node belongs to: a submap's (``robot/epoch/submap``), else the node itself (a map file)."""
    parts = key.split("/")
    return parts[0] if len(parts) == 3 else key
