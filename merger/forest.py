"""The spanning forest's paths, without a search per question.

The pose graph checks every integration that closes a cycle against the forest's path between its
two submaps, with a tolerance that grows with what the path's links can have drifted
(:meth:`~fleetmap.merger.chains.ChainGraph._cycle_tolerance`), and counts, for the culprit rule,
the tree edges on every such path. Found by a breadth-first search and a walk along the path for
each loop, that cost grew with the whole map at every step (issue 49). Here the forest is rooted
once: each submap knows its parent edge, its depth and sums over the links from its root, so a
path is a climb from both ends to their lowest common ancestor, and the drift of a path is a
difference of sums.

The drift (three standard deviations, first order: a link's heading error turns everything after
it about the link's start) of a path ``a -> b`` is ``var_t = sum(0.5 tr(C_t) + c |p_b - s|^2)`` and
``var_r = sum(c)`` over the links on it, with ``C_t`` a link's translation covariance, ``c`` its
heading variance and ``s`` where the path enters it. Expanded, ``|p_b - s|^2 = |p_b|^2 - 2 p_b.s +
|s|^2``, so sums of ``c``, ``c s`` and ``c |s|^2`` from the root suffice: one set for the links the
path climbs (it enters each at its child end) and one for those it descends (at its parent end).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from fleetmap.merger.graph import Component, Edge
from fleetmap.shared.core.geometry import Array, Transform2D

_Sums = tuple[float, float, float, float, float, float, float, float, int]
"""From a node's root down to it: c, then c x, c y, c |s|^2 entered at the child end (a path that
climbs), the same at the parent end (one that descends), 0.5 tr(C_t), and the integrations."""

_ZERO: _Sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)


class RootedForest:
    """A spanning forest rooted at the first key of each tree (``keys`` in order), with its links'
    covariances (both ways round, by the edge's two keys)."""

    def __init__(
        self, keys: Iterable[str], adjacency: dict[str, list[Edge]], covariances: dict[tuple[str, str], Array]
    ) -> None:
        self.parent: dict[str, Edge | None] = {}
        """The tree edge from each node's parent to it (None: a root)."""
        self.depth: dict[str, int] = {}
        self.root: dict[str, str] = {}
        self.at: dict[str, Transform2D] = {}
        """Each node's pose in its root's frame (along the tree's edges)."""
        self.joins_above: dict[str, frozenset[tuple[str, str]]] = {}
        """The keys of the integrations on each node's path from its root: a node is on the far
        side of a join from its root exactly where the join is among them."""
        self._sums: dict[str, _Sums] = {}
        self._jumps: dict[str, list[str]] = {}
        """Each node's ancestors 1, 2, 4, ... levels up (binary lifting: a lowest common ancestor
        in a climb of log(depth) jumps, not one edge at a time up a robot's long chain)."""
        for start in keys:
            if start in self.depth:
                continue
            self.parent[start], self.depth[start], self.root[start] = None, 0, start
            self.at[start], self._sums[start] = Transform2D.identity(), _ZERO
            self.joins_above[start] = frozenset()
            self._jumps[start] = []
            queue, i = [start], 0
            while i < len(queue):
                k = queue[i]
                i += 1
                for e in adjacency[k]:
                    u = e.b
                    if u in self.depth:
                        continue
                    self.parent[u], self.depth[u], self.root[u] = e, self.depth[k] + 1, start
                    self.at[u] = self.at[k].compose(e.transform)
                    self._sums[u] = _add(self._sums[k], e, covariances, self.at[u], self.at[k])
                    self.joins_above[u] = self.joins_above[k] if e.link else self.joins_above[k] | {e.key()}
                    self._hang(u, k)
                    queue.append(u)

    def add_root(self, key: str) -> None:
        """A new tree of one node."""
        self.parent[key], self.depth[key], self.root[key] = None, 0, key
        self.at[key], self._sums[key] = Transform2D.identity(), _ZERO
        self.joins_above[key] = frozenset()
        self._jumps[key] = []

    def add_leaf(self, e: Edge, covariances: dict[tuple[str, str], Array]) -> None:
        """Hang ``e.b`` (a tree of one node) from ``e.a``: the forest as if rooted again, for the
        cost of one node."""
        k, u = e.a, e.b
        self.parent[u], self.depth[u], self.root[u] = e, self.depth[k] + 1, self.root[k]
        self.at[u] = self.at[k].compose(e.transform)
        self._sums[u] = _add(self._sums[k], e, covariances, self.at[u], self.at[k])
        self.joins_above[u] = self.joins_above[k] if e.link else self.joins_above[k] | {e.key()}
        self._hang(u, k)

    def _hang(self, u: str, parent: str) -> None:
        """``u``'s jumps, its parent's known: 2^j levels up is 2^(j-1) up from 2^(j-1) up."""
        jumps = self._jumps[u] = [parent]
        while len(jumps) <= len(self._jumps[jumps[-1]]):
            jumps.append(self._jumps[jumps[-1]][len(jumps) - 1])

    def lowest_common(self, a: str, b: str) -> str | None:
        """The lowest common ancestor of two nodes (None: in different trees)."""
        if self.root.get(a) is None or self.root.get(a) != self.root.get(b):
            return None
        if self.depth[a] < self.depth[b]:
            a, b = b, a
        climb, j = self.depth[a] - self.depth[b], 0
        while climb:
            if climb & 1:
                a = self._jumps[a][j]
            climb, j = climb >> 1, j + 1
        if a == b:
            return a
        for j in reversed(range(len(self._jumps[a]))):
            # a and b at one depth have as many jumps; one past a's root is no jump
            if j < len(self._jumps[a]) and self._jumps[a][j] != self._jumps[b][j]:
                a, b = self._jumps[a][j], self._jumps[b][j]
        return self._jumps[a][0]

    def path_keys(self, a: str, b: str) -> list[tuple[str, str]]:
        """The keys of the tree edges on the path from a to b (empty if not connected)."""
        top = self.lowest_common(a, b)
        if top is None:
            return []
        keys = []
        for k in (a, b):
            while k != top:
                e = self.parent[k]
                assert e is not None
                keys.append(e.key())
                k = e.a
        return keys

    def drift(self, a: str, b: str) -> tuple[int, float, float]:
        """The path from a to b: its integrations, and three standard deviations (m, rad) of what
        its links can have drifted (the module docstring)."""
        top = self.lowest_common(a, b)
        if top is None:
            raise ValueError(f"{a} and {b} are not in one tree")
        sa, sb, st = self._sums[a], self._sums[b], self._sums[top]
        c = (sa[0] - st[0]) + (sb[0] - st[0])
        cx = (sa[1] - st[1]) + (sb[4] - st[4])
        cy = (sa[2] - st[2]) + (sb[5] - st[5])
        c2 = (sa[3] - st[3]) + (sb[6] - st[6])
        tr = (sa[7] - st[7]) + (sb[7] - st[7])
        end = self.at[b]
        var_t = tr + c * (end.x * end.x + end.y * end.y) - 2.0 * (end.x * cx + end.y * cy) + c2
        joins = sa[8] + sb[8] - 2 * st[8]
        return joins, 3.0 * math.sqrt(max(var_t, 0.0)), 3.0 * math.sqrt(max(c, 0.0))

    def spread(self, a: str, b: str) -> tuple[float, float] | None:
        """Three standard deviations (m, rad) of where the forest can have put b relative to a:
        :meth:`drift` (the integrations on the path add nothing: the walls fix them); None if
        they are not in one tree."""
        if a not in self.root or self.root.get(a) != self.root.get(b):
            return None
        _, drift_t, drift_r = self.drift(a, b)
        return drift_t, drift_r


def _add(
    sums: _Sums, e: Edge, covariances: dict[tuple[str, str], Array], child: Transform2D, parent: Transform2D
) -> _Sums:
    cov = covariances.get((e.a, e.b)) if e.link else None
    if cov is None:
        return (*sums[:8], sums[8] + (not e.link))
    c = float(cov[2, 2])
    return (
        sums[0] + c,
        sums[1] + c * child.x,
        sums[2] + c * child.y,
        sums[3] + c * (child.x * child.x + child.y * child.y),
        sums[4] + c * parent.x,
        sums[5] + c * parent.y,
        sums[6] + c * (parent.x * parent.x + parent.y * parent.y),
        sums[7] + 0.5 * float(cov[0, 0] + cov[1, 1]),
        sums[8],
    )


@dataclass
class KeptForest:
    """A solve's spanning forest and what it rests on, kept for the next solve
    (:meth:`~fleetmap.merger.posegraph.PoseGraph._kept_solve`): the tree, its loop closures and the
    integrations it rejected; each submap's group (``root``), pose in its group's frame (``rel``)
    and the groups' members; the tree's adjacency, both ways round, and the forest rooted."""

    tree: list[Edge]
    loops: list[Edge]
    conflicts: list[Edge]
    """The integrations the forest rejected: joins refused, cycles that do not close."""
    root: dict[str, str]
    rel: dict[str, Transform2D]
    members: dict[str, list[str]]
    adjacency: dict[str, list[Edge]]
    forest: RootedForest
    apart: list[Edge] = field(default_factory=list)
    """The integrations between two trees: joins refused, and ambiguous ones (which join nothing)."""
    rejected: list[Edge] = field(default_factory=list)
    """Every integration the solve rejected (the conflicts, the culprits, those the refined poses
    disagree with)."""
    contested: bool = False
    """Whether the culprit vote, counting every conflict, accuses a tree join (:func:`~fleetmap.merger.graph._culprit`):
    then only the accusers' groups decide it, and they may decide otherwise as they grow."""
    excluded: set[tuple[str, str]] = field(default_factory=set)
    """The integrations left out of the forest as culprits or joins their groups do not bear out."""
    edges: dict[tuple[str, str], Edge] = field(default_factory=dict)
    """Every edge the forest was built from, by key."""
    aside: dict[tuple[str, str], Edge] = field(default_factory=dict)
    """The integrations left out (``excluded``, and those the refined poses disagree with), by key."""
    versions: dict[str, int] = field(default_factory=dict)
    """Every submap's version when the forest was built."""
    components: dict[str, Component] = field(default_factory=dict)
    """The refined components, by their group's root."""
    unlooked: set[str] = field(default_factory=set)
    """The submaps new or with a new version whose pairs across their group's joins have not been
    looked at since (:meth:`~fleetmap.merger.posegraph.PoseGraph._kept_joins_hold`)."""
    looked: dict[str, int] = field(default_factory=dict)
    """Each submap's version when its pairs across its group's joins were last looked at."""
