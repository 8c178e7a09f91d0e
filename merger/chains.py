"""A robot's chain of submaps in the pose graph: the links its tracking measured, and how far a path
along them can have drifted.

Each robot's tracking links its consecutive submaps (:class:`~fleetmap.shared.io.messages.SubmapLink`),
with the tracking's covariance. A cycle through them, or a join judged across them, may disagree
by what their covariances add up to (:meth:`ChainGraph._drift`: first order, a link's heading error
turns everything after it about its start); the rest of the merger's judgement rests on that.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.merger.graph import Edge, MapGraph
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.errors import BadInput


def _parts(key: str) -> tuple[str | None, str | None, int | None]:
    """A submap key's robot, epoch and submap number (Nones for a node that is no submap)."""
    parts = key.split("/")
    if len(parts) != 3 or not parts[2].isdigit():
        return None, None, None
    return parts[0], parts[1], int(parts[2])


def _map_file(key: str) -> bool:
    """Whether a node is a map no link will ever extend (``fleetmap merge``'s map files, a
    benchmark's local maps), not a robot's submap (``robot/epoch/n``)."""
    return _parts(key)[0] is None


def _chain_of(key: str) -> str:
    """The chain a node belongs to: a submap's robot epoch (``robot/epoch``), else the node itself."""
    parts = key.split("/")
    return "/".join(parts[:2]) if len(parts) == 3 else key


def _tree_paths(adjacency: dict[str, list[Edge]], start: str) -> dict[str, list[Edge]]:
    """The tree path from ``start`` to every node of its tree, as lists of edges in order."""
    paths: dict[str, list[Edge]] = {start: []}
    queue = [start]
    i = 0
    while i < len(queue):
        k = queue[i]
        for t in adjacency[k]:
            if t.b not in paths:
                paths[t.b] = [*paths[k], t]
                queue.append(t.b)
        i += 1
    return paths


class ChainGraph(MapGraph):
    """Submaps, their integrations, and the robots' links between their submaps."""

    def __init__(
        self,
        integration: IntegrationParams | None = None,
        merge: MergeParams | None = None,
        tracking: TrackingParams | None = None,
        anchor: str = "first",
    ) -> None:
        super().__init__(integration, merge, anchor)
        self.tracking = tracking or TrackingParams()
        self._links: dict[str, Edge] = {}
        """Links by the later submap's key."""
        self._link_covariances: dict[tuple[str, str], Array] = {}
        """Each link's covariance, both ways round (what a cycle through it may have drifted)."""
        self._link_sources: set[str] = set()
        """The earlier submap of every link."""

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._links = {b: e for b, e in self._links.items() if key not in (e.a, e.b)}
        self._link_covariances = {p: c for p, c in self._link_covariances.items() if key not in p}
        self._link_sources = {e.a for e in self._links.values()}

    def put_link(self, a: str, b: str, transform: Transform2D, covariance: Array) -> None:
        """Submap ``b`` follows ``a``, its frame ``transform`` in a's, as sure as ``covariance``."""
        cov = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        try:
            information = np.linalg.inv(cov)
        except np.linalg.LinAlgError:
            raise BadInput(f"link {a}-{b}", "its covariance is singular") from None
        information = 0.5 * (information + information.T)
        link = Edge(a, b, transform, math.inf, True, information=tuple(information.ravel()), link=True)
        if self._links.get(b) != link:  # each version of a submap sends its link again: the same
            # edge kept as it was, so the kept forest sees an edge it holds, not one to compare
            self._links[b] = link
            self.edits += 1
        self._link_covariances[(a, b)] = self._link_covariances[(b, a)] = cov
        self._link_sources.add(a)

    def link_to(self, key: str) -> Edge | None:
        """The link from ``key``'s previous submap to it."""
        return self._links.get(key)

    @property
    def links(self) -> list[Edge]:
        return list(self._links.values())

    def linked(self, a: str, b: str) -> bool:
        """Whether a link joins the two submaps directly."""
        la, lb = self._links.get(a), self._links.get(b)
        return (la is not None and la.a == b) or (lb is not None and lb.a == a)

    def chain_drift(self, a: str, b: str) -> tuple[float, float] | None:
        """Three standard deviations (m, rad) of the drift between two submaps of one robot's
        chain, from the covariances of the links between them; None if they are not on one
        chain (or a link between them is missing)."""
        ra, ea, sa = _parts(a)
        rb, eb, sb = _parts(b)
        if ra is None or (ra, ea) != (rb, eb) or sa is None or sb is None:
            return None
        lo, hi = (a, b) if sa < sb else (b, a)
        path: list[Edge] = []
        k = hi
        while k != lo:
            link = self._links.get(k)
            if link is None:
                return None
            path.append(link)
            k = link.a
        path.reverse()
        return self._drift(path)

    def _cycle_tolerance(self, path: list[Edge]) -> tuple[float, float]:
        """What a cycle through ``path`` and the edge closing it may disagree by: the base tolerance
        for each integration (the closing edge included), and the drift of its links (:meth:`_drift`)."""
        base_t, base_r = self._tolerance(1 + sum(1 for e in path if not e.link))
        drift_t, drift_r = self._drift(path)
        return math.hypot(base_t, drift_t), math.hypot(base_r, drift_r)

    def _drift(self, path: list[Edge]) -> tuple[float, float]:
        """Three standard deviations (m, rad) of what the links on ``path`` can have drifted, from
        their covariances (first order: a link's heading error turns everything after it about
        its start)."""
        starts = [Transform2D.identity()]  # where each edge of the path starts, and the end
        for e in path:
            starts.append(starts[-1].compose(e.transform))
        end = starts[-1]
        var_t = var_r = 0.0
        for e, at in zip(path, starts, strict=False):
            cov = self._link_covariances.get((e.a, e.b)) if e.link else None
            if cov is not None:
                lever = math.hypot(end.x - at.x, end.y - at.y)
                var_t += 0.5 * (cov[0, 0] + cov[1, 1]) + cov[2, 2] * lever * lever
                var_r += cov[2, 2]
        return 3.0 * math.sqrt(var_t), 3.0 * math.sqrt(var_r)

    def _chained(self, group: list[str]) -> bool:
        """Whether a group holds a submap linked to another (a robot's chain, which grows)."""
        return any(k in self._links or k in self._link_sources for k in group)

    def _path_sums(
        self, paths: dict[str, list[Edge]], where: dict[str, Transform2D], toward_start: bool
    ) -> dict[str, tuple[float, float, float, float, float, int]]:
        """For every node of ``where`` (its position in one frame): sums over the links of its
        tree path from the path's start (:func:`_tree_paths`) of c, c x, c y, c (x^2 + y^2) and
        0.5 tr of the translation covariance, c a link's heading variance and (x, y) where a path
        between the node and the start enters the link (the node nearer the far end when it runs
        ``toward_start``, else the one nearer the start), and the integrations on it. See
        :meth:`_join_holds` and :meth:`_drift`."""
        sums: dict[str, tuple[float, float, float, float, float, int]] = {}
        for k, path in paths.items():  # breadth first: a node's parent comes before it
            if not path:
                sums[k] = (0.0, 0.0, 0.0, 0.0, 0.0, 0)
                continue
            t = path[-1]
            parent = sums.get(t.a)
            if parent is None or k not in where:
                continue
            s0, s1x, s1y, s2, tr, joins = parent
            cov = self._link_covariances.get((t.a, t.b)) if t.link else None
            if cov is None:
                sums[k] = (s0, s1x, s1y, s2, tr, joins + (not t.link))
                continue
            enters = where[k] if toward_start else where.get(t.a)
            if enters is None:
                continue
            c = float(cov[2, 2])
            sums[k] = (
                s0 + c,
                s1x + c * enters.x,
                s1y + c * enters.y,
                s2 + c * (enters.x * enters.x + enters.y * enters.y),
                tr + 0.5 * float(cov[0, 0] + cov[1, 1]),
                joins,
            )
        return sums
