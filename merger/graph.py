"""The map graph: partial maps and the paper's integrations between them.

Nodes are partial maps (a robot's submap or local map, a map file); edges are integration
attempts, each with its transform, transformation value and validity. The graph is incremental: a
new map is integrated with the existing ones, most similar first (a pairwise geometric histogram of
their walls, fleetmap.shared.core.descriptor), and pairs already integrated are never integrated
again.

The merge order nobody gave is read off the graph by :class:`~fleetmap.merger.posegraph.PoseGraph`
(a maximum spanning forest of valid integrations, each join borne out by the maps it joins, every
other edge checked against its cycle, then all poses refined together); this module holds what
that solve is made of: the forest's union, tree paths and the cycle-vote culprit rule. Maps with
no links (``fleetmap merge`` on map files) are solved there the same way, without links.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from fleetmap.merger.executor import Indexes, PairJob, PairResult, reference_of, run_pair
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.descriptor import pairwise_histogram, similarity
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.integration import Window, index_for
from fleetmap.shared.core.mapgrid import MapIndex, viewpoints_of
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.simplify import SIMPLIFY_TOLERANCE, simplify
from fleetmap.shared.core.tracking import ReferenceMap
from fleetmap.shared.core.validity import seen_from_enough_places
from fleetmap.shared.errors import BadInput

log = logging.getLogger(__name__)

CYCLE_TRANSLATION_TOLERANCE = 0.30
"""A non-tree edge that disagrees with its tree path by more than this (m) ..."""
CYCLE_ROTATION_TOLERANCE = 0.087
"""... or this (rad, 5 degrees), times the square root of the path's hops, is rejected
(docs/decisions/002-pose-graph.md)."""
EDGE_SIGMA_TRANSLATION = 0.05
"""How far (m) a wall of one map may lie from the same wall of another when their poses are refined
together: the scale of an edge's information (002) ..."""
EDGE_SIGMA_ROTATION = 0.01
"""... and an edge weighed by its value alone: its rotation's standard deviation at unit weight (rad)."""
DESCRIPTOR_STEP = 0.5
"""The cheap descriptor that ranks far candidates bins how far two walls lie apart in steps of this
(m) ..."""
DESCRIPTOR_REACH = 12.0
"""... up to this (m), about a submap's extent: it tells a corridor from a hall (aces cut in 8: first
overlapping candidate in the top 3 for 70 % of submaps, against 23 % by wall directions; 002)."""
MAX_CANDIDATES = 0
"""``fleetmap merge``: a new map is integrated with at most this many existing maps, most similar
first (0: all; a user's few map files each meet every other)."""


@dataclass(frozen=True)
class Edge:
    """An integration attempt: ``transform`` maps b's frame into a's (b's pose in a)."""

    a: str
    b: str
    transform: Transform2D
    value: float
    valid: bool
    runner_up: float = 0.0
    seconds: float = 0.0
    versions: tuple[int, int] = (0, 0)
    violation: float = 0.0
    """Wall length the transform puts in the other map's seen free space (m)."""
    solid_violation: float | None = None
    """The part of it the validity rule limits (:attr:`Integration.solid_violation`; None: all)."""
    information: tuple[float, ...] | None = None
    """How firmly the two maps' walls fix ``transform`` (row-major 3x3,
    :func:`~fleetmap.shared.core.refine.fit_information`; found for an edge integrated valid): along a
    corridor the walls leave the translation free, and the poses refined together take it from
    the other edges. None: not known (an edge integrated invalid,
    ``EDGE_INFORMATION`` off, fewer than two parallel pairs matched, or an
    edge given without it); such an edge weighs by value alone, the same in every direction."""
    link: bool = False
    """A robot's own link between consecutive submaps (its tracking), not an integration: its
    information is the inverse of the link's covariance, and no cycle check rejects it."""
    rivals: tuple[Transform2D, ...] = ()
    """The clearly different alignments that scored next best (:attr:`Integration.rivals`), best
    first: where a repetitive building puts b too."""

    @property
    def limited_violation(self) -> float:
        """The wall in seen free space that counts against the transform's validity (m)."""
        return self.violation if self.solid_violation is None else self.solid_violation

    @property
    def ambiguity(self) -> float:
        """The best clearly different transformation's score over this one's (value less
        violation; inf when that is not positive)."""
        score = self.value - self.violation
        return self.runner_up / score if score > 0 else math.inf

    def reversed(self) -> Edge:
        """The same edge from b to a (made once per edge: every solve's forest asks again)."""
        return self._reversed

    @cached_property
    def _reversed(self) -> Edge:
        inverse = self.transform.inverse()
        rivals = tuple(t.inverse() for t in self.rivals)
        information = None
        if self.information is not None:
            # The inverse is its own inverse: T's parameters move by J(T^-1) times T^-1's.
            j = _inverse_jacobian(inverse)
            information = tuple((j.T @ np.array(self.information).reshape(3, 3) @ j).ravel().tolist())
        return replace(
            self,
            a=self.b,
            b=self.a,
            transform=inverse,
            versions=self.versions[::-1],
            information=information,
            rivals=rivals,
        )

    def key(self) -> tuple[str, str]:
        return (self.a, self.b) if self.a <= self.b else (self.b, self.a)


@dataclass
class _Node:
    map: SegmentMap
    order: int
    version: int
    descriptor: Array | None
    """Its pairwise geometric histogram (:meth:`MapGraph.descriptor`), built on first use."""
    work: SegmentMap
    """The map as integrated and fused: simplified (fleetmap.shared.core.simplify) unless it is a scan."""
    index: MapIndex | None = None
    """Its grid index for the large-map path, built on first use and kept."""


@dataclass(frozen=True)
class Component:
    """One global map: its anchor, members, their poses in the anchor's frame, the fused segments."""

    anchor: str
    members: tuple[str, ...]
    poses: dict[str, Transform2D]
    segments: Array = field(repr=False)


@dataclass(frozen=True)
class MergeResult:
    poses: dict[str, Transform2D | None]
    """Every map's pose in its component's anchor frame; None for a map merged with nothing."""
    components: list[Component]
    """Largest first (most members, then most segment length)."""
    tree: list[Edge]
    loops: list[Edge]
    rejected: list[Edge]
    """Valid edges that disagreed with the rest of the graph."""

    def component_of(self, key: str) -> Component | None:
        return next((c for c in self.components if key in c.members), None)


class _GraphIndexes(Indexes):
    """The graph's own indexes and registration grids, as :func:`~fleetmap.merger.executor.run_pair`
    asks for them (built once per version, kept with the node)."""

    def __init__(self, graph: MapGraph) -> None:
        self._graph = graph

    def get(self, key: str, version: int, kind: str, build: Callable[[], object], content: object = None) -> object:
        if key not in self._graph or self._graph.version_of(key) != version:
            return build()  # a job of a version the graph no longer holds
        return self._graph._index(key) if kind == "index" else self._graph.reference(key)


def _same_geometry(a: SegmentMap, b: SegmentMap) -> bool:
    """Whether two versions of a map hold the same segments, seen from the same viewpoints."""
    return (
        a.ordered == b.ordered
        and a.oriented == b.oriented
        and np.array_equal(a.segments, b.segments)
        and np.array_equal(viewpoints_of(a), viewpoints_of(b))
    )


def _disagreement(a: Transform2D, b: Transform2D) -> tuple[float, float]:
    return a.distance(b)


class MapGraph:
    """Partial maps and their pairwise integrations; :class:`~fleetmap.merger.posegraph.PoseGraph`
    adds the robots' links and solves them into global maps."""

    def __init__(
        self,
        integration: IntegrationParams | None = None,
        merge: MergeParams | None = None,
        anchor: str = "first",
    ) -> None:
        if anchor not in ("first", "largest"):
            raise BadInput("anchor", f"expected 'first' or 'largest', got {anchor!r}")
        self.integration = integration or IntegrationParams()
        self.merge = merge or MergeParams()
        self.anchor = anchor
        self.tracking = TrackingParams()
        """The registration of an integration near a prediction (:meth:`align_pair`)."""
        self._nodes: dict[str, _Node] = {}
        self._edges: dict[tuple[str, str], Edge] = {}
        self.edits = 0
        """Changes to the graph's maps (added or removed), integrations and links so far: a solve
        whose graph has had none since the last one holds every edge it held
        (:meth:`~fleetmap.merger.posegraph.PoseGraph.solve`)."""
        self.rivalled: dict[str, set[tuple[str, str]]] = {}
        """The integrations at each map that are invalid and have rivals: whether such a one is
        ambiguous depends on its maps' versions, not on the edge alone
        (:meth:`~fleetmap.merger.spanning.ForestBuilder._ambiguous`)."""
        self._counter = 0
        self._references: dict[str, tuple[int, ReferenceMap]] = {}

    # -- nodes and edges -------------------------------------------------------------------
    def __contains__(self, key: str) -> bool:
        return key in self._nodes

    def __len__(self) -> int:
        return len(self._nodes)

    @property
    def keys(self) -> list[str]:
        return sorted(self._nodes, key=lambda k: self._nodes[k].order)

    def map_of(self, key: str) -> SegmentMap:
        return self._nodes[key].map

    def version_of(self, key: str) -> int:
        return self._nodes[key].version

    @property
    def edges(self) -> list[Edge]:
        return list(self._edges.values())

    def descriptor(self, key: str) -> Array:
        """The cheap descriptor of a map's walls that ranks candidates (a pairwise geometric
        histogram, :func:`~fleetmap.shared.core.descriptor.pairwise_histogram`), for its version."""
        node = self._nodes[key]
        if node.descriptor is None:
            node.descriptor = pairwise_histogram(node.map.segments, DESCRIPTOR_STEP, DESCRIPTOR_REACH)
        return node.descriptor

    def candidates_for(self, key: str) -> list[str]:
        """Existing maps to integrate ``key`` with, most similar first (at most :data:`MAX_CANDIDATES`; 0: all)."""
        h = self.descriptor(key)
        others = [k for k in self.keys if k != key]
        ranked = sorted(others, key=lambda k: (-similarity(self.descriptor(k), h), self._nodes[k].order))
        limit = MAX_CANDIDATES
        return ranked[:limit] if limit > 0 else ranked

    def put_map(self, key: str, segment_map: SegmentMap, version: int = 0, keep_edges: bool = False) -> bool:
        """Add a map or replace it with a newer version (its old edges go, unless the new version
        holds the same segments and viewpoints: then they stand). False if not newer.

        With ``keep_edges`` the old version's edges stand until :meth:`integrate_pair` replaces
        them (the live merger integrates a new version over several steps; a local map's frame is
        its first scan's whatever the version, so they stay about right, and the map does not drop
        out of the global map meanwhile)."""
        if len(segment_map) == 0:
            raise BadInput(key, "the map is empty (no segments)")
        node = self._nodes.get(key)
        if node is not None:
            if version <= node.version:
                return False
            if _same_geometry(node.map, segment_map):
                # The same walls seen from the same places (an epoch's last version, which only
                # says that the robot has left it): its integrations with the version it repeats
                # stand, their versions move on (one kept from an older version stays old).
                old = node.version
                node.version = version
                self.edits += 1
                for k, e in list(self._edges.items()):
                    if key in k:
                        va, vb = e.versions
                        if (va if e.a == key else vb) == old:
                            self._edges[k] = replace(e, versions=(version, vb) if e.a == key else (va, version))
                return True
            node.map, node.version = segment_map, version
            node.descriptor = None
            node.work, node.index = self._work(key, segment_map), None
            if not keep_edges:
                for k in [k for k in self._edges if key in k]:
                    self._put_edge(k, None)
            return True
        self.edits += 1
        self._nodes[key] = _Node(
            segment_map,
            self._counter,
            version,
            None,
            self._work(key, segment_map),
        )
        self._counter += 1
        return True

    def _work(self, key: str, m: SegmentMap) -> SegmentMap:
        del key
        tol = SIMPLIFY_TOLERANCE
        return simplify(m, tol) if tol > 0 and not m.ordered else m

    def _index(self, key: str) -> MapIndex:
        node = self._nodes[key]
        if node.index is None:
            node.index = index_for(node.work, self.integration)
        return node.index

    def remove_map(self, key: str) -> None:
        self.edits += 1
        self._nodes.pop(key, None)
        self._references.pop(key, None)
        for k in [k for k in self._edges if key in k]:
            self._put_edge(k, None)
        self.rivalled.pop(key, None)

    def add_edge(self, edge: Edge) -> None:
        """Record an integration (computed here or elsewhere, e.g. restored from a recording)."""
        if edge.a not in self._nodes or edge.b not in self._nodes:
            raise BadInput(f"edge {edge.a}-{edge.b}", "names a map that is not in the graph")
        self._put_edge(edge.key(), edge)

    def _put_edge(self, key: tuple[str, str], edge: Edge | None) -> None:
        """Record an integration by its key, or remove it (None), counted in :attr:`edits`."""
        self.edits += 1
        if edge is None:
            self._edges.pop(key, None)
        else:
            self._edges[key] = edge
        rivalled = edge is not None and not edge.valid and bool(edge.rivals)
        for k in key:
            if rivalled:
                self.rivalled.setdefault(k, set()).add(key)
            elif k in self.rivalled:
                self.rivalled[k].discard(key)

    def edge(self, a: str, b: str) -> Edge | None:
        e = self._edges.get((a, b) if a <= b else (b, a))
        if e is None:
            return None
        return e if e.a == a else e.reversed()

    def integrate_pair(self, a: str, b: str) -> Edge:
        """INTEGRATE(a, b) unless this pair (at these versions) is already known."""
        known = self.edge(a, b)
        if known is not None and self.is_current(a, b):
            return known
        job = self.pair_job(a, b)
        return self.take(job, run_pair(job, self.indexes))

    def pair_job(self, a: str, b: str, predicted: Transform2D | None = None, window: Window | None = None) -> PairJob:
        """The integration of b on a at their current versions, near ``predicted`` (b's frame in
        a's) or pose-free (within ``window``, if given), as a job any executor runs
        (:mod:`fleetmap.merger.executor`), with the indexes of the two maps the graph holds already."""
        na, nb = self._nodes[a], self._nodes[b]
        given: dict[str, object] = {}
        if na.index is not None:
            given["index_a"] = na.index
        if nb.index is not None:
            given["index_b"] = nb.index
        reference = self._references.get(a)
        if reference is not None and reference[0] == na.version:
            given["reference_a"] = reference[1]
        return PairJob(
            a, b, (na.version, nb.version), na.map, nb.map, na.work, nb.work, predicted, self.integration,
            self.tracking, self.merge, given, window,
        )  # fmt: skip

    def align_pair(self, a: str, b: str, predicted: Transform2D) -> Edge:
        """b's walls registered on a's near ``predicted`` (b's frame in a's) and valued as an
        integration (:func:`~fleetmap.shared.core.near.align_near`); the edge replaces any known."""
        job = self.pair_job(a, b, predicted)
        return self.take(job, run_pair(job, self.indexes))

    def reference(self, key: str) -> ReferenceMap:
        """The registration grid of a node's walls (built once per version)."""
        node = self._nodes[key]
        held = self._references.get(key)
        if held is None or held[0] != node.version:
            held = self._references[key] = (node.version, reference_of(node.map))
        return held[1]

    def take(self, job: PairJob, result: PairResult) -> Edge:
        """Record a job's result as the pair's edge (replacing any known) and return it; a result
        for versions the graph no longer holds is returned, not recorded."""
        r = result.integration
        near = job.predicted is not None
        e = Edge(
            job.a,
            job.b,
            result.transform,
            r.value,
            r.valid,
            0.0 if near else r.runner_up,
            r.seconds,
            job.versions,
            r.violation,
            r.solid_violation,
            result.information,
            rivals=() if near else tuple(t for t, _ in r.rivals),
        )
        na, nb = self._nodes.get(job.a), self._nodes.get(job.b)
        if na is not None and nb is not None and (na.version, nb.version) == job.versions:
            self._put_edge(e.key(), e)
        self.keep_built(job.a, job.b, job.versions, result.built)
        return e

    def keep_built(self, a: str, b: str, versions: tuple[int, int], built: dict[str, Any]) -> None:
        """Keep the indexes a worker built for a job on ``a`` and ``b`` at ``versions`` (of the
        versions the graph holds), so that nothing builds them again."""
        na, nb = self._nodes.get(a), self._nodes.get(b)
        if na is not None and na.version == versions[0]:
            if na.index is None and "index_a" in built:
                na.index = built["index_a"]
            held = self._references.get(a)
            if "reference_a" in built and (held is None or held[0] != na.version):
                self._references[a] = (na.version, built["reference_a"])
        if nb is not None and nb.version == versions[1] and nb.index is None and "index_b" in built:
            nb.index = built["index_b"]

    @property
    def indexes(self) -> Indexes:
        """The graph's search indexes and registration grids, as an integration job run in this
        process asks for them (:func:`~fleetmap.merger.executor.run_pair`)."""
        return _GraphIndexes(self)

    def add_map(self, key: str, segment_map: SegmentMap, version: int = 0) -> list[Edge]:
        """Add (or update) a map and integrate it with the existing maps, most similar first."""
        if not self.put_map(key, segment_map, version):
            return []
        return [self._oriented_pair(other, key) for other in self.pairs_for(key)]

    def pairs_for(self, key: str) -> list[str]:
        """The maps to integrate ``key`` with, most similar first: :meth:`candidates_for` less
        those it cannot merge with (:meth:`_too_few_places`)."""
        mine = self._nodes[key].map
        return [other for other in self.candidates_for(key) if not self._too_few_places(self._nodes[other].map, mine)]

    def is_current(self, a: str, b: str) -> bool:
        """Whether the pair's edge is known at both maps' current versions."""
        known = self.edge(a, b)
        return known is not None and known.versions == (self._nodes[a].version, self._nodes[b].version)

    def integrate_pair_once(self, x: str, y: str) -> Edge | None:
        """INTEGRATE the pair, always one way (see :meth:`_oriented_pair`); None if its edge is
        already known at these versions."""
        job = self.job_once(x, y)
        return None if job is None else self.take(job, run_pair(job, self.indexes))

    def job_once(self, x: str, y: str, window: Window | None = None) -> PairJob | None:
        """:meth:`integrate_pair_once` as a job for an executor (within ``window``, for the pair one
        way round, if given); None if the pair's edge is already known at these versions."""
        if self.is_current(x, y):
            return None
        a, b = (x, y) if x < y else (y, x)  # one way, as _oriented_pair
        return self.pair_job(a, b, window=window)

    def seen_enough(self, a: str, b: str) -> bool:
        """Whether two maps can merge at all (see :meth:`_too_few_places`)."""
        return not self._too_few_places(self._nodes[a].map, self._nodes[b].map)

    def _too_few_places(self, a: SegmentMap, b: SegmentMap) -> bool:
        """Whether two partial maps cannot merge whatever their geometry: one was seen from fewer
        than ``VALID_MIN_MAP_SCANS`` places (fleetmap.shared.core.integration's rule). Such a pair is
        not integrated (a new epoch's first versions, a robot that saw its map from one place)."""
        return not (a.ordered or b.ordered or seen_from_enough_places(a, b, self.integration))

    def _oriented_pair(self, x: str, y: str) -> Edge:
        # The first key (in sorted order) is S1: INTEGRATE(a, b) is not exactly the inverse of
        # INTEGRATE(b, a), so the pair is always integrated one way, whatever order the maps
        # arrived in (a restarted merger, or another run of the same session, gets the same edge).
        a, b = (x, y) if x < y else (y, x)
        return self.integrate_pair(a, b)

    # -- solving (the forest's pieces; PoseGraph.solve) ------------------------------------
    def _tolerance(self, hops: int) -> tuple[float, float]:
        s = math.sqrt(max(hops, 1))
        return CYCLE_TRANSLATION_TOLERANCE * s, CYCLE_ROTATION_TOLERANCE * s

    def _pick_anchor(self, group: list[str]) -> str:
        if self.anchor == "first":
            return min(group, key=lambda k: self._nodes[k].order)
        return min(group, key=lambda k: (-self._nodes[k].map.total_length, k))


def _inverse_jacobian(t: Transform2D) -> Array:
    """How the parameters (x, y, heading) of a transform's inverse move with those of ``t``."""
    c, s = math.cos(t.theta), math.sin(t.theta)
    return np.array([[-c, -s, s * t.x - c * t.y], [s, -c, c * t.x + s * t.y], [0.0, 0.0, -1.0]])


def _culprit(
    tree: list[Edge],
    loops: list[Edge],
    conflicts: list[Edge],
    path_keys: Callable[[str, str], Iterable[tuple[str, str]]],
) -> Edge | None:
    """The tree edge that more cycles accuse than support, if any (``path_keys(a, b)``: the keys of
    the tree edges on the path from a to b).

    Each rejected edge votes against the tree edges on its cycle; each loop closure votes for
    them; a tree edge also counts as one vote for itself. The culprit has the most votes against
    it beyond those for it. Votes are counted, not weighted by value: a wrong integration can have
    a high value (a repetitive building matched one rack off), and value grows with map size.
    In a single cycle (a triangle) no edge stands out, and the edge that closes it is rejected.
    """
    if not conflicts:
        return None
    bad: dict[tuple[str, str], float] = {}
    good: dict[tuple[str, str], float] = {}
    for votes, edges in ((bad, conflicts), (good, loops)):
        for e in edges:
            for key in path_keys(e.a, e.b):
                votes[key] = votes.get(key, 0.0) + 1.0
    best, margin = None, 0.0
    for t in tree:
        m = bad.get(t.key(), 0.0) - good.get(t.key(), 0.0) - 1.0
        if m > margin:
            best, margin = t, m
    return best


def _bfs_order(adjacency: dict[str, list[Edge]], start: str, cut: tuple[str, str] | None = None) -> list[str]:
    """The nodes reached from ``start``, breadth first (not across the edge whose key is ``cut``)."""
    order = [start]
    seen = {start}
    i = 0
    while i < len(order):
        for e in adjacency[order[i]]:
            if e.b not in seen and (cut is None or e.key() != cut):
                seen.add(e.b)
                order.append(e.b)
        i += 1
    return order


def _unite(
    e: Edge,
    root: dict[str, str],
    rel: dict[str, Transform2D],
    members: dict[str, list[str]],
    tree: list[Edge],
    adjacency: dict[str, list[Edge]],
) -> None:
    """Join the two groups of a forest that ``e`` spans (union by size): the smaller group's poses
    move into the larger's root frame, ``e`` goes into the tree."""
    ra, rb = root[e.a], root[e.b]
    # Pose of rb's frame in ra's frame: P_a * T_ab * P_b^-1.
    move = rel[e.a].compose(e.transform).compose(rel[e.b].inverse())
    small, big = (ra, rb) if len(members[ra]) < len(members[rb]) else (rb, ra)
    if small == ra:
        move = move.inverse()
    for k in members[small]:
        rel[k] = move.compose(rel[k])
        root[k] = big
    members[big].extend(members.pop(small))
    tree.append(e)
    adjacency[e.a].append(e)
    adjacency[e.b].append(e.reversed())


def _tree_path(adjacency: dict[str, list[Edge]], a: str, b: str) -> list[Edge]:
    """Tree edges on the path from a to b (empty if not connected)."""
    prev: dict[str, Edge | None] = {a: None}
    queue = [a]
    i = 0
    while i < len(queue) and b not in prev:
        for e in adjacency[queue[i]]:
            if e.b not in prev:
                prev[e.b] = e
                queue.append(e.b)
        i += 1
    if b not in prev:
        return []
    path: list[Edge] = []
    k = b
    while (step := prev[k]) is not None:
        path.append(step)
        k = step.a
    return path[::-1]
