"""The ambiguity rule on two groups of submaps as wholes: no clearly different alignment of them holds as well.

The paper refuses an integration when a clearly different transformation scores about as well.
On a join of two groups (:mod:`fleetmap.merger.joins`) the same rule asks whether another
alignment of the two groups, proposed by the other integrations between them and their rivals,
is borne out as well (:meth:`RivalJudge._rival_join`); if one is, the join waits. A rival that puts
wall where the other group's lasers saw through, against a join that puts none there, is refuted
(:meth:`RivalJudge._refutes`, record 081).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

from fleetmap.merger.graph import Edge, _tree_path
from fleetmap.merger.joins import JOIN_HYPOTHESES, RIVALS_KEPT, JoinJudge, _within
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.validity import VALID_REFUTE_CLEAN, VALID_REFUTE_VIOLATION, max_map_violation

log = logging.getLogger(__name__)


RIVAL_JOINS = 3
"""At most this many clearly different alignments of two groups are judged before a join of them
(:meth:`RivalJudge._rival_join`): each costs a join check."""


class RivalJudge(JoinJudge):
    """:class:`~fleetmap.merger.joins.JoinJudge` with the ambiguity rule on the two groups (the module)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # as ChainGraph's
        super().__init__(*args, **kwargs)
        self._rivals: dict[object, tuple[Edge, float, float] | None] = {}
        """Each join's rival alignment of its two groups, if any (:meth:`_rival_join`)."""

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

        The alignments looked at are the other integrations between the groups, their best (unless
        :meth:`_outweighed`) and their rivals (:data:`JOIN_HYPOTHESES` of them), most valuable
        first, at most ``RIVAL_JOINS`` clearly different ones. One counts only if the two groups
        as wholes hold it valid, by a cheap look at every pair that then meets
        (:meth:`_group_look`: the wall in seen free space within what the validity rule allows the
        wall on wall): a rival can put a metre of wall in free space at each of twenty pairs, none
        enough to refute it alone (the office: r3 turned round 39 m off, 23.6 m in free space
        against 102 m on wall, borne out by two pairs).
        In a warehouse every aisle looks like the next: a young robot's submaps down one aisle
        integrate validly with another robot's of the aisle 14 m along, every pair of their
        submaps bears that out, and the rivals one and six aisles along are borne out as well
        (warehouse-events: r4 and r1's second epoch merged 14 m off; docs/decisions/002-pose-graph.md).
        What says which is right is the wall each puts where the other group saw through: a rival
        that puts some there, against a join that puts none, is no rival (:meth:`_refutes`)."""
        in_a, in_b = set(group_a), set(group_b)
        joined = rel[e.a].compose(e.transform).compose(rel[e.b].inverse())  # b's root in a's, by e
        scored: list[tuple[float, Edge]] = []  # each alignment with what it scored
        for k in group_a if len(group_a) <= len(group_b) else group_b:
            for f in by_node.get(k, ()):
                if f.key() == e.key() or not ((f.a in in_a and f.b in in_b) or (f.a in in_b and f.b in in_a)):
                    continue
                g = f if f.a in in_a else f.reversed()
                if not self._outweighed(g):
                    scored.append((g.value, g))
                scored += [(g.runner_up, replace(g, transform=t)) for t in g.rivals[: JOIN_HYPOTHESES - 1]]
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

    def _outweighed(self, f: Edge) -> bool:
        """Whether an integration between two groups is outweighed by others between them that
        agree with each other (none here; :mod:`fleetmap.merger.consistency`): not a rival."""
        return False

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
                if self._refutes(joined, other, group_a, group_b, rel):
                    log.debug(
                        "join %s-%s: its rival %s-%s puts wall where the other group saw through", e.a, e.b, h.a, h.b
                    )
                    continue
                apart = joined.compose(at_b).inverse().compose(other.compose(at_b))
                return h, math.hypot(apart.x, apart.y), abs(apart.theta)
        return None

    def _refutes(
        self,
        joined: Transform2D,
        other: Transform2D,
        group_a: list[str],
        group_b: list[str],
        rel: dict[str, Transform2D],
    ) -> bool:
        """Whether a join's alignment of two groups refutes a rival one that they bear out as well
        (:meth:`_found_rival_join`): record 007's rule for a pair's rivals (``unrefuted``), on the
        groups as wholes. Where the join puts them, their walls stand where the other group's
        lasers saw free space for at most ``VALID_REFUTE_CLEAN`` of their wall on wall; where the
        rival puts them, ``VALID_REFUTE_VIOLATION`` or more, of the solid walls the validity rule
        limits. Wall in seen free space is evidence against an alignment; in a building that repeats
        itself, wall on wall is none between two (warehouse-events: r1 kidnapped into the north lane
        and the crashed r4 put 14 m off, four rack pitches, by five valid integrations borne out by
        their pairs, 753 m on wall against 40 m of solid wall in free space, the forklift's bay
        where r2 saw a rack's end; the right alignment 216 m against none). The join's wall in free
        space is the solid wall too (record 007 counts all of it for the best pair): the two
        alignments are weighed by one measure."""
        hit, clean = self._group_look(group_a, group_b, rel, joined, solid=True)  # wall on wall: as without
        if hit <= 0 or clean > VALID_REFUTE_CLEAN * hit:
            return False
        _, against = self._group_look(group_a, group_b, rel, other, solid=True)
        return against >= VALID_REFUTE_VIOLATION
