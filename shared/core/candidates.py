"""Find transformations (paper III-A, Algorithms 2 and 3).

An *angle* is a pair of non-parallel segments of one map; its value is the oriented angle from
the first segment to the second and its *vertex* is where their supporting lines cross. A
transformation superimposes an angle of S2 on an equal angle of S1: the rotation brings the
directions of the two segments onto those of S1's, the translation brings vertex onto vertex.

Heuristics (which pairs of segments form the angles):

- ``all``: every pair (Algorithm 2).
- ``consecutive``: consecutive segments (III-A-1): in the improved variant, consecutive in scan
  order whether or not they touch, both longer than SEGMENTLENGTHPERCENTAGE % of the longest
  segment; in the plain variant (``consecutive_touching_only``) only segments with a common
  extreme. Maps without an order use segments whose extremes coincide.
- ``random``: Algorithm 3, K rounds of N_k = 20 * 2**k draws among segments longer than
  SEGMENTDIVISIONFACTOR**k times the longest, with a seeded generator.
- ``histogram``: segments of the principal and normal directions of the orientation histogram
  (III-A-3).

All of it is vectorised: an angle set is a handful of arrays, and matching two angle sets is a
sort and two binary searches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.geometry import Array, lengths, orientations, wrap_angle
from fleetmap.shared.core.segmap import SegmentMap
from numpy.typing import NDArray
from scipy.spatial import cKDTree

IntArray = NDArray[Any]

SEED = 0
"""Seed of the random heuristic's generator (Algorithm 3), so the same maps give the same result."""
MAX_ANGLES = 300
"""The consecutive and histogram heuristics use at most this many angles per map, those of the
longest segments: large partial maps would give hundreds of millions of matches."""
MIN_VERTEX_ANGLE = 0.35
"""Two segments closer to parallel than this (rad, 20 degrees) form no angle: their vertex is ill
defined (a small rotation moves it metres along the walls)."""


@dataclass(frozen=True)
class AngleSet:
    """Angles between pairs of segments of one map (Algorithm 2, steps 1-8)."""

    first: IntArray
    second: IntArray
    alpha: Array
    """Oriented angle from the first segment to the second (wrapped to the angle period)."""
    vertex: Array
    """``(a, 2)``: where the two supporting lines cross."""
    phi_first: Array
    phi_second: Array

    def __len__(self) -> int:
        return int(self.first.shape[0])


def angle_set(
    segments: Array, first: IntArray, second: IntArray, params: IntegrationParams, period: float, limit: int = 0
) -> AngleSet:
    """Angles of the given segment pairs, without pairs too close to parallel to have a vertex.

    With ``limit`` > 0 only that many angles are kept, those whose shorter segment is longest
    (the paper's own preference: long segments are the reliable ones). Large partial maps would
    otherwise give angle sets whose matches run into the hundreds of millions.
    """
    phi = orientations(segments)
    alpha = np.mod(phi[second] - phi[first] + period / 2, period) - period / 2
    keep = np.abs(np.sin(alpha)) >= math.sin(MIN_VERTEX_ANGLE)
    first, second, alpha = first[keep], second[keep], alpha[keep]
    if 0 < limit < len(first):
        ln = lengths(segments)
        best = np.argsort(-np.minimum(ln[first], ln[second]), kind="stable")[:limit]
        best.sort()
        first, second, alpha = first[best], second[best], alpha[best]
    a = segments[first]
    b = segments[second]
    ux, uy = a[:, 2] - a[:, 0], a[:, 3] - a[:, 1]
    vx, vy = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    det = ux * vy - uy * vx
    wx, wy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    s = (wx * vy - wy * vx) / det
    vertex = np.column_stack([a[:, 0] + s * ux, a[:, 1] + s * uy])
    return AngleSet(first, second, alpha, vertex, phi[first], phi[second])


def _both_orders(first: IntArray, second: IntArray) -> tuple[IntArray, IntArray]:
    return np.concatenate([first, second]), np.concatenate([second, first])


def pairs_all(n: int) -> tuple[IntArray, IntArray]:
    """Every unordered pair i < j."""
    i, j = np.triu_indices(n, k=1)
    return i.astype(np.int64), j.astype(np.int64)


def touching_pairs(segments: Array, tolerance: float) -> tuple[IntArray, IntArray]:
    """Pairs of segments with a common extreme (closer than ``tolerance``), i < j."""
    n = len(segments)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ends = segments.reshape(-1, 2)
    pairs = cKDTree(ends).query_pairs(tolerance, output_type="ndarray")
    i, j = pairs[:, 0] // 2, pairs[:, 1] // 2
    keep = i != j
    i, j = np.minimum(i[keep], j[keep]), np.maximum(i[keep], j[keep])
    if len(i) == 0:
        return i.astype(np.int64), j.astype(np.int64)
    uniq = np.unique(np.column_stack([i, j]), axis=0)
    return uniq[:, 0].astype(np.int64), uniq[:, 1].astype(np.int64)


def pairs_consecutive(m: SegmentMap, params: IntegrationParams) -> tuple[IntArray, IntArray]:
    """Consecutive segments (III-A-1), in the variant the parameters choose."""
    seg = m.segments
    n = len(seg)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not m.ordered:
        return touching_pairs(seg, params.point_distance_tolerance)
    i = np.arange(n - 1, dtype=np.int64)
    j = i + 1
    if params.consecutive_touching_only:
        gap = np.hypot(seg[i, 2] - seg[j, 0], seg[i, 3] - seg[j, 1])
        keep = gap < params.point_distance_tolerance
    else:
        ln = lengths(seg)
        long_enough = ln >= params.segment_length_percentage / 100.0 * ln.max()
        keep = long_enough[i] & long_enough[j]
    return i[keep], j[keep]


def pairs_histogram(segments: Array, params: IntegrationParams) -> tuple[IntArray, IntArray]:
    """Pairs of a principal-direction and a normal-direction segment (III-A-3)."""
    n = len(segments)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    slots = max(int(params.nslots), 2)
    direction = np.mod(orientations(segments), math.pi)
    bucket = np.minimum((direction / math.pi * slots).astype(np.int64), slots - 1)
    hist = np.bincount(bucket, weights=lengths(segments), minlength=slots)
    principal = int(np.argmax(hist))
    normal = (principal + slots // 2) % slots
    p = np.flatnonzero(bucket == principal)
    q = np.flatnonzero(bucket == normal)
    if len(p) == 0 or len(q) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pi, qi = np.meshgrid(p, q, indexing="ij")
    return pi.ravel().astype(np.int64), qi.ravel().astype(np.int64)


def match_angles(a1: AngleSet, a2: AngleSet, params: IntegrationParams, period: float) -> Array:
    """Transformations ``(t, 3)`` superimposing each angle of S2 on every equal angle of S1
    (Algorithm 2, steps 9-14)."""
    if len(a1) == 0 or len(a2) == 0:
        return np.zeros((0, 3))
    tol = params.angle_difference_tolerance
    order = np.argsort(a2.alpha, kind="stable")
    sorted_alpha = a2.alpha[order]
    ext_alpha = np.concatenate([sorted_alpha - period, sorted_alpha, sorted_alpha + period])
    ext_index = np.concatenate([order, order, order])
    lo = np.searchsorted(ext_alpha, a1.alpha - tol, side="left")
    hi = np.searchsorted(ext_alpha, a1.alpha + tol, side="right")
    owner, pos = ragged_ranges(lo, hi)
    p = owner
    q = ext_index[pos]
    return _superimpose(a1, p, a2, q, period)


def _superimpose(a1: AngleSet, p: IntArray, a2: AngleSet, q: IntArray, period: float) -> Array:
    """The rototranslation bringing angle q of S2 onto angle p of S1.

    The rotation is the mean of the two segment-direction differences; for unoriented maps
    (period pi) a segment's direction is known only up to pi, so both readings are returned.
    """
    th_a = a1.phi_first[p] - a2.phi_first[q]
    th_b = a1.phi_second[p] - a2.phi_second[q]
    half = period / 2
    diff = np.mod(th_b - th_a + half, period) - half
    theta = th_a + 0.5 * diff
    if period < 2 * math.pi:
        theta = np.mod(theta, period)
        theta = np.concatenate([theta, theta + math.pi])
        p = np.concatenate([p, p])
        q = np.concatenate([q, q])
    theta = wrap_angle(theta)
    c, s = np.cos(theta), np.sin(theta)
    v2 = a2.vertex[q]
    v1 = a1.vertex[p]
    tx = v1[:, 0] - (c * v2[:, 0] - s * v2[:, 1])
    ty = v1[:, 1] - (s * v2[:, 0] + c * v2[:, 1])
    return np.column_stack([tx, ty, theta])


def ragged_ranges(lo: IntArray, hi: IntArray) -> tuple[IntArray, IntArray]:
    """For ranges ``[lo[r], hi[r])``: the owner r and the position of every element."""
    counts = np.maximum(hi - lo, 0)
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(lo), dtype=np.int64), counts)
    starts = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    return owner, np.arange(total, dtype=np.int64) + starts


def random_transformations(
    s1: Array, s2: Array, params: IntegrationParams, period: float, rng: np.random.Generator
) -> Array:
    """Algorithm 3: angles between randomly drawn segments, longer ones first."""
    out = []
    l1, l2 = lengths(s1), lengths(s2)
    phi1, phi2 = orientations(s1), orientations(s2)
    for k in range(1, int(params.random_iterations) + 1):
        n_k = int(params.random_base_samples) * 2**k
        f = params.segment_division_factor**k
        c1 = np.flatnonzero(l1 > f * l1.max())
        c2 = np.flatnonzero(l2 > f * l2.max())
        if len(c1) < 2 or len(c2) < 2:
            continue
        i1, j1 = _draw_pairs(c1, n_k, rng)
        i2, j2 = _draw_pairs(c2, n_k, rng)
        alpha1 = np.mod(phi1[j1] - phi1[i1] + period / 2, period) - period / 2
        alpha2 = np.mod(phi2[j2] - phi2[i2] + period / 2, period) - period / 2
        same = np.abs(np.mod(alpha1 - alpha2 + period / 2, period) - period / 2) < params.angle_difference_tolerance
        if not same.any():
            continue
        a1 = angle_set(s1, i1[same], j1[same], params, period)
        a2 = angle_set(s2, i2[same], j2[same], params, period)
        # angle_set drops near-parallel pairs; keep the draws whose both angles survived.
        keep1 = np.abs(np.sin(alpha1[same])) >= math.sin(MIN_VERTEX_ANGLE)
        keep2 = np.abs(np.sin(alpha2[same])) >= math.sin(MIN_VERTEX_ANGLE)
        both = keep1 & keep2
        p = np.cumsum(keep1)[both] - 1
        q = np.cumsum(keep2)[both] - 1
        if len(p):
            out.append(_superimpose(a1, p, a2, q, period))
    return np.vstack(out) if out else np.zeros((0, 3))


def _draw_pairs(candidates: IntArray, n: int, rng: np.random.Generator) -> tuple[IntArray, IntArray]:
    """n draws of two distinct segments, uniformly among ``candidates``."""
    m = len(candidates)
    a = rng.integers(0, m, size=n)
    b = rng.integers(0, m - 1, size=n)
    b = b + (b >= a)
    return candidates[a], candidates[b]


def segment_alignments(s1: Array, s2: Array, params: IntegrationParams, period: float, top: int = 12) -> Array:
    """Transformations laying one long segment of S2 on one of S1, extreme on extreme (fleetmap).

    Angles need two non-parallel segments; a corridor scan may have none, only parallel walls.
    There the longest segments are aligned directly (direction on direction, first extreme on
    first extreme and second on second), which the evaluation then ranks like any other candidate.
    """
    l1, l2 = lengths(s1), lengths(s2)
    i = np.argsort(-l1, kind="stable")[:top]
    k = np.argsort(-l2, kind="stable")[:top]
    i = i[l1[i] >= params.segment_length_refuse / 2]
    k = k[l2[k] >= params.segment_length_refuse / 2]
    if len(i) == 0 or len(k) == 0:
        return np.zeros((0, 3))
    ii, kk = (a.ravel() for a in np.meshgrid(i, k, indexing="ij"))
    theta = orientations(s1)[ii] - orientations(s2)[kk]
    out = []
    flips = (0.0, math.pi) if period < 2 * math.pi else (0.0,)
    for flip in flips:
        th = wrap_angle(theta + flip)
        c, s = np.cos(th), np.sin(th)
        ends2 = ((0, 2), (2, 0)) if flip else ((0, 0), (2, 2))
        for e1, e2 in ends2:
            px, py = s2[kk, e2], s2[kk, e2 + 1]
            out.append(np.column_stack([s1[ii, e1] - (c * px - s * py), s1[ii, e1 + 1] - (s * px + c * py), th]))
    return np.vstack(out)


def find_transformations(m1: SegmentMap, m2: SegmentMap, heuristic: str, params: IntegrationParams) -> Array:
    """Candidate transformations ``(t, 3)`` of S2 on S1 for one heuristic (not auto)."""
    oriented = m1.oriented and m2.oriented
    period = 2 * math.pi if oriented else math.pi
    s1, s2 = m1.segments, m2.segments
    if heuristic == "random":
        rng = np.random.default_rng(SEED)
        t = random_transformations(s1, s2, params, period, rng)
    elif heuristic == "alignments":
        t = segment_alignments(s1, s2, params, period)
    else:
        if heuristic == "all":
            p1 = pairs_all(len(s1))
            p2 = pairs_all(len(s2))
        elif heuristic == "consecutive":
            p1 = pairs_consecutive(m1, params)
            p2 = pairs_consecutive(m2, params)
        elif heuristic == "histogram":
            p1 = pairs_histogram(s1, params)
            p2 = pairs_histogram(s2, params)
        else:
            raise ValueError(f"unknown heuristic {heuristic!r}")
        limit = 0 if heuristic == "all" else MAX_ANGLES
        a1 = angle_set(s1, p1[0], p1[1], params, period, limit)
        a2 = angle_set(s2, *_both_orders(*p2), params, period, 2 * limit)
        t = match_angles(a1, a2, params, period)
    return t
