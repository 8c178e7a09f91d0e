"""The candidate transformations an integration weighs, and the distinct ones it refines.

The paper's heuristics (Algorithms 2 and 3, :mod:`fleetmap.shared.core.candidates`) and fleetmap's
segment alignments give candidate transformations (:func:`gather_candidates`); the few best that
are clearly different from each other (:func:`distinct_candidates`, within a :class:`Window` when
the caller knows roughly where the answer lies) are refined by least squares
(:mod:`fleetmap.shared.core.integration`, step 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.candidates import IntArray, find_transformations
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.segmap import SegmentMap

AUTO_MAX_ALL_CANDIDATES = 4000
"""auto also tries the all heuristic when it yields at most this many transformations (small maps,
where trying every pair costs little)."""
DISTINCT_TRANSLATION = 0.10
"""Candidates within this (m) ..."""
DISTINCT_ROTATION = 0.035
"""... and this (rad, 2 degrees) of a better one are the same transformation: the few refined are
different transformations, not one found twice."""

SUPPORT_CELL = (0.1, 0.05)
"""A candidate's support is the number of candidates in its cell of this size (m, rad)."""

AUTO_ORDER = ("consecutive", "histogram", "random", "alignments", "all")
"""What auto tries: the paper's heuristics, fleetmap's segment alignments (for corridors, which
have no angles), and all pairs while the maps are small enough for that to stay cheap."""


def gather_candidates(
    m1: SegmentMap, m2: SegmentMap, heuristic: str, params: IntegrationParams
) -> tuple[Array, IntArray]:
    """Candidate transformations and the index (in AUTO_ORDER) of the heuristic behind each."""
    names = AUTO_ORDER if heuristic == "auto" else (heuristic,)
    parts, labels = [], []
    for name in names:
        if heuristic != "auto" and name == "alignments":
            continue
        if heuristic == "auto" and name == "all":
            # auto tries all pairs only while that stays cheap (small maps).
            n1, n2 = len(m1), len(m2)
            if (
                n1 * (n1 - 1) / 2 * n2 * (n2 - 1) * params.angle_difference_tolerance / math.pi
                > AUTO_MAX_ALL_CANDIDATES
            ):
                continue
        t = find_transformations(m1, m2, name, params)
        parts.append(t)
        labels.append(np.full(len(t), AUTO_ORDER.index(name), dtype=np.int64))
    if not parts:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.vstack(parts), np.concatenate(labels)


def distinct_candidates(t: Array, labels: IntArray, params: IntegrationParams) -> tuple[Array, IntArray]:
    """Candidates closer than POINTDISTANCETOLERANCE and 0.3 degrees are one; most supported first.

    Support is the number of candidates in the same 0.1 m / 0.05 rad cell: the right
    transformation is usually found from many angle pairs, so evaluating the most supported
    candidates first lets the early stop prune the rest.
    """
    if len(t) == 0:
        return t, labels
    q = params.point_distance_tolerance
    _, first = np.unique(cell_keys(t, q, 0.005), return_index=True)
    _, cell, support = np.unique(cell_keys(t, *SUPPORT_CELL), return_inverse=True, return_counts=True)
    keep = np.sort(first)
    order = np.lexsort((keep, -support[cell.ravel()[keep]]))
    chosen = keep[order]
    return t[chosen], labels[chosen]


def cell_keys(t: Array, step: float, angle_step: float) -> IntArray:
    """One integer per candidate naming its (step, step, angle_step) cell: a 1-D key sorts far
    faster than ``np.unique(..., axis=0)`` on the three cell indices."""
    x, y, a = (np.round(t[:, i] / s).astype(np.int64) for i, s in enumerate((step, step, angle_step)))
    x -= x.min()
    y -= y.min()
    a -= a.min()
    return (x * (y.max() + 1) + y) * (a.max() + 1) + a


def _in_window(t: Array, labels: IntArray, window: Window | None) -> tuple[Array, IntArray]:
    if window is None or len(t) == 0:
        return t, labels
    keep = window.contains(t)
    return t[keep], labels[keep]


def _pick_distinct(t: Array, values: Array, k: int, p: IntegrationParams) -> list[int]:
    """Indices of the k best candidates that differ by more than :data:`DISTINCT_TRANSLATION` or
    :data:`DISTINCT_ROTATION`."""
    picked: list[int] = []
    for idx in np.argsort(-values, kind="stable"):
        if values[idx] <= 0 or len(picked) >= k:
            break
        if not any(_alike(t, idx, j) for j in picked):
            picked.append(int(idx))
    return picked


def _alike(t: Array, i: int, j: int) -> bool:
    """Whether candidates i and j are within :data:`DISTINCT_TRANSLATION` and :data:`DISTINCT_ROTATION`
    of each other."""
    d = math.hypot(t[i, 0] - t[j, 0], t[i, 1] - t[j, 1])
    return d < DISTINCT_TRANSLATION and abs(math.remainder(t[i, 2] - t[j, 2], 2 * math.pi)) < DISTINCT_ROTATION


def settled_ahead(t: Array, scores: Array, p: IntegrationParams) -> list[bool]:
    """For each refined pick ``t`` (``(n, 3)``) that scores, whether a better-scoring one lies within
    :data:`DISTINCT_TRANSLATION` and :data:`DISTINCT_ROTATION` of it (not among the distinct ones,
    :func:`_pick_distinct`): the first refinement steps brought the two into one minimum, and
    refined on they would end as one transformation found twice, so only the better one is
    (docs/decisions/064-a-pick-settled-into-a-better-ones-minimum-is-not-refined-on.md)."""
    kept = set(_pick_distinct(t, scores, len(scores), p))
    return [n not in kept and float(scores[n]) > 0 for n in range(len(scores))]


def _also_by_value(t: Array, values: Array, picked: list[int], k: int, p: IntegrationParams) -> list[int]:
    """The k best-valued candidates apart from the ``picked`` ones and from each other.

    Scans with noisy walls (short segments whose directions are off by a degree or two) give
    candidates near the right transformation that are off by a few tenths of a metre: they match
    the most wall, but put much of it in the other scan's seen free space, which the right
    transformation, once refined, does not. The free space judges a transformation only once it
    is refined, so these are refined too, and scored after
    (docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
    kept: list[int] = []
    for j in _pick_distinct(t, values, k + len(picked), p):
        if len(kept) >= k:
            break
        if not any(_alike(t, j, i) for i in picked):
            kept.append(j)
    return kept


@dataclass(frozen=True)
class Window:
    """Where S2 is expected on S1 (fleetmap: a robot's recent motion predicts its next scan's pose):
    only transformations within ``radius`` (m) and ``rotation`` (rad) of ``centre`` are considered."""

    centre: Transform2D
    radius: float
    rotation: float

    def contains(self, t: Array) -> Array:
        """Which of the ``(n, 3)`` transformations ``t`` lie in the window."""
        c = self.centre
        near = np.hypot(t[:, 0] - c.x, t[:, 1] - c.y) <= self.radius
        return np.asarray(near & (np.abs(wrap_angle(t[:, 2] - c.theta)) <= self.rotation))
