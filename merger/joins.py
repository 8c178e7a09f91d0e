"""Judging a join: whether two groups of submaps may be joined by an integration, as wholes.

The pose graph (:class:`~fleetmap.merger.posegraph.PoseGraph`) reads the merge order off a
maximum spanning forest; each of its joins unites two groups of submaps. This module holds what a
join is judged by: the robots' links between their submaps and how far a chain of them can have
drifted (:meth:`JoinJudge._drift`), the paper's validity rule on the two groups as wholes
(:meth:`JoinJudge._join_holds`: the pairs that then meet bear it out, none puts wall where the
other saw free space, and their walls fix it in every direction), the ambiguity rule on them
(:meth:`JoinJudge._rival_join`: no clearly different alignment holds as well), and the verdicts
kept from step to step (:meth:`JoinJudge._kept_verdict`: a join is judged again only when a pair
that could change its verdict is new).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
from fleetmap.merger.graph import Edge, MapGraph, _disagreement, _tree_path
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.integration import GridFreeSpace, align_near
from fleetmap.shared.core.mapgrid import grid_scores
from fleetmap.shared.core.refine import fit_information
from fleetmap.shared.core.tracking import REACH_ROTATION
from fleetmap.shared.core.transformation_value import PreparedPairs, prepare, transformation_value
from fleetmap.shared.core.validity import max_map_violation
from fleetmap.shared.errors import BadInput

log = logging.getLogger(__name__)


VERDICT_VERSIONS = 5
"""A pair's verdict on a join is found again once either submap has this many versions more."""

RIVALS_KEPT = 10_000
"""Rival verdicts kept (:meth:`JoinJudge._rival_join`) before they are forgotten all at once."""
RIVAL_JOINS = 3
"""At most this many clearly different alignments of two groups are judged before a join of them
(:meth:`JoinJudge._rival_join`): each costs a join check."""

Verdict = tuple[float, float, Array | None]
"""What a pair says of a join (:meth:`JoinJudge._pair_verdict`): the value it bears it out with,
the wall against it, and, where it bears it out, how firmly its walls fix the translation (2x2, in
the pair's first submap's frame; None: they do not)."""


LOOKS_KEPT = 200_000
"""Cheap looks kept (:meth:`JoinJudge._look`); past this many the memo starts again."""


@dataclass
class _Judged:
    """A join's verdict (:meth:`JoinJudge._join_holds`) and its two sides when it was given: each
    submap's version and pose from the join's own submap on its side."""

    holds: bool
    side_a: dict[str, tuple[int, Transform2D]]
    side_b: dict[str, tuple[int, Transform2D]]


def _within(a: Transform2D, b: Transform2D, tol_t: float, tol_r: float) -> bool:
    dt, dr = _disagreement(a, b)
    return dt <= tol_t and dr <= tol_r


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


def _translation_information(prep: PreparedPairs, t: Transform2D, params: IntegrationParams) -> Array | None:
    """How firmly two maps' matched walls fix b's position at ``t`` (the translation block of
    :func:`~fleetmap.shared.core.refine.fit_information`, in a's frame); None if they do not."""
    h = fit_information(prep, t, params)
    return None if h is None else np.asarray(h)[:2, :2]


class JoinJudge(MapGraph):
    """Submaps, their links and their integrations, and the judgement of a join of two groups."""

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
        self._verdicts: dict[object, bool] = {}
        """Whether each join of two groups of submaps held (:meth:`_join_holds`)."""
        self._judged: dict[tuple[object, ...], _Judged] = {}
        """Each join's last verdict and what it rested on (:meth:`_kept_verdict`), by the edge as
        :meth:`_join_holds` was asked (its two submaps in order, versions and transform)."""
        self._rivals: dict[object, tuple[Edge, float, float] | None] = {}
        """Each join's rival alignment of its two groups, if any (:meth:`_rival_join`)."""
        self._pair_verdicts: dict[tuple[str, str], tuple[Transform2D, tuple[int, int], Verdict]] = {}
        self._discs: dict[str, tuple[int, Array, float]] = {}
        self._looks: dict[tuple[str, str, int, int, int, int, int], tuple[float, float]] = {}
        """Each pair's cheap look (:meth:`_look`) at its versions and a pose to the centimetre."""

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._links = {b: e for b, e in self._links.items() if key not in (e.a, e.b)}
        self._link_covariances = {p: c for p, c in self._link_covariances.items() if key not in p}
        self._link_sources = {e.a for e in self._links.values()}
        self._discs.pop(key, None)
        # what its pairs said is kept by version, and a map put back starts at its versions again
        self._pair_verdicts = {p: v for p, v in self._pair_verdicts.items() if key not in p}
        self._looks = {k: v for k, v in self._looks.items() if key not in k[:2]}
        self._judged = {k: v for k, v in self._judged.items() if key not in v.side_a and key not in v.side_b}

    def put_link(self, a: str, b: str, transform: Transform2D, covariance: Array) -> None:
        """Submap ``b`` follows ``a``, its frame ``transform`` in a's, as sure as ``covariance``."""
        cov = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        try:
            information = np.linalg.inv(cov)
        except np.linalg.LinAlgError:
            raise BadInput(f"link {a}-{b}", "its covariance is singular") from None
        information = 0.5 * (information + information.T)
        self._links[b] = Edge(a, b, transform, math.inf, True, information=tuple(information.ravel()), link=True)
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

    def _rival_join(
        self,
        e: Edge,
        group_a: list[str],
        group_b: list[str],
        rel: dict[str, Transform2D],
        adjacency: dict[str, list[Edge]],
        by_node: dict[str, list[Edge]],
    ) -> tuple[Edge, float, float] | None:
        """Another way the two groups a join would unite lie on each other, that they bear out as
        well (:meth:`_join_holds`), if any: with how far and how much turned (rad) it puts group b
        from where ``e`` puts it. The paper's ambiguity rule on the two groups as wholes: an
        integration is refused when a clearly different alignment scores about as well, and two
        groups are not joined while two clearly different alignments of them both hold.

        The alignments looked at are the other integrations between the groups, their best and
        their rivals (``join_hypotheses`` of them), most valuable first, at most ``RIVAL_JOINS``
        clearly different ones. One counts only if the two groups as wholes hold it valid, by a
        cheap look at every pair that then meets (:meth:`_group_look`: the wall in seen free space
        within what the validity rule allows the wall on wall): a rival can put a metre of wall in
        free space at each of twenty pairs, none enough to refute it alone (the office: r3 turned
        round 39 m off, 23.6 m in free space against 102 m on wall, borne out by two pairs).
        In a warehouse every aisle looks like the next: a young robot's submaps down one aisle
        integrate validly with another robot's of the aisle 14 m along, every pair of their
        submaps bears that out, and the rivals one and six aisles along are borne out as well:
        nothing yet says which is right (warehouse-events: r4 and r1's second epoch merged 14 m off;
        docs/decisions/002-pose-graph.md)."""
        in_a, in_b = set(group_a), set(group_b)
        joined = rel[e.a].compose(e.transform).compose(rel[e.b].inverse())  # b's root in a's, by e
        scored: list[tuple[float, Edge]] = []  # each alignment with what it scored
        for k in group_a if len(group_a) <= len(group_b) else group_b:
            for f in by_node.get(k, ()):
                if f.key() == e.key() or not ((f.a in in_a and f.b in in_b) or (f.a in in_b and f.b in in_a)):
                    continue
                g = f if f.a in in_a else f.reversed()
                scored.append((g.value, g))
                scored += [(g.runner_up, replace(g, transform=t)) for t in g.rivals[: self.merge.join_hypotheses - 1]]
        scored.sort(key=lambda s: (-s[0], s[1].a, s[1].b))
        hypotheses = [h for _, h in scored]
        # kept for the two groups and the alignments between them: every round of a solve asks again
        key = (
            frozenset(group_a),
            frozenset(group_b),
            tuple((h.a, h.b, h.versions, *(round(v, 3) for v in h.transform.as_array())) for h in [e, *hypotheses]),
        )
        if key in self._rivals:
            return self._rivals[key]
        if len(self._rivals) > RIVALS_KEPT:
            self._rivals.clear()
        rival = self._rivals[key] = self._found_rival_join(e, joined, hypotheses, group_a, group_b, rel, adjacency)
        return rival

    def _found_rival_join(
        self,
        e: Edge,
        joined: Transform2D,
        hypotheses: list[Edge],
        group_a: list[str],
        group_b: list[str],
        rel: dict[str, Transform2D],
        adjacency: dict[str, list[Edge]],
    ) -> tuple[Edge, float, float] | None:
        """:meth:`_rival_join` found, from the alignments between the groups, most valuable first."""
        p = self.integration
        looked: list[Transform2D] = [joined]
        for h in hypotheses:
            if len(looked) > RIVAL_JOINS:
                break
            other = rel[h.a].compose(h.transform).compose(rel[h.b].inverse())
            # compared where each puts h's own submap b, through the tree paths on either side
            path = [*_tree_path(adjacency, h.a, e.a), e, *_tree_path(adjacency, e.b, h.b)]
            tol_t, tol_r = self._cycle_tolerance(path)
            at_b = rel[h.b]
            if any(_within(g.compose(at_b), other.compose(at_b), tol_t, tol_r) for g in looked):
                continue
            looked.append(other)
            hit, free = self._group_look(group_a, group_b, rel, other)
            if hit < p.validity.valid_min_value or free > max_map_violation(hit, p) * hit:
                continue  # the groups as wholes refute it: wall a little in free space along many pairs
            if self._join_holds(replace(h, valid=True), group_a, group_b, rel, adjacency):
                apart = joined.compose(at_b).inverse().compose(other.compose(at_b))
                return h, math.hypot(apart.x, apart.y), abs(apart.theta)
        return None

    def _group_look(
        self, group_a: list[str], group_b: list[str], rel: dict[str, Transform2D], b_root: Transform2D
    ) -> tuple[float, float]:
        """A cheap look (:meth:`_look`) at every pair of two groups' submaps that meet with group b's
        root at ``b_root`` in a's: wall on wall and wall in the other's seen free space, summed."""
        placed_b = {k: b_root.compose(rel[k]) for k in group_b}
        meeting = self.meeting(group_a, {k: rel[k] for k in group_a}, group_b, placed_b)
        hit = free = 0.0
        for i, a in enumerate(group_a):
            a_inverse = rel[a].inverse()
            for j in np.flatnonzero(meeting[i]).tolist():
                b = group_b[j]
                pair_hit, pair_free = self._look(a, b, a_inverse.compose(placed_b[b]))
                hit += pair_hit
                free += pair_free
        return hit, free

    def _join_holds(
        self,
        e: Edge,
        group_a: list[str],
        group_b: list[str],
        rel: dict[str, Transform2D],
        adjacency: dict[str, list[Edge]],
    ) -> bool:
        """Whether an integration may join two groups of submaps: the paper's validity rule on the
        two groups as wholes. Where it puts them, the pairs of their submaps that then overlap are
        looked at: a pair that registers validly near there (within the cycle tolerance) bears the
        join out (its value counts for it); a pair that puts ``valid_refute_violation`` m of wall
        or more where the other saw free space, more than the validity rule allows it, contradicts
        it (that wall counts against). The wall is measured as the validity rule measures it: solid
        walls clear of the other's (``map_free_space_min_length``, ``map_free_space_clearance``),
        not the clutter of chairs and people that moved between two visits. The join holds if at
        least ``join_support`` pairs bear it out, itself included (every pair there is, up to that,
        where a group can never grow), and the wall against is within what the validity rule allows
        their value (``max_map_violation``).
        A repetitive building (racks, a corridor that looks the same turned round) matches one pair
        of submaps wrongly, and the neighbours of the pair often bear that out too; along the two
        groups, walls then stand where the other robot saw through.

        The pairs that bear it out must also fix it in every direction: their walls' translation
        information, summed in one frame (:func:`~fleetmap.shared.core.refine.fit_information` on
        the submaps' own walls), must leave it within the cycle tolerance at three standard
        deviations by the edges' noise model (``edge_sigma_translation`` per unit). Down a corridor
        with no ends in view every pair bears out a join 1 m on or back as well as the right one
        (aces cut in 4: a robot 0.75 m off along a corridor, joined by pairs whose walls fixed it
        in no direction; docs/decisions/002-pose-graph.md).

        Only the pairs whose place the join fixes well enough are judged: each pair's tolerance is
        the cycle tolerance of the tree path from one submap through the join to the other
        (:meth:`_cycle_tolerance`), and a pair whose chains can have drifted farther than
        registration reaches (the tracking's correspondence distance, 5 degrees) says nothing
        either way: judged at the tree's poses, the right join of two long chains looks refuted
        at their far ends (docs/decisions/002-pose-graph.md).

        Registering every overlapping pair would cost a registration per pair and join, and the
        groups are whole components: each pair is first looked at cheaply where the join puts it
        (its grid score: wall on wall, wall in seen free space, :func:`~fleetmap.shared.core.mapgrid.grid_scores`).
        A pair the look says refutes the join is registered to make sure (a drifted chain puts
        walls a little off); then the pairs with the most wall on wall are registered, most first,
        until enough bear the join out and their value outweighs the wall against, or none is left
        with ``valid_min_value`` of wall on wall (nothing for a registration to pull on). The
        verdict is kept for the edge at its versions and the two groups; each pair's is kept too
        (:meth:`_pair_verdict`)."""
        t = e.transform
        key = (
            e.key(),
            e.versions,
            round(t.x, 3),
            round(t.y, 3),
            round(t.theta, 4),
            frozenset(group_a),
            frozenset(group_b),
        )
        held = self._verdicts.get(key)
        if held is None:
            held = self._kept_verdict(e, group_a, group_b, rel)
        if held is not None:
            self._verdicts[key] = held
            return held
        p = self.integration
        # every submap of group b in the frame of a's root, as e puts them
        a_root_from_b_root = rel[e.a].compose(e.transform).compose(rel[e.b].inverse())
        placed_b = {k: a_root_from_b_root.compose(rel[k]) for k in group_b}
        # how far each submap can have drifted from where the tree puts it, seen from the join
        # the drift of the tree path a -> e.a -> e.b -> b of each pair (:meth:`_drift`), from sums
        # along each side's paths: var_t = sum of 0.5 tr + c |p_b - p_i|^2 over the path's links
        # (c: a link's heading variance, p_i: where the path enters it) expands into sums of c,
        # c p_i and c |p_i|^2, so a pair costs a few operations, not a walk along its path
        side_a = self._path_sums(_tree_paths(adjacency, e.a), {k: rel[k] for k in group_a}, toward_start=True)
        side_b = self._path_sums(_tree_paths(adjacency, e.b), placed_b, toward_start=False)
        reach_t, reach_r = self.tracking.max_correspondence, REACH_ROTATION
        pairs: list[tuple[str, str, Transform2D, float, float]] = []
        meeting = self.meeting(group_a, {k: rel[k] for k in group_a}, group_b, placed_b)
        for i, a in enumerate(group_a):
            sa = side_a.get(a)
            if sa is None:
                continue
            a_inverse = rel[a].inverse()
            for j in np.flatnonzero(meeting[i]).tolist():
                b = group_b[j]
                sb, pb = side_b[b], placed_b[b]
                implied = a_inverse.compose(pb)
                c = sa[0] + sb[0]
                lever = pb.x * (sa[1] + sb[1]) + pb.y * (sa[2] + sb[2])
                var_t = sa[4] + sb[4] + c * (pb.x * pb.x + pb.y * pb.y) - 2.0 * lever + sa[3] + sb[3]
                drift_t, drift_r = 3.0 * math.sqrt(max(var_t, 0.0)), 3.0 * math.sqrt(c)
                if drift_t <= reach_t and drift_r <= reach_r:
                    # farther along the groups, the chains' drift hides the pair from registration:
                    # it can neither bear the join out nor refute it
                    base_t, base_r = self._tolerance(2 + sa[5] + sb[5])
                    pairs.append((a, b, implied, math.hypot(base_t, drift_t), math.hypot(base_r, drift_r)))
        looks = [self._look(a, b, implied) for a, b, implied, _, _ in pairs]
        supports, value, against = 0, 0.0, 0.0
        fixed = np.zeros((2, 2))  # the supporting walls' translation information, in a's root frame
        done: set[int] = set()

        def register(i: int) -> None:
            nonlocal supports, value, against, fixed
            a, b, implied, tol_t, tol_r = pairs[i]
            supported, contradicted, information = self._pair_verdict(a, b, implied, tol_t, tol_r)
            supports += supported > 0
            value += supported
            against += contradicted
            if information is not None:
                c, s = math.cos(rel[a].theta), math.sin(rel[a].theta)
                turn = np.array([[c, -s], [s, c]])
                fixed = fixed + turn @ information @ turn.T
            done.add(i)

        def pinned() -> bool:
            # every direction fixed: the walls that bear the join out leave it, by the edges' own
            # noise model (edge_sigma_translation per unit of information), within the cycle
            # tolerance at three standard deviations; along a corridor with no ends they do not
            worst = float(np.linalg.eigvalsh(fixed)[0])
            sigma = self.merge.edge_sigma_translation / math.sqrt(worst) if worst > 0 else math.inf
            return 3.0 * sigma <= self.merge.cycle_translation_tolerance

        bearing = sorted(
            (i for i, look in enumerate(looks) if look[0] >= p.validity.valid_min_value), key=lambda i: -looks[i][0]
        )
        required = self.merge.join_support
        if not (self._chained(group_a) and self._chained(group_b)):
            # a group no link extends yet (a robot's only submap) has only the pairs it has to bear
            # a join out: the paper's validity of the one integration may be all
            required = min(required, len(pairs))
            if all(_map_file(k) for k in (*group_a, *group_b)):
                # map files, which no link will ever extend: a pair with less wall on wall than a
                # valid integration of two maps holds (``valid_min_map_value``) can bear nothing
                # out (edmonton's local maps at their true poses: two joins refused for a pair that
                # barely overlaps; tests/merger/test_graph_real_data.py). Not for a robot's first
                # submap, whose join its next submaps can bear out (office-events: its map's p95
                # error 0.032 -> 0.075 m with it)
                able = sum(looks[i][0] >= p.validity.valid_min_map_value for i in bearing)
                required = min(required, max(able, 1))

        def refuted() -> bool:
            # the wall against outweighs what every pair not registered yet could add, at most its
            # look's wall on wall
            most = value + sum(looks[i][0] for i in bearing if i not in done)
            return against > max_map_violation(most, p) * most

        refuting = [i for i, (_, free) in enumerate(looks) if free >= p.validity.valid_refute_violation]
        for i in sorted(refuting, key=lambda i: -looks[i][1]):
            if refuted():
                break
            register(i)
        for i in bearing:
            if refuted() or (supports >= required and against <= max_map_violation(value, p) * value and pinned()):
                break
            if i not in done:
                register(i)
        limit = max_map_violation(value, p) * value
        holds = supports >= required and against <= limit and pinned()
        log.debug(
            "join %s-%s (%.1f m): %d of %d pairs registered, %d bear it out (%.1f m), %.1f m of wall against"
            " (at most %.1f): %s",
            e.a,
            e.b,
            e.value,
            len(done),
            len(pairs),
            supports,
            value,
            against,
            limit,
            "kept" if holds else "rejected",
        )
        self._verdicts[key] = holds
        if len(self._judged) > RIVALS_KEPT:
            self._judged.clear()
        self._judged[(e.a, e.b, e.versions, round(t.x, 3), round(t.y, 3), round(t.theta, 4))] = _Judged(
            holds, self._seen(e.a, group_a, rel), self._seen(e.b, group_b, rel)
        )
        return holds

    def _seen(self, at: str, group: list[str], rel: dict[str, Transform2D]) -> dict[str, tuple[int, Transform2D]]:
        """Each submap of one side of a join: its version and its pose from the join's submap ``at``."""
        origin = rel[at].inverse()
        return {k: (self.version_of(k), origin.compose(rel[k])) for k in group}

    def _kept_verdict(
        self, e: Edge, group_a: list[str], group_b: list[str], rel: dict[str, Transform2D]
    ) -> bool | None:
        """A join's last verdict, where nothing new can change it (None: judge it again).

        A verdict rests on the pairs of the two sides' submaps that met across the join. Since it
        was given, either side may have grown (a robot's next submaps, another group joined to
        it), a submap may have a new version, or the tree may have moved one within its side (by
        more than a third of the base tolerance, as a pair's verdict is kept: :meth:`_pair_verdict`).
        Only the pairs such a submap makes are new evidence, so only they are looked at (the cheap
        look, :meth:`_look`): a join that held is judged again only if one of them puts
        ``valid_refute_violation`` of wall where the other side saw free space, and one that
        failed only if one of them has ``valid_min_value`` of wall on wall to bear it out. Judged
        again at every step, each join would cost what the whole of both sides holds (issue 49:
        on aces given four times, half the merger's time)."""
        t = e.transform
        judged = self._judged.get((e.a, e.b, e.versions, round(t.x, 3), round(t.y, 3), round(t.theta, 4)))
        if judged is None:
            return None
        now_a, now_b = self._seen(e.a, group_a, rel), self._seen(e.b, group_b, rel)
        if not (judged.side_a.keys() <= now_a.keys() and judged.side_b.keys() <= now_b.keys()):
            return None  # a side lost a submap: the tree changed under it
        tol_t, tol_r = self._tolerance(1)

        def fresh(then: dict[str, tuple[int, Transform2D]], now: dict[str, tuple[int, Transform2D]]) -> list[str]:
            out = []
            for k, (version, pose) in now.items():
                held = then.get(k)
                if held is None or held[0] != version or not _within(held[1], pose, tol_t / 3, tol_r / 3):
                    out.append(k)
            return out

        fresh_a, fresh_b = fresh(judged.side_a, now_a), fresh(judged.side_b, now_b)
        if fresh_a or fresh_b:
            p = self.integration.validity
            a_root_from_b_root = rel[e.a].compose(e.transform).compose(rel[e.b].inverse())
            placed_b = {k: a_root_from_b_root.compose(rel[k]) for k in group_b}
            at_a = {k: rel[k] for k in group_a}
            for side_a, side_b in ((fresh_a, group_b), (group_a, fresh_b)):
                if not side_a or not side_b:
                    continue
                meeting = self.meeting(side_a, at_a, side_b, placed_b)
                for i, a in enumerate(side_a):
                    a_inverse = rel[a].inverse()
                    for j in np.flatnonzero(meeting[i]).tolist():
                        hit, free = self._look(a, side_b[j], a_inverse.compose(placed_b[side_b[j]]))
                        if (free >= p.valid_refute_violation) if judged.holds else (hit >= p.valid_min_value):
                            return None
        judged.side_a, judged.side_b = now_a, now_b
        return judged.holds

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

    def _look(self, a: str, b: str, implied: Transform2D) -> tuple[float, float]:
        """A cheap look at b's walls where ``implied`` puts them on a's: the wall length on wall
        and in the other's seen free space (the large-map path's grid score, both ways)."""
        key = (
            a,
            b,
            self.version_of(a),
            self.version_of(b),
            round(implied.x * 100),
            round(implied.y * 100),
            round(implied.theta * 1000),
        )
        held = self._looks.get(key)
        if held is None:
            if len(self._looks) > LOOKS_KEPT:
                self._looks.clear()
            hit, free = grid_scores(self._index(a), self._index(b), implied.as_array(), fine=True)
            held = self._looks[key] = (float(hit[0]), float(free[0]))
        return held

    def _pair_verdict(self, a: str, b: str, implied: Transform2D, tol_t: float, tol_r: float) -> Verdict:
        """What a pair says of ``implied`` (b's frame in a's): (the value it bears it out with, 0 if
        not; the wall it puts in the other's seen free space there, 0 unless that refutes it; how
        firmly its walls fix the translation where it bears it out, None if not at all).
        Kept for the pair while the implied pose stays within a third of the tolerances and
        neither submap grew by ``VERDICT_VERSIONS`` versions (an active submap gains a few scans a
        version: what its walls bore out they still bear out)."""
        versions = (self.version_of(a), self.version_of(b))
        held = self._pair_verdicts.get((a, b))
        if held is not None and all(
            0 <= now - then < VERDICT_VERSIONS for now, then in zip(versions, held[1], strict=True)
        ):
            dt, dr = _disagreement(held[0], implied)
            if dt <= tol_t / 3 and dr <= tol_r / 3:
                return held[2]
        verdict = self._found_pair_verdict(a, b, implied, tol_t, tol_r)
        self._pair_verdicts[(a, b)] = (implied, versions, verdict)
        return verdict

    def _found_pair_verdict(self, a: str, b: str, implied: Transform2D, tol_t: float, tol_r: float) -> Verdict:
        """:meth:`_pair_verdict` found (the pair's known integration where it is current)."""
        known = self.edge(a, b) if (a, b) in self._edges or (b, a) in self._edges else None
        na, nb = self._nodes[a], self._nodes[b]
        p = self.integration

        def pairs() -> PreparedPairs:
            return prepare(na.map.segments, nb.map.segments, na.map.oriented and nb.map.oriented, p)

        if known is not None and known.valid and known.versions == (self.version_of(a), self.version_of(b)):
            dt, dr = _disagreement(known.transform, implied)
            if dt <= tol_t and dr <= tol_r:
                if known.information is not None:  # fitted on these walls at its transform already
                    return known.value, 0.0, np.asarray(known.information).reshape(3, 3)[:2, :2]
                return known.value, 0.0, _translation_information(pairs(), known.transform, p)
        prep = pairs()
        r = align_near(na.map, nb.map, implied, p, self.tracking, self.reference(a), self._index(a), self._index(b))
        dt, dr = _disagreement(r.transform, implied)
        if r.valid and dt <= tol_t and dr <= tol_r:
            return r.value, 0.0, _translation_information(prep, r.transform, p)
        # registered elsewhere (a repetitive building has several valid alignments) or not valid:
        # what the pair says at the implied pose itself, its wall in free space as the validity
        # rule limits it (solid walls: the integration that made the join was valid by that)
        free = GridFreeSpace(self._index(a), self._index(b))
        at = implied.as_array()
        value = max(transformation_value(prep, at, p, refuse=False), 0.0)
        violation = float(free.violation(at, solid=True)[0]) if free.active else 0.0
        if violation >= p.validity.valid_refute_violation and violation > max_map_violation(value, p) * value:
            log.debug("pair %s-%s: %.1f m of wall in seen free space against %.1f m matched", a, b, violation, value)
            return 0.0, violation, None
        return 0.0, 0.0, None

    def meeting(
        self, group_a: list[str], at_a: dict[str, Transform2D], group_b: list[str], at_b: dict[str, Transform2D]
    ) -> Array:
        """Which submaps of two groups, placed in one frame, can touch: the discs about their walls
        (:meth:`_disc`) meet; a boolean ``(len(group_a), len(group_b))`` array."""

        def discs(group: list[str], at: dict[str, Transform2D]) -> tuple[Array, Array]:
            centres = np.empty((len(group), 2))
            radii = np.empty(len(group))
            for n, k in enumerate(group):
                centre, radii[n] = self._disc(k)
                centres[n] = at[k].apply_points(centre[None, :])[0]
            return centres, radii

        ca, ra = discs(group_a, at_a)
        cb, rb = discs(group_b, at_b)
        gap = np.hypot(ca[:, None, 0] - cb[None, :, 0], ca[:, None, 1] - cb[None, :, 1])
        return np.asarray(gap <= ra[:, None] + rb[None, :])

    def _disc(self, key: str) -> tuple[Array, float]:
        """The disc about a node's walls: their ends' centroid and the farthest end from it."""
        node = self._nodes[key]
        held = self._discs.get(key)
        if held is None or held[0] != node.version:
            ends = node.map.segments.reshape(-1, 2)
            centre = ends.mean(axis=0) if len(ends) else np.zeros(2)
            radius = float(np.hypot(*(ends - centre).T).max()) if len(ends) else 0.0
            held = self._discs[key] = (node.version, centre, radius)
        return held[1], held[2]
