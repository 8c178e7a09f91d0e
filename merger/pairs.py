"""What one pair of submaps says of a join: a cheap look at where the join puts them, and, where
that does not decide, the pair registered near there.

A join of two groups (:mod:`fleetmap.merger.joins`) is judged by the pairs of their submaps that
then meet (:meth:`PairJudge.meeting`: the discs about their walls touch). Each pair is first looked
at cheaply (:meth:`PairJudge._look`: its grid score, wall on wall and wall in the other's seen free
space, :func:`~fleetmap.shared.core.mapgrid.grid_scores`), and registered only where the look does
not decide (:meth:`PairJudge._pair_verdict`: near the implied pose, as
:func:`~fleetmap.shared.core.near.align_near` registers a placed submap). Both are kept by
the two submaps' versions, so a step judges again only what it changed.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from fleetmap.merger.chains import ChainGraph
from fleetmap.merger.graph import _disagreement
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.integration import GridFreeSpace
from fleetmap.shared.core.mapgrid import grid_scores
from fleetmap.shared.core.near import align_near
from fleetmap.shared.core.refine import fit_information
from fleetmap.shared.core.transformation_value import PreparedPairs, prepare, transformation_value
from fleetmap.shared.core.validity import refuted_by_free_space

log = logging.getLogger(__name__)


VERDICT_VERSIONS = 5
"""A pair's verdict on a join is found again once either submap has this many versions more."""

Verdict = tuple[float, float, Array | None]
"""What a pair says of a join (:meth:`PairJudge._pair_verdict`): the value it bears it out with,
the wall against it, and, where it bears it out, how firmly its walls fix the translation (2x2, in
the pair's first submap's frame; None: they do not)."""


LOOKS_KEPT = 200_000
"""Cheap looks kept (:meth:`PairJudge._look`); past this many the memo starts again."""


def _translation_information(prep: PreparedPairs, t: Transform2D, params: IntegrationParams) -> Array | None:
    """How firmly two maps' matched walls fix b's position at ``t`` (the translation block of
    :func:`~fleetmap.shared.core.refine.fit_information`, in a's frame); None if they do not."""
    h = fit_information(prep, t, params)
    return None if h is None else np.asarray(h)[:2, :2]


class PairJudge(ChainGraph):
    """Submaps, their links and integrations, and what each pair of submaps says of a join."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # as ChainGraph's
        super().__init__(*args, **kwargs)
        self._pair_verdicts: dict[tuple[str, str], tuple[Transform2D, tuple[int, int], Verdict]] = {}
        self._discs: dict[str, tuple[int, Array, float]] = {}
        self._looks: dict[tuple[str, str, int, int, int, int, int, bool], tuple[float, float]] = {}
        """Each pair's cheap look (:meth:`_look`) at its versions and a pose to the centimetre, all its
        wall in free space or the solid only."""

    def remove_map(self, key: str) -> None:
        super().remove_map(key)
        self._discs.pop(key, None)
        # what its pairs said is kept by version, and a map put back starts at its versions again
        self._pair_verdicts = {p: v for p, v in self._pair_verdicts.items() if key not in p}
        self._looks = {k: v for k, v in self._looks.items() if key not in k[:2]}

    def _group_look(
        self,
        group_a: list[str],
        group_b: list[str],
        rel: dict[str, Transform2D],
        b_root: Transform2D,
        solid: bool = False,
    ) -> tuple[float, float]:
        """A cheap look (:meth:`_look`) at every pair of two groups' submaps that meet with group b's
        root at ``b_root`` in a's: wall on wall and wall in the other's seen free space, summed
        (``solid``: only the wall the validity rule limits there)."""
        placed_b = {k: b_root.compose(rel[k]) for k in group_b}
        meeting = self.meeting(group_a, {k: rel[k] for k in group_a}, group_b, placed_b)
        hit = free = 0.0
        for i, a in enumerate(group_a):
            a_inverse = rel[a].inverse()
            for j in np.flatnonzero(meeting[i]).tolist():
                b = group_b[j]
                pair_hit, pair_free = self._look(a, b, a_inverse.compose(placed_b[b]), solid)
                hit += pair_hit
                free += pair_free
        return hit, free

    def _look(self, a: str, b: str, implied: Transform2D, solid: bool = False) -> tuple[float, float]:
        """A cheap look at b's walls where ``implied`` puts them on a's: the wall length on wall
        and in the other's seen free space (the large-map path's grid score, both ways; ``solid``:
        only the solid walls clear of the other's, which the validity rule limits)."""
        key = (
            a,
            b,
            self.version_of(a),
            self.version_of(b),
            round(implied.x * 100),
            round(implied.y * 100),
            round(implied.theta * 1000),
            solid,
        )
        held = self._looks.get(key)
        if held is None:
            if len(self._looks) > LOOKS_KEPT:
                self._looks.clear()
            hit, free = grid_scores(self._index(a), self._index(b), implied.as_array(), fine=True, solid=solid)
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
        if refuted_by_free_space(value, violation, p):
            log.debug("pair %s-%s: %.1f m of wall in seen free space against %.1f m matched", a, b, violation, value)
            return 0.0, violation, None
        return 0.0, 0.0, None

    def meeting(
        self, group_a: list[str], at_a: dict[str, Transform2D], group_b: list[str], at_b: dict[str, Transform2D]
    ) -> Array:
        """Which submaps of two groups, placed in one frame, can touch: the discs about their walls
        (:meth:`_disc`) meet; a boolean ``(len(group_a), len(group_b))`` array."""
        ca, ra = self.discs_at(group_a, at_a)
        cb, rb = self.discs_at(group_b, at_b)
        gap = np.hypot(ca[:, None, 0] - cb[None, :, 0], ca[:, None, 1] - cb[None, :, 1])
        return np.asarray(gap <= ra[:, None] + rb[None, :])

    def discs_at(self, group: list[str], at: dict[str, Transform2D]) -> tuple[Array, Array]:
        """The discs about the walls of ``group``'s submaps (:meth:`_disc`) placed at ``at``: their
        centres ``(n, 2)`` and radii ``(n,)``."""
        n = len(group)
        local = np.empty((n, 2))
        radii = np.empty(n)
        poses = np.empty((n, 3))
        for i, k in enumerate(group):
            local[i], radii[i] = self._disc(k)
            t = at[k]
            poses[i] = t.x, t.y, t.theta
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        centres = np.column_stack(
            (poses[:, 0] + c * local[:, 0] - s * local[:, 1], poses[:, 1] + s * local[:, 0] + c * local[:, 1])
        )
        return centres, radii

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
