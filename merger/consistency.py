"""Joins accepted by pairwise consistency: the integrations between two groups that agree decide.

Pairwise consistency maximisation (Mangelson, Dominguez, Eustice & Everett, ICRA 2018, section
IV), as Kimera-Multi, DOOR-SLAM and Swarm-SLAM accept inter-robot loop closures. Two integrations
between the same two groups of submaps (each group a tree of the forest: a robot's chain and what
joined it so far) are *consistent* when the cycle they make with the groups' own trees closes
within the chi-square bound of its covariance: from one integration's submap in group a, across it
to group b, along b's tree to the other integration's submap there, back across the other
integration, and along a's tree home. The covariance is the cycle tolerance's
(:meth:`~fleetmap.merger.chains.ChainGraph._cycle_tolerance`: the base tolerance per integration as
three standard deviations, and what the trees' links can have drifted,
:meth:`~fleetmap.merger.forest.RootedForest.drift`). The integrations between the two groups and
their consistency make a graph; a clique is a set of integrations that all agree (Mangelson et al.,
problem (7); the maximal cliques found exactly by ``networkx``), weighed here by the paper's
transformation value, the weight the forest orders its edges by.

A join holds (:meth:`ConsistencyJudge._join_accepted`) only if its integration is in the heaviest
set that agrees, among the integrations between the two groups that the validity rule on the
groups as wholes has not refused (:meth:`~fleetmap.merger.joins.JoinJudge._join_holds`). So one
integration that scores best joins nothing where lighter ones that agree with each other through
the robots' own links, together heavier, put the groups elsewhere: a building that repeats itself
(racks, doors at even spacing) matches one pair of submaps as well one bay along, and the walls
near that pair bear it out, while independent integrations elsewhere along the two chains do not.

The second integration that confirms a join may also be a pair registered near it (the wholes
rule's :data:`~fleetmap.merger.joins.JOIN_SUPPORT`). Requiring two pose-free integrations that agree,
Mangelson's form, was measured and not kept: aces cut in 8 left two groups of robots apart (84.8 %
of cross-robot relations joined, against 100 %), a right join that no pose-free integration of the
pairs it makes meet found again (record 014).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from typing import Any

import networkx as nx
from fleetmap.merger.forest import RootedForest
from fleetmap.merger.graph import Edge
from fleetmap.merger.rivals import RivalJudge
from fleetmap.shared.core.geometry import Transform2D, wrap_scalar
from scipy.special import chdtri

log = logging.getLogger(__name__)

CONSISTENT_CHI2 = float(chdtri(3, 0.01))  # the inverse of chi-square's upper tail (scipy.stats takes 0.6 s to import)
"""The bound on a consistent cycle's squared Mahalanobis distance: 99 % of a chi-square with three
degrees of freedom (x, y, heading; Mangelson et al. IV-B)."""


def cycle_distance(error: Transform2D, tol_t: float, tol_r: float) -> float:
    """The squared Mahalanobis distance of a cycle's error, its covariance the cycle tolerance's:
    ``tol_t`` and ``tol_r`` three standard deviations of its translation (each axis) and heading."""
    st, sr = tol_t / 3.0, tol_r / 3.0
    return (error.x * error.x + error.y * error.y) / (st * st) + wrap_scalar(error.theta) ** 2 / (sr * sr)


class ConsistencyJudge(RivalJudge):
    """:class:`~fleetmap.merger.rivals.RivalJudge` with the join's pairwise consistency (the module)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # as ChainGraph's
        super().__init__(*args, **kwargs)
        self.refused_whole: set[tuple[object, ...]] = set()
        """The integrations whose join of two groups the validity rule on them as wholes refused
        since the forest was last built from nothing (by :func:`_agreed_key`): no longer candidates
        for a consistent set (:meth:`_consistent_join`), or a heavier set, refused, would hold every
        lighter one back."""
        self.outweighed: set[tuple[object, ...]] = set()
        """The integrations between two groups outside the heaviest set of them that agrees (two or
        more: a lone heavier integration outweighs nothing) that agree with nothing outside it, since
        the forest was last built from nothing (by :func:`_agreed_key`): no rival alignment of a
        join (:meth:`~fleetmap.merger.rivals.RivalJudge._rival_join`)."""
        self._agreed: set[tuple[object, ...]] = set()
        """The integrations a consistent set once joined two groups by (:meth:`_consistent_join`),
        by :func:`_agreed_key`: from then on the join is judged as the forest's other joins are
        (its groups as wholes, the culprit rule), not by its set again."""

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._agreed = {k for k in self._agreed if key not in k[:2]}
        self.refused_whole = {k for k in self.refused_whole if key not in k[:2]}
        self.outweighed = {k for k in self.outweighed if key not in k[:2]}

    def _outweighed(self, f: Edge) -> bool:
        return _agreed_key(f) in self.outweighed

    def _join_accepted(
        self,
        e: Edge,
        group_a: list[str],
        group_b: list[str],
        rel: dict[str, Transform2D],
        adjacency: dict[str, list[Edge]],
        by_node: dict[str, list[Edge]] | None = None,
    ) -> bool:
        """Whether an integration may join two groups: the paper's validity rule on them as wholes
        (:meth:`~fleetmap.merger.joins.JoinJudge._join_holds`), and pairwise consistency
        (:meth:`_consistent_join`; ``by_node``: every integration by each of its submaps, gathered
        from the graph if not given)."""
        if not self._join_holds(e, group_a, group_b, rel, adjacency):
            self.refused_whole.add(_agreed_key(e))
            return False
        if by_node is None:
            by_node = integrations_by_node(self._edges.values())
        return self._consistent_join(e, group_a, group_b, adjacency, by_node)

    def _consistent_join(
        self,
        e: Edge,
        group_a: list[str],
        group_b: list[str],
        adjacency: dict[str, list[Edge]],
        by_node: dict[str, list[Edge]],
    ) -> bool:
        """Whether ``e`` is in the heaviest set of the integrations between the two groups that all
        agree (the module), those the groups as wholes refused left out."""
        key = _agreed_key(e)
        if key in self._agreed:
            return True
        in_a, in_b = set(group_a), set(group_b)
        if e.a not in in_a:
            e = e.reversed()
        between = [f for f in _between(e, in_a, in_b, by_node) if f is e or _agreed_key(f) not in self.refused_whole]
        if len(between) == 1:
            self._agreed.add(key)
            return True
        forest = RootedForest([e.a, e.b], adjacency, self._link_covariances)
        consistent = nx.Graph()
        consistent.add_nodes_from(range(len(between)))
        implied = [forest.at[f.a].compose(f.transform).compose(forest.at[f.b].inverse()) for f in between]
        for i, f in enumerate(between):
            for j in range(i + 1, len(between)):
                if self._agree(f, between[j], implied[i], forest):
                    consistent.add_edge(i, j)
        # the heaviest set that agrees, by the paper's transformation value (a tie: the one that holds e)
        chosen = max(
            (frozenset(c) for c in nx.find_cliques(consistent)),
            key=lambda c: (sum(between[i].value for i in c), 0 in c),
        )
        members = [between[i] for i in sorted(chosen)]
        if len(chosen) > 1:
            # a set that agrees outweighs an integration that agrees with nothing beyond it (a lone
            # alignment); two sets that each agree are two alignments, for the rival rule to weigh
            self.outweighed.update(
                _agreed_key(f)
                for i, f in enumerate(between)
                if i not in chosen and not (set(consistent.neighbors(i)) - chosen)
            )
        if 0 not in chosen:
            log.debug(
                "join %s-%s refused: the integrations between its groups that agree with each other weigh"
                " more elsewhere (%s)",
                e.a,
                e.b,
                ", ".join(f"{f.a}-{f.b}" for f in members),
            )
            return False
        self._agreed.update(_agreed_key(f) for f in members)
        return True

    def _agree(self, f: Edge, g: Edge, implied_f: Transform2D, forest: RootedForest) -> bool:
        """Whether two integrations between the same two groups (each from group a to group b) make
        a cycle that closes within :data:`CONSISTENT_CHI2` (the module)."""
        # g's submap in b, put where f puts group b, seen from where g puts it
        error = forest.at[g.a].compose(g.transform).inverse().compose(implied_f).compose(forest.at[g.b])
        joins_a, drift_ta, drift_ra = forest.drift(g.a, f.a)
        joins_b, drift_tb, drift_rb = forest.drift(f.b, g.b)
        base_t, base_r = self._tolerance(2 + joins_a + joins_b)
        tol_t = math.sqrt(base_t * base_t + drift_ta * drift_ta + drift_tb * drift_tb)
        tol_r = math.sqrt(base_r * base_r + drift_ra * drift_ra + drift_rb * drift_rb)
        return cycle_distance(error, tol_t, tol_r) <= CONSISTENT_CHI2


def integrations_by_node(edges: Iterable[Edge]) -> dict[str, list[Edge]]:
    """The integrations (not the links) among ``edges``, by each of their two submaps."""
    by_node: dict[str, list[Edge]] = {}
    for e in edges:
        if not e.link:
            by_node.setdefault(e.a, []).append(e)
            by_node.setdefault(e.b, []).append(e)
    return by_node


def _agreed_key(e: Edge) -> tuple[object, ...]:
    """An integration's key in :class:`ConsistencyJudge`'s sets: its submaps in order, versions and transform."""
    f = e if e.a <= e.b else e.reversed()
    t = f.transform
    return (f.a, f.b, f.versions, round(t.x, 3), round(t.y, 3), round(t.theta, 4))


def _between(e: Edge, in_a: set[str], in_b: set[str], by_node: dict[str, list[Edge]]) -> list[Edge]:
    """The valid integrations between two groups, each from group a to group b, ``e`` first."""
    found: dict[tuple[str, str], Edge] = {e.key(): e}
    small = in_a if len(in_a) <= len(in_b) else in_b
    for k in small:
        for f in by_node.get(k, ()):
            if f.link or not f.valid or f.key() in found:
                continue
            if f.a in in_a and f.b in in_b:
                found[f.key()] = f
            elif f.b in in_a and f.a in in_b:
                found[f.key()] = f.reversed()
    return list(found.values())
