"""The map graph: merging partial maps whose order nobody knows (the paper's future work, VI).

Nodes are partial maps (a robot's local map, one per epoch); edges are integration attempts, each
with its transform, transformation value and validity. The merge order is read off the graph:

1. **Maximum spanning forest** over the valid edges, weighted by transformation value (Kruskal,
   best value first), with a *cycle check* on every edge that closes a cycle: its transform must
   agree with the composition of the tree path between its ends. Edges that agree are kept as
   loop closures; edges that disagree are rejected. If more rejected edges accuse one tree edge
   than loop closures (and the edge itself) support it, that tree edge is the wrong one: it is
   rejected and the forest is built again. So one wrong integration,
   however high its value, cannot corrupt a map that has redundant evidence (ROS map_merge trusts
   one tree and lets the map jump). An edge that no cycle can check (a *bridge* of the valid
   edges: without it the maps on either side fall apart) joins them only if its value is at
   least ``bridge_min_value`` (fleetmap): it is rejected otherwise.
2. **Placement**: each tree is one global map; every map is placed by composing transforms along
   the tree from the component's anchor, and where loop closures exist all poses are refined
   together by least squares over SE(2) (value-weighted, robust loss, anchor fixed).
3. **Fusion**: each map is fused once into the global frame (the pivot method's lesson: no line
   is fused again and again).

The graph is incremental: a new map is integrated with the existing ones, most similar first (a
pairwise geometric histogram of their walls, fleetmap.shared.core.descriptor), and pairs already integrated
are never integrated again. Anchors are stable: by default the first map of a component stays its
anchor as maps are added.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import networkx as nx
import numpy as np
from fleetmap.merger.executor import Indexes, PairJob, PairResult, fitted, reference_of, run_pair
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.descriptor import pairwise_histogram, similarity
from fleetmap.shared.core.fusion import fuse
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.integration import index_for
from fleetmap.shared.core.mapgrid import MapIndex, viewpoints_of
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.simplify import simplify
from fleetmap.shared.core.tracking import ReferenceMap
from fleetmap.shared.core.validity import seen_from_enough_places
from fleetmap.shared.errors import BadInput
from scipy.optimize import least_squares

log = logging.getLogger(__name__)


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
    the other edges. None: not known (an edge integrated invalid, ``MergeParams.edge_information``
    off, fewer than two parallel pairs matched, or an edge given without it); such an edge weighs
    by value alone, the same in every direction."""
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
    """Partial maps and their pairwise integrations; :meth:`solve` gives the global maps."""

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
            node.descriptor = pairwise_histogram(
                node.map.segments, self.merge.descriptor_step, self.merge.descriptor_reach
            )
        return node.descriptor

    def candidates_for(self, key: str) -> list[str]:
        """Existing maps to integrate ``key`` with, most similar first (at most max_candidates)."""
        h = self.descriptor(key)
        others = [k for k in self.keys if k != key]
        ranked = sorted(others, key=lambda k: (-similarity(self.descriptor(k), h), self._nodes[k].order))
        limit = self.merge.max_candidates
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
                for k, e in list(self._edges.items()):
                    if key in k:
                        va, vb = e.versions
                        if (va if e.a == key else vb) == old:
                            self._edges[k] = replace(e, versions=(version, vb) if e.a == key else (va, version))
                return True
            node.map, node.version = segment_map, version
            node.descriptor = None
            node.work, node.index = self._work(segment_map), None
            if not keep_edges:
                for k in [k for k in self._edges if key in k]:
                    del self._edges[k]
            return True
        self._nodes[key] = _Node(
            segment_map,
            self._counter,
            version,
            None,
            self._work(segment_map),
        )
        self._counter += 1
        return True

    def _work(self, m: SegmentMap) -> SegmentMap:
        tol = self.integration.simplify_tolerance
        return simplify(m, tol) if tol > 0 and not m.ordered else m

    def _index(self, key: str) -> MapIndex:
        node = self._nodes[key]
        if node.index is None:
            node.index = index_for(node.work, self.integration)
        return node.index

    def remove_map(self, key: str) -> None:
        self._nodes.pop(key, None)
        self._references.pop(key, None)
        for k in [k for k in self._edges if key in k]:
            del self._edges[k]

    def add_edge(self, edge: Edge) -> None:
        """Record an integration (computed here or elsewhere, e.g. restored from a recording)."""
        if edge.a not in self._nodes or edge.b not in self._nodes:
            raise BadInput(f"edge {edge.a}-{edge.b}", "names a map that is not in the graph")
        self._edges[edge.key()] = edge

    def fit_edges(self) -> int:
        """Fit every valid edge that carries no information (restored from a state
        file that does not carry it) as a new integration's would be; how many."""
        missing = [e for e in self._edges.values() if e.valid and e.information is None]
        for e in missing:
            transform, information = fitted(self.pair_job(e.a, e.b), e.transform)
            self._edges[e.key()] = replace(e, transform=transform, information=information)
        return len(missing)

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

    def pair_job(self, a: str, b: str, predicted: Transform2D | None = None) -> PairJob:
        """The integration of b on a at their current versions, near ``predicted`` (b's frame in
        a's) or pose-free, as a job any executor runs (:mod:`fleetmap.merger.executor`), with the
        indexes of the two maps the graph holds already."""
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
            self.tracking, self.merge, given,
        )  # fmt: skip

    def align_pair(self, a: str, b: str, predicted: Transform2D) -> Edge:
        """b's walls registered on a's near ``predicted`` (b's frame in a's) and valued as an
        integration (:func:`~fleetmap.shared.core.integration.align_near`); the edge replaces any known."""
        job = self.pair_job(a, b, predicted)
        return self.take(job, run_pair(job, self.indexes))

    def reference(self, key: str) -> ReferenceMap:
        """The registration grid of a node's walls (built once per version)."""
        node = self._nodes[key]
        held = self._references.get(key)
        if held is None or held[0] != node.version:
            held = self._references[key] = (node.version, reference_of(node.map, self.tracking))
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
            self._edges[e.key()] = e
        # the indexes a worker built: kept, so that nothing builds them again
        if na is not None and na.version == job.versions[0]:
            if na.index is None and "index_a" in result.built:
                na.index = result.built["index_a"]
            held = self._references.get(job.a)
            if "reference_a" in result.built and (held is None or held[0] != na.version):
                self._references[job.a] = (na.version, result.built["reference_a"])
        if nb is not None and nb.version == job.versions[1] and nb.index is None and "index_b" in result.built:
            nb.index = result.built["index_b"]
        return e

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

    def job_once(self, x: str, y: str) -> PairJob | None:
        """:meth:`integrate_pair_once` as a job for an executor; None if the pair's edge is already
        known at these versions."""
        if self.is_current(x, y):
            return None
        a, b = (x, y) if x < y else (y, x)  # one way, as _oriented_pair
        return self.pair_job(a, b)

    def seen_enough(self, a: str, b: str) -> bool:
        """Whether two maps can merge at all (see :meth:`_too_few_places`)."""
        return not self._too_few_places(self._nodes[a].map, self._nodes[b].map)

    def _too_few_places(self, a: SegmentMap, b: SegmentMap) -> bool:
        """Whether two partial maps cannot merge whatever their geometry: one was seen from fewer
        than ``valid_min_map_scans`` places (fleetmap.shared.core.integration's rule). Such a pair is
        not integrated (a new epoch's first versions, a robot that saw its map from one place)."""
        return not (a.ordered or b.ordered or seen_from_enough_places(a, b, self.integration))

    def _oriented_pair(self, x: str, y: str) -> Edge:
        # The first key (in sorted order) is S1: INTEGRATE(a, b) is not exactly the inverse of
        # INTEGRATE(b, a), so the pair is always integrated one way, whatever order the maps
        # arrived in (a restarted merger, or another run of the same session, gets the same edge).
        a, b = (x, y) if x < y else (y, x)
        return self.integrate_pair(a, b)

    # -- solving ---------------------------------------------------------------------------
    def solve(self, fuse_maps: bool = True) -> MergeResult:
        valid = [e for e in self._edges.values() if e.valid]
        order = {k: n.order for k, n in self._nodes.items()}
        valid.sort(key=lambda e: (-e.value, order[e.a], order[e.b]))
        partial = {k for k, n in self._nodes.items() if not n.map.ordered}
        # A weak edge is rejected if it is a bridge of the edges the cycle check accepts: then no
        # cycle checks it, or only one that disagrees (two weak edges that join the same two
        # groups of maps differently are a conflict, and the stronger must not win by default).
        weak: dict[tuple[str, str], Edge] = {}
        while True:
            kept = [e for e in valid if e.key() not in weak]
            excluded: set[tuple[str, str]] = set()
            while True:
                tree, loops, conflicts, adjacency = self._kruskal([e for e in kept if e.key() not in excluded])
                culprit = _culprit(tree, loops, conflicts, adjacency)
                if culprit is None:
                    break
                log.debug("rejecting edge %s-%s: the cycles through it disagree", culprit.a, culprit.b)
                excluded.add(culprit.key())
            found = _weak_bridges(tree + loops, self.merge.bridge_min_value, partial)
            if not found:
                break
            weak.update(found)
        for e in weak.values():
            log.debug(
                "rejecting edge %s-%s: no cycle checks it and its value %.1f m is under %.1f m",
                e.a,
                e.b,
                e.value,
                self.merge.bridge_min_value,
            )
        rejected = conflicts + [e for e in kept if e.key() in excluded] + list(weak.values())
        components = self._components(tree, loops, fuse_maps)
        poses: dict[str, Transform2D | None] = {k: None for k in self.keys}
        for c in components:
            if len(c.members) > 1:
                poses.update(c.poses)
        return MergeResult(poses, components, tree, loops, rejected)

    def _tolerance(self, hops: int) -> tuple[float, float]:
        s = math.sqrt(max(hops, 1))
        return self.merge.cycle_translation_tolerance * s, self.merge.cycle_rotation_tolerance * s

    def _kruskal(self, edges: Iterable[Edge]) -> tuple[list[Edge], list[Edge], list[Edge], dict[str, list[Edge]]]:
        """Maximum spanning forest with the cycle check; poses relative to each tree's root."""
        root = {k: k for k in self._nodes}
        rel = {k: Transform2D.identity() for k in self._nodes}  # pose of k in root[k]'s frame
        members = {k: [k] for k in self._nodes}
        tree: list[Edge] = []
        loops: list[Edge] = []
        conflicts: list[Edge] = []
        adjacency: dict[str, list[Edge]] = {k: [] for k in self._nodes}
        for e in edges:
            ra, rb = root[e.a], root[e.b]
            if ra != rb:
                _unite(e, root, rel, members, tree, adjacency)
            else:
                predicted = rel[e.a].inverse().compose(rel[e.b])
                dt, dr = _disagreement(predicted, e.transform)
                hops = len(_tree_path(adjacency, e.a, e.b))
                tol_t, tol_r = self._tolerance(hops)
                (loops if dt <= tol_t and dr <= tol_r else conflicts).append(e)
        return tree, loops, conflicts, adjacency

    def _components(self, tree: list[Edge], loops: list[Edge], fuse_maps: bool) -> list[Component]:
        adjacency: dict[str, list[Edge]] = {k: [] for k in self._nodes}
        for e in tree:
            adjacency[e.a].append(e)
            adjacency[e.b].append(e.reversed())
        seen: set[str] = set()
        out = []
        for start in self.keys:
            if start in seen:
                continue
            # Breadth-first from any member to collect the component, then from its anchor.
            group = _bfs_order(adjacency, start)
            seen.update(group)
            anchor = self._pick_anchor(group)
            order = _bfs_order(adjacency, anchor)
            poses = {anchor: Transform2D.identity()}
            via: dict[str, Edge] = {}
            for k in order:
                for e in adjacency[k]:
                    if e.b not in poses:
                        poses[e.b] = poses[k].compose(e.transform)
                        via[e.b] = e
            group_set = set(group)
            cycle_edges = [e for e in loops if e.a in group_set]
            if cycle_edges:
                # Each edge as it was integrated, not as the walk from the anchor met it: the residual
                # of an edge is not that of its reverse, and the anchor (the first map to arrive)
                # must not change the relative poses (a restarted merger gets the same map).
                tree_edges = [self._edges[via[k].key()] for k in order if k in via]
                poses = self._least_squares(anchor, poses, tree_edges + cycle_edges)
            segments = self._fuse(order, poses) if fuse_maps else np.zeros((0, 4))
            out.append(Component(anchor, tuple(order), poses, segments))
        out.sort(key=lambda c: (-len(c.members), -sum(self._nodes[k].map.total_length for k in c.members)))
        return out

    def _pick_anchor(self, group: list[str]) -> str:
        if self.anchor == "first":
            return min(group, key=lambda k: self._nodes[k].order)
        return min(group, key=lambda k: (-self._nodes[k].map.total_length, k))

    def _least_squares(self, anchor: str, poses: dict[str, Transform2D], edges: list[Edge]) -> dict[str, Transform2D]:
        """All poses of a component refined together over SE(2) (robust loss).

        An edge whose :attr:`Edge.information` is known weighs as its walls fix it: its residual is
        the difference of its transform and the poses' (x, y, heading) through the square root of
        that information (over ``edge_sigma_translation`` squared) with ``isotropic_share`` of the value-weighted weight
        below added, so that no direction is entirely free. Along a corridor one edge may be 0.3 m
        off while another, whose walls end there, is right: weighted by value alone in every
        direction, the wrong one would pull the map along the corridor
        (docs/decisions/008-pivot-local-maps.md). Another edge, or one whose information is not a
        weight (not positive definite with that share added), weighs by its value, the same in
        every direction. Only a component with a cycle is refined: a tree's poses are its edges'."""
        free = [k for k in poses if k != anchor]
        index = {k: i for i, k in enumerate(free)}
        x0 = np.concatenate([poses[k].as_array() for k in free])
        weights = np.sqrt(np.array([max(e.value, 1e-3) for e in edges]))
        sigma_t, sigma_r = self.merge.edge_sigma_translation, self.merge.edge_sigma_rotation
        roots: list[Array | None] = []
        for e, w in zip(edges, weights, strict=True):
            if e.information is None:
                roots.append(None)
                continue
            iso = np.diag([1 / sigma_t**2, 1 / sigma_t**2, 1 / sigma_r**2]) * w**2 * self.merge.isotropic_share
            try:
                root = np.linalg.cholesky(np.array(e.information).reshape(3, 3) / sigma_t**2 + iso).T
            except np.linalg.LinAlgError:
                root = None
            roots.append(root if root is not None and np.isfinite(root).all() else None)

        def pose(x: Array, k: str) -> Transform2D:
            if k == anchor:
                return poses[anchor]
            i = index[k]
            return Transform2D(x[3 * i], x[3 * i + 1], x[3 * i + 2])

        def residuals(x: Array) -> Array:
            out = np.empty(3 * len(edges))
            for j, e in enumerate(edges):
                between = pose(x, e.a).inverse().compose(pose(x, e.b))
                root = roots[j]
                if root is not None:
                    t = e.transform
                    diff = np.array([between.x - t.x, between.y - t.y, float(wrap_angle(between.theta - t.theta))])
                    out[3 * j : 3 * j + 3] = root @ diff
                    continue
                err = e.transform.inverse().compose(between)
                out[3 * j : 3 * j + 3] = (
                    np.array([err.x / sigma_t, err.y / sigma_t, float(wrap_angle(err.theta)) / sigma_r]) * weights[j]
                )
            return out

        sol = least_squares(residuals, x0, loss="soft_l1", f_scale=3.0, x_scale="jac")
        refined = {anchor: poses[anchor]}
        for k in free:
            refined[k] = Transform2D.from_array(sol.x[3 * index[k] : 3 * index[k] + 3])
        return refined

    def _fuse(self, order: list[str], poses: dict[str, Transform2D]) -> Array:
        """Each map fused once into the global frame, in tree order from the anchor."""
        merged: SegmentMap | None = None
        for k in order:
            m = self._nodes[k].work
            if merged is None:
                merged = SegmentMap(poses[k].apply(m.segments), ordered=False, oriented=m.oriented)
            else:
                merged = fuse(merged, m, poses[k], self.integration)
        return merged.segments if merged is not None else np.zeros((0, 4))


def _inverse_jacobian(t: Transform2D) -> Array:
    """How the parameters (x, y, heading) of a transform's inverse move with those of ``t``."""
    c, s = math.cos(t.theta), math.sin(t.theta)
    return np.array([[-c, -s, s * t.x - c * t.y], [s, -c, c * t.x + s * t.y], [0.0, 0.0, -1.0]])


def _weak_bridges(edges: list[Edge], min_value: float, partial: set[str]) -> dict[tuple[str, str], Edge]:
    """The ``edges`` between two partial maps (in ``partial``; not scans) that no cycle of them
    can check (bridges of their graph) and whose value is under ``min_value``, by key.
    The paper's right merges of local maps scored about 10 m and its wrong ones about 5 m; a
    wrong one just over ``valid_min_map_value`` that joins two groups of maps has nothing to
    contradict it (see ``MergeParams.bridge_min_value``; docs/decisions/008-pivot-local-maps.md)."""
    if min_value <= 0 or not edges:
        return {}
    g = nx.Graph()
    g.add_edges_from((e.a, e.b) for e in edges)
    bridges = {(a, b) if a <= b else (b, a) for a, b in nx.bridges(g)}  # as Edge.key orders them
    return {
        e.key(): e for e in edges if e.value < min_value and e.a in partial and e.b in partial and e.key() in bridges
    }


def _culprit(
    tree: list[Edge], loops: list[Edge], conflicts: list[Edge], adjacency: dict[str, list[Edge]]
) -> Edge | None:
    """The tree edge that more cycles accuse than support, if any.

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
            for t in _tree_path(adjacency, e.a, e.b):
                votes[t.key()] = votes.get(t.key(), 0.0) + 1.0
    best, margin = None, 0.0
    for t in tree:
        m = bad.get(t.key(), 0.0) - good.get(t.key(), 0.0) - 1.0
        if m > margin:
            best, margin = t, m
    return best


def _bfs_order(adjacency: dict[str, list[Edge]], start: str) -> list[str]:
    order = [start]
    seen = {start}
    i = 0
    while i < len(order):
        for e in adjacency[order[i]]:
            if e.b not in seen:
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
