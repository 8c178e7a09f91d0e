"""Map alignment by RANSAC over landmark correspondences (Ballesta et al. 2009, Section 3.1).

A second aligner beside the paper's integration, independent of it in how it searches:

1. Landmarks of both maps (corners and segment ends, each with a heading and a descriptor of the
   walls around it, :mod:`fleetmap.shared.core.landmarks`); each landmark of S2 corresponds to the
   :data:`MATCHES` landmarks of S1 of its kind with the most similar descriptors (step 1; the
   paper keeps the single most similar, below a threshold: laser corners look alike more often
   than visual features do, and RANSAC sorts out the wrong ones).
2. Two correspondences (every pair while there are at most :data:`ITERATIONS` of them, else
   that many drawn at random) that keep their distance (the paper's geometric constraint, eq. 1,
   within twice the support distance) give an SE(2) transformation (eqs. 2-4); both landmarks'
   headings must turn by it, within ANGLEDIFFERENCETOLERANCE.
3. Its supports are the correspondences it maps within :data:`SUPPORT_DISTANCE` (th2) with
   their headings turned alike; the transformation with the most supports wins (ties: the smaller
   squared distances), and is refined by least squares on its supports (Umeyama's closed form in
   2D), re-collecting them, until they no longer change.

Pure: numpy in, numpy out. The transformation maps S2's frame into S1's, as everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.candidates import MIN_VERTEX_ANGLE, SEED, IntArray
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.landmarks import Landmarks, find_landmarks
from scipy.spatial import cKDTree

SUPPORT_DISTANCE = 0.2
"""A correspondence supports a transformation that maps it within this (m): the paper's th2 for laser
landmarks (docs/decisions/012-the-other-papers.md)."""
MIN_SUPPORTS = 3
"""A transformation with fewer supports aligns nothing (the paper's min, 20 visual landmarks; a
hypothesis always has the two correspondences it was drawn from)."""
ITERATIONS = 2000
"""Pairs of correspondences tried (the paper's M, 70): every pair while there are at most this many,
else this many drawn at random."""

CHUNK = 2048
"""Hypotheses whose supports are counted at once (bounds the (hypotheses, correspondences) arrays)."""

DESCRIPTOR_RADIUS = 2.0
"""A landmark's descriptor counts the walls within this (m) of it (1 m and 3 m gave the same
successes on the real scan pairs: docs/decisions/012-the-other-papers.md)."""

MATCHES = 3
"""Each landmark of S2 corresponds to this many of S1's, the most similar first (1 and 5 gave the
same successes)."""

REFINE_ROUNDS = 5
"""Least-squares rounds on the supports at most (they settle in two or three)."""


@dataclass(frozen=True)
class RansacAlignment:
    """The RANSAC outcome: the best transformation with its supports, and other hypotheses, best
    first, each with its supports (the caller picks the clearly different ones as rivals)."""

    transform: Transform2D
    supports: int
    others: tuple[tuple[Transform2D, int], ...]
    landmarks: tuple[int, int]
    """How many landmarks each map has."""
    correspondences: int
    hypotheses: int
    """Transformations whose supports were counted."""


def landmarks_of(segments: Array, p: IntegrationParams) -> Landmarks:
    """A map's landmarks with the reach, vertex angle and descriptor radius of ``p``."""
    reach = p.segment_distance_threshold * p.point_distance_tolerance
    return find_landmarks(segments, reach, MIN_VERTEX_ANGLE, DESCRIPTOR_RADIUS)


def correspondences(l1: Landmarks, l2: Landmarks, k: int) -> tuple[IntArray, IntArray]:
    """Step 1: each landmark of S2 with the ``k`` landmarks of S1 of its kind whose descriptors are
    nearest (Euclidean), as (indices in S1, indices in S2)."""
    out1, out2 = [], []
    for kind in np.unique(l2.kinds):
        in1 = np.flatnonzero(l1.kinds == kind)
        in2 = np.flatnonzero(l2.kinds == kind)
        if len(in1) == 0:
            continue
        kk = min(k, len(in1))
        _, j = cKDTree(l1.descriptors[in1]).query(l2.descriptors[in2], k=kk)
        j = np.asarray(j).reshape(len(in2), kk)
        out1.append(in1[j.ravel()])
        out2.append(np.repeat(in2, kk))
    if not out1:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out1), np.concatenate(out2)


def ransac_align(
    s1: Array, s2: Array, p: IntegrationParams, window: Callable[[Array], Array] | None = None
) -> RansacAlignment:
    """Steps 1-3 of the module docstring on segment maps ``s1`` and ``s2``. ``window``, if given,
    says which of ``(t, 3)`` hypotheses lie where S2 is expected: only those are considered."""
    l1, l2 = landmarks_of(s1, p), landmarks_of(s2, p)
    c1, c2 = correspondences(l1, l2, MATCHES)
    none = RansacAlignment(Transform2D.identity(), 0, (), (len(l1), len(l2)), len(c1), 0)
    if len(c1) < 2:
        return none
    p1, p2 = l1.points[c1], l2.points[c2]
    turn = wrap_angle(l1.headings[c1] - l2.headings[c2])
    i, j = _pairs(len(c1), ITERATIONS, SEED)
    t = _hypotheses(p1, p2, turn, i, j, SUPPORT_DISTANCE, p.angle_difference_tolerance)
    if window is not None and len(t):
        t = t[window(t)]
    if len(t) == 0:
        return none
    none = RansacAlignment(Transform2D.identity(), 0, (), (len(l1), len(l2)), len(c1), len(t))
    reach, angle = SUPPORT_DISTANCE, p.angle_difference_tolerance
    counts, errors = _supports(t, p1, p2, turn, reach, angle)
    order = np.lexsort((errors, -counts))
    best = _refined(t[order[0]], p1, p2, turn, reach, angle)
    n_best = int(_support_mask(best.as_array()[None], p1, p2, turn, reach, angle)[0].sum())
    if n_best < MIN_SUPPORTS:
        return none
    others = tuple((Transform2D.from_array(t[k]), int(counts[k])) for k in order[1:] if counts[k] >= MIN_SUPPORTS)
    return RansacAlignment(best, n_best, others, (len(l1), len(l2)), len(c1), len(t))


def _pairs(n: int, limit: int, seed: int) -> tuple[IntArray, IntArray]:
    """Every pair of the ``n`` correspondences, or ``limit`` distinct ones drawn at random."""
    total = n * (n - 1) // 2
    if limit <= 0 or total <= limit:
        i, j = np.triu_indices(n, k=1)
        return i.astype(np.int64), j.astype(np.int64)
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, size=limit)
    j = (i + rng.integers(1, n, size=limit)) % n
    return i, j


def _hypotheses(p1: Array, p2: Array, turn: Array, i: IntArray, j: IntArray, support: float, angle: float) -> Array:
    """Step 2: ``(t, 3)``: the transformation of each pair (i, j) of correspondences that keeps its
    distance (eq. 1) and turns both landmarks' headings alike."""
    v1 = p1[j] - p1[i]
    v2 = p2[j] - p2[i]
    d1, d2 = np.hypot(v1[:, 0], v1[:, 1]), np.hypot(v2[:, 0], v2[:, 1])
    keep = (np.abs(d1 - d2) <= 2 * support) & (d2 > 2 * support)
    i, j, v1, v2 = i[keep], j[keep], v1[keep], v2[keep]
    # Eq. 4: the rotation that turns v2 onto v1.
    theta = np.arctan2(v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0], v2[:, 0] * v1[:, 0] + v2[:, 1] * v1[:, 1])
    agree = (np.abs(wrap_angle(turn[i] - theta)) <= angle) & (np.abs(wrap_angle(turn[j] - theta)) <= angle)
    i, j, theta = i[agree], j[agree], theta[agree]
    # Eqs. 2-3, at the pair's midpoint (the two ends weigh alike).
    c, s = np.cos(theta), np.sin(theta)
    m1 = 0.5 * (p1[i] + p1[j])
    m2 = 0.5 * (p2[i] + p2[j])
    tx = m1[:, 0] - (c * m2[:, 0] - s * m2[:, 1])
    ty = m1[:, 1] - (s * m2[:, 0] + c * m2[:, 1])
    return np.column_stack([tx, ty, theta])


def _support_mask(t: Array, p1: Array, p2: Array, turn: Array, support: float, angle: float) -> Array:
    """Step 3: ``(t, n)``: which correspondences each transformation supports."""
    return _residuals(t, p1, p2, turn, angle) <= support**2


def _residuals(t: Array, p1: Array, p2: Array, turn: Array, angle: float) -> Array:
    """``(t, n)`` squared distances of each correspondence under each transformation (infinite where
    the headings do not turn alike)."""
    c, s = np.cos(t[:, 2:3]), np.sin(t[:, 2:3])
    x = c * p2[:, 0] - s * p2[:, 1] + t[:, 0:1] - p1[:, 0]
    y = s * p2[:, 0] + c * p2[:, 1] + t[:, 1:2] - p1[:, 1]
    d2 = x * x + y * y
    return np.where(np.abs(wrap_angle(turn[None, :] - t[:, 2:3])) <= angle, d2, np.inf)


def _supports(t: Array, p1: Array, p2: Array, turn: Array, support: float, angle: float) -> tuple[Array, Array]:
    """Each hypothesis's number of supports and the sum of their squared distances."""
    counts = np.zeros(len(t), np.int64)
    errors = np.zeros(len(t))
    for start in range(0, len(t), CHUNK):
        r = _residuals(t[start : start + CHUNK], p1, p2, turn, angle)
        inside = r <= support**2
        counts[start : start + CHUNK] = inside.sum(axis=1)
        errors[start : start + CHUNK] = np.where(inside, r, 0.0).sum(axis=1)
    return counts, errors


def _refined(t: Array, p1: Array, p2: Array, turn: Array, support: float, angle: float) -> Transform2D:
    """Least squares on the supports of ``t``, collected again, until they stay the same."""
    best = np.asarray(t, dtype=np.float64)
    mask = _support_mask(best[None], p1, p2, turn, support, angle)[0]
    for _ in range(REFINE_ROUNDS):
        if mask.sum() < 2:
            break
        best = fit_points(p1[mask], p2[mask])
        again = _support_mask(best[None], p1, p2, turn, support, angle)[0]
        if (again == mask).all():
            break
        mask = again
    return Transform2D.from_array(best)


def fit_points(a: Array, b: Array) -> Array:
    """The rigid transformation ``(x, y, theta)`` that maps points ``b`` onto ``a`` in least squares
    (Umeyama 1991 in the plane: the rotation from the centred points' cross and dot products)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, v = a - ca, b - cb
    theta = math.atan2(float((v[:, 0] * u[:, 1] - v[:, 1] * u[:, 0]).sum()), float((v * u).sum()))
    c, s = math.cos(theta), math.sin(theta)
    return np.array([ca[0] - (c * cb[0] - s * cb[1]), ca[1] - (s * cb[0] + c * cb[1]), theta])
