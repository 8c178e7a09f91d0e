"""Evaluate transformations (paper III-B, Algorithm 4), vectorised over candidates and pairs.

The transformation value of t is the sum of the matching values of every pair (s1, s2^t)
(:func:`fleetmap.shared.core.geometry.matching_value`); t is discarded when it makes two segments
longer than SEGMENTLENGTHREFUSE cross (steps 6-8).

What makes it fast without changing the result that matters:

- A pair contributes only if its segments overlap once projected and are within
  SEGMENTDISTANCETHRESHOLD * POINTDISTANCETOLERANCE (d) of each other. Pairs are looked up
  by orientation: all pairs (i, k) are sorted by the rotation that would make them parallel, so
  the pairs near parallel under a candidate's rotation are one binary search away, and a
  midpoint-distance test (exact: segments whose midpoints are farther apart than their half
  lengths plus the threshold cannot overlap) prunes the rest before the exact computation.
  Pairs more than :data:`PAIR_ANGLE_LIMIT` from parallel are skipped: for them d <= D forces the
  shorter segment to be shorter than 2D / sin(angle), so their matching value is at most
  2D cot(angle), under 0.15 m at the default D = 75 mm, and in practice zero.
- The early stop of III-B: S1's segments are taken longest first in blocks; after each block a
  candidate whose value plus the length of S1 not yet evaluated cannot reach the best value
  known (from the most supported candidates, evaluated first) is dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.candidates import IntArray, ragged_ranges
from fleetmap.shared.core.geometry import Array, lengths, matching_value, orientations
from fleetmap.shared.core.pairkernel import near_matching_values
from fleetmap.shared.core.work import PAIR_FOUND, PAIR_VALUED, SELF_CROSSING, Work
from scipy.spatial import cKDTree

CHUNK_ENTRIES = 1_500_000
"""Candidate-pair entries processed at once: bounds memory to a few tens of MB."""


PAIR_ANGLE_LIMIT = 0.5
"""Segment pairs further from parallel than this (rad) are not evaluated: their matching value is at
most 2D cot(angle), under 0.15 m at the default D (above)."""
REFUSE_RANGE_SLOPE = 0.01
"""The margin by which two long segments must cross to refuse grows by this (m) per metre of a scan
segment's range: a far wall is fixed by a few sparse points (edmonton's consecutive pairs: 165 of 199
right and valid, 147 at 0; docs/decisions/006-real-lasers-extraction-and-refusal.md)."""

DENSE_PAIRS = 250_000
"""Up to this many segment pairs, one transformation's pairs are found densely; above, with a k-d tree."""


@dataclass(frozen=True)
class PreparedPairs:
    """Everything about S1 x S2 that does not depend on the candidate transformation."""

    s1: Array
    s2: Array
    period: float
    len1: Array
    mid1: Array
    half1: Array
    mid2: Array
    half2: Array
    long1: IntArray
    long2: IntArray
    reach1: Array
    reach2: Array
    """Each long segment's crossing margin (m, see :func:`refused`), in ``long1``/``long2`` order."""
    phi1: Array
    phi2: Array
    cache: dict[str, object] = field(default_factory=dict, compare=False, repr=False)
    """Built on first use: the pair table for many candidates (per block of S1, longest segments
    first: sorted pair rotations tripled for wrap-around, the pair behind each, and the pairs' S1
    and S2 indices, with the length of S1 left after each block) and S1's k-d tree."""
    work: Work = field(default_factory=Work, compare=False, repr=False)
    """The integration's work so far, charged by every stage that compares pairs
    (:mod:`fleetmap.shared.core.work`)."""

    @property
    def blocks(self) -> list[tuple[IntArray, Array, IntArray, IntArray]]:
        return _blocks(self)[0]

    @property
    def remaining_after(self) -> list[float]:
        return _blocks(self)[1]


def prepare(
    s1: Array,
    s2: Array,
    oriented: bool,
    params: IntegrationParams,
    scan1: bool = False,
    scan2: bool = False,
    work: Work | None = None,
) -> PreparedPairs:
    """The pairs of S1 x S2 prepared for many candidates; ``scan1``/``scan2``: the map is a scan
    seen from its frame's origin (its far walls are fixed less well: :func:`refused`); ``work``:
    the integration's budget, charged here and by every evaluation on these pairs."""
    work = Work() if work is None else work
    period = 2 * math.pi if oriented else math.pi
    len1, len2 = lengths(s1), lengths(s2)
    refuse = params.segment_length_refuse
    long1, long2 = np.flatnonzero(len1 > refuse), np.flatnonzero(len2 > refuse)
    work.charge(SELF_CROSSING * ((0 if scan1 else len(long1) ** 2) + (0 if scan2 else len(long2) ** 2)))
    # a map whose own long walls cross (walls fused from many views meeting at a junction) breaks
    # the premise of steps 6-8 for those walls: crossing them says nothing of a transformation
    if not scan1:
        long1 = long1[~_self_crossing(s1[long1], _crossing_margins(s1[long1], False, params))]
    if not scan2:
        long2 = long2[~_self_crossing(s2[long2], _crossing_margins(s2[long2], False, params))]
    return PreparedPairs(
        s1=s1,
        s2=s2,
        period=period,
        len1=len1,
        mid1=0.5 * (s1[:, 0:2] + s1[:, 2:4]),
        half1=0.5 * len1,
        mid2=0.5 * (s2[:, 0:2] + s2[:, 2:4]),
        half2=0.5 * len2,
        long1=long1,
        long2=long2,
        reach1=_crossing_margins(s1[long1], scan1, params),
        reach2=_crossing_margins(s2[long2], scan2, params),
        phi1=orientations(s1),
        phi2=orientations(s2),
        work=work,
    )


def _blocks(prep: PreparedPairs) -> tuple[list[tuple[IntArray, Array, IntArray, IntArray]], list[float]]:
    """The pair table for many candidates, built on first use (see PreparedPairs.blocks)."""
    cached = prep.cache.get("blocks")
    if cached is not None:
        return cached  # type: ignore[return-value]
    s1, s2, period = prep.s1, prep.s2, prep.period
    prep.work.charge(len(s1) * len(s2))
    len1, phi1, phi2 = prep.len1, prep.phi1, prep.phi2
    order1 = np.argsort(-len1, kind="stable")
    cum = np.cumsum(len1[order1])
    total = float(cum[-1]) if len(cum) else 0.0
    # Block edges at fixed fractions of S1's length: the first block holds the longest segments.
    edges = [0]
    for f in BLOCK_FRACTIONS:
        e = int(np.searchsorted(cum, f * total - 1e-12, side="left")) + 1
        e = min(max(e, edges[-1] + 1), len(s1))
        if e > edges[-1]:
            edges.append(e)
    if edges[-1] < len(s1):
        edges.append(len(s1))
    block_list = []
    remaining = []
    n2 = len(s2)
    for b in range(len(edges) - 1):
        rows = order1[edges[b] : edges[b + 1]]
        i = np.repeat(rows, n2)
        k = np.tile(np.arange(n2), len(rows))
        order, ext = _by_rotation(_wrapped(phi1[i] - phi2[k], period), period)
        block_list.append((order, ext, i, k))
        remaining.append(total - float(cum[edges[b + 1] - 1]))
    prep.cache["blocks"] = (block_list, remaining)
    return block_list, remaining


def _wrapped(a: Array, period: float) -> Array:
    """Angles wrapped to [-period / 2, period / 2)."""
    return np.mod(a + period / 2, period) - period / 2


def _by_rotation(rot: Array, period: float) -> tuple[IntArray, Array]:
    """Pairs sorted by the rotation that makes them parallel (``rot``, wrapped), the sorted
    rotations repeated a period below and above so that a window wrapping round is one slice:
    the pairs' order three times over, and those rotations."""
    order = np.argsort(rot, kind="stable")
    rs = rot[order]
    return np.concatenate([order, order, order]), np.concatenate([rs - period, rs, rs + period])


BLOCK_FRACTIONS = (0.5, 0.8, 1.0)
"""S1 is evaluated in blocks holding these fractions of its length, longest segments first."""


def _crossing_margins(long: Array, scan: bool, params: IntegrationParams) -> Array:
    """How far (m) each long segment must reach beyond another's line, and the other beyond its,
    for the two to cross (:func:`refused`): SEGMENTDISTANCETHRESHOLD * POINTDISTANCETOLERANCE,
    plus, for a scan's segment, :data:`REFUSE_RANGE_SLOPE` times its midpoint's distance from the
    sensor."""
    margin = np.full(len(long), params.segment_distance_threshold * params.point_distance_tolerance)
    if scan and REFUSE_RANGE_SLOPE > 0:
        margin += REFUSE_RANGE_SLOPE * np.hypot(0.5 * (long[:, 0] + long[:, 2]), 0.5 * (long[:, 1] + long[:, 3]))
    return margin


def _lines(segments: Array) -> tuple[Array, Array]:
    """Each segment's line: its unit normal (left of its direction) and offset (normal . point)."""
    u = segments[:, 2:4] - segments[:, 0:2]
    normal = np.column_stack([-u[:, 1], u[:, 0]]) / np.hypot(u[:, 0], u[:, 1])[:, None]
    return normal, np.einsum("ij,ij->i", normal, segments[:, 0:2])


def _self_crossing(long: Array, reach: Array) -> Array:
    """Which of a map's long segments cross another of its own (as :func:`refused` reads "cross")."""
    n = len(long)
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    normal, offset = _lines(long)
    margin = 0.5 * (reach[:, None] + reach[None, :])
    d1 = normal @ long[:, 0:2].T - offset[:, None]  # (i, j): j's first end from i's line
    d2 = normal @ long[:, 2:4].T - offset[:, None]
    j_crosses_i = (np.minimum(d1, d2) < -margin) & (np.maximum(d1, d2) > margin)
    both = j_crosses_i & j_crosses_i.T
    np.fill_diagonal(both, False)
    return np.asarray(both.any(axis=1))


def refused(prep: PreparedPairs, t: Array, params: IntegrationParams) -> Array:
    """Algorithm 4, steps 6-8: candidates that make two long segments cross.

    Two segments longer than SEGMENTLENGTHREFUSE that cross each other cannot both be walls seen
    by the two maps, unless a map's own walls already cross there: a map's long segments that
    cross another of its own (walls fused from many views) are left out (:func:`prepare`).
    "Cross" is read strictly: each segment reaches more than a margin beyond the other's line on
    both sides, the mean of the two segments' margins (:func:`_crossing_margins`):
    SEGMENTDISTANCETHRESHOLD * POINTDISTANCETOLERANCE, and more for a scan's far segments. Two
    walls meeting at a corner touch (and, with extraction noise, overshoot a little) without
    crossing, and two nearly parallel segments that overlap are a match, not a contradiction. A
    far wall is fixed by a few sparse points, so its line may turn by tens of degrees and cross
    another scan's line of the same wall: hence a scan's margin grows with range
    (docs/decisions/006-real-lasers-extraction-and-refusal.md).
    """
    out = np.zeros(len(t), dtype=bool)
    if len(prep.long1) == 0 or len(prep.long2) == 0 or len(t) == 0:
        return out
    a = prep.s1[prep.long1]
    b = prep.s2[prep.long2]
    prep.work.charge(len(t) * len(a) * len(b))
    margin = (0.5 * (prep.reach1[:, None] + prep.reach2[None, :]))[None]  # (1, na, nb)
    na, ca = _lines(a)
    ca = ca[None, :, None]
    nb0, _ = _lines(b)
    step = max(1, CHUNK_ENTRIES // (len(a) * len(b)))
    for c0 in range(0, len(t), step):
        tc = t[c0 : c0 + step]
        bt = _transform(b, tc)  # (c, nb, 4)
        cos, sin = np.cos(tc[:, 2])[:, None], np.sin(tc[:, 2])[:, None]
        nb = np.stack([cos * nb0[:, 0] - sin * nb0[:, 1], sin * nb0[:, 0] + cos * nb0[:, 1]], axis=1)  # (c, 2, nb)
        cb = (nb[:, 0, :] * bt[:, :, 0] + nb[:, 1, :] * bt[:, :, 1])[:, None, :]
        # Signed distances (c, na, nb) of b's ends from a's lines and of a's ends from b's lines,
        # each a normal dotted with a point minus the line's offset: as matrix products, about
        # twice as fast as broadcasting the coordinates one by one.
        db1 = np.matmul(na, bt[:, :, 0:2].transpose(0, 2, 1)) - ca
        db2 = np.matmul(na, bt[:, :, 2:4].transpose(0, 2, 1)) - ca
        b_crosses_a = (np.minimum(db1, db2) < -margin) & (np.maximum(db1, db2) > margin)
        da1 = np.matmul(a[:, 0:2], nb) - cb
        da2 = np.matmul(a[:, 2:4], nb) - cb
        a_crosses_b = (np.minimum(da1, da2) < -margin) & (np.maximum(da1, da2) > margin)
        out[c0 : c0 + step] = (b_crosses_a & a_crosses_b).any(axis=(1, 2))
    return out


def _transform(seg: Array, t: Array) -> Array:
    c = np.cos(t[:, 2])[:, None]
    s = np.sin(t[:, 2])[:, None]
    out = np.empty((len(t), len(seg), 4))
    for k in (0, 2):
        out[:, :, k] = c * seg[None, :, k] - s * seg[None, :, k + 1] + t[:, 0, None]
        out[:, :, k + 1] = s * seg[None, :, k] + c * seg[None, :, k + 1] + t[:, 1, None]
    return out


def _block_values(
    prep: PreparedPairs, block: int, t: Array, params: IntegrationParams, want_pairs: bool = False
) -> tuple[Array, tuple[IntArray, IntArray, IntArray, Array] | None]:
    """Sum of matching values over the pairs of one S1 block, for each candidate."""
    order, ext, pi, pk = prep.blocks[block]
    d_max = params.segment_distance_threshold * params.point_distance_tolerance
    theta = _wrapped(t[:, 2], prep.period)
    lo = np.searchsorted(ext, theta - PAIR_ANGLE_LIMIT, side="left")
    hi = np.searchsorted(ext, theta + PAIR_ANGLE_LIMIT, side="right")
    values = np.zeros(len(t))
    found: list[tuple[IntArray, IntArray, IntArray, Array]] = []
    counts = hi - lo
    c0 = 0
    while c0 < len(t):
        # As many candidates as fit in one chunk of entries.
        csum = np.cumsum(counts[c0:])
        c1 = c0 + max(1, int(np.searchsorted(csum, CHUNK_ENTRIES, side="right")))
        prep.work.charge(PAIR_VALUED * int(csum[c1 - c0 - 1]))
        owner, pos = ragged_ranges(lo[c0:c1], hi[c0:c1])
        pair = order[pos]
        i = pi[pair]
        k = pk[pair]
        tc = t[c0:c1]
        cos = np.cos(tc[:, 2])
        sin = np.sin(tc[:, 2])
        oc, os_ = cos[owner], sin[owner]
        m2 = prep.mid2[k]
        mx = oc * m2[:, 0] - os_ * m2[:, 1] + tc[owner, 0]
        my = os_ * m2[:, 0] + oc * m2[:, 1] + tc[owner, 1]
        reach = prep.half1[i] + prep.half2[k] + d_max
        near = (mx - prep.mid1[i, 0]) ** 2 + (my - prep.mid1[i, 1]) ** 2 <= reach * reach
        owner, i, k, oc, os_ = owner[near], i[near], k[near], oc[near], os_[near]
        b = prep.s2[k]
        tx, ty = tc[owner, 0], tc[owner, 1]
        bt = np.column_stack(
            [
                oc * b[:, 0] - os_ * b[:, 1] + tx,
                os_ * b[:, 0] + oc * b[:, 1] + ty,
                oc * b[:, 2] - os_ * b[:, 3] + tx,
                os_ * b[:, 2] + oc * b[:, 3] + ty,
            ]
        )
        mv = matching_value(
            prep.s1[i],
            bt,
            params.point_distance_tolerance,
            params.segment_distance_threshold,
            params.penalization_base,
        )
        values[c0:c1] += np.bincount(owner, weights=mv, minlength=c1 - c0)
        if want_pairs:
            pos_mv = mv > 0
            found.append((owner[pos_mv] + c0, i[pos_mv], k[pos_mv], mv[pos_mv]))
        c0 = c1
    if not want_pairs:
        return values, None
    if not found:
        z = np.zeros(0, np.int64)
        return values, (z, z, z, np.zeros(0))
    return values, tuple(np.concatenate(parts) for parts in zip(*found, strict=True))  # type: ignore[return-value]


def transformation_values(
    prep: PreparedPairs,
    t: Array,
    params: IntegrationParams,
    best_known: float | None = None,
) -> Array:
    """The transformation value of each candidate (Algorithm 4, steps 2-23).

    Discarded candidates (steps 6-8) get -1. With ``best_known`` (the early stop of III-B), a
    candidate whose value plus the length of S1 not yet evaluated falls below ``best_known`` is
    dropped and also gets -1: it cannot be the best.
    """
    values = np.zeros(len(t))
    alive = ~refused(prep, t, params)
    values[~alive] = -1.0
    for b in range(len(prep.blocks)):
        idx = np.flatnonzero(alive)
        if len(idx) == 0:
            break
        v, _ = _block_values(prep, b, t[idx], params)
        values[idx] += v
        if best_known is not None and b + 1 < len(prep.blocks):
            hopeless = values[idx] + prep.remaining_after[b] < best_known
            values[idx[hopeless]] = -1.0
            alive[idx[hopeless]] = False
    return values


def matched_pairs(prep: PreparedPairs, t: Array, params: IntegrationParams) -> tuple[IntArray, IntArray, Array]:
    """Pairs (i in S1, k in S2) with a positive matching value under one transformation.

    The pairs near parallel under its rotation come from the pairs sorted by rotation
    (:func:`_dense_parallel`; from a k-d tree of S1 for large maps), then the midpoint filter.
    """
    x, y, theta = (float(v) for v in np.asarray(t, dtype=np.float64).reshape(3))
    c, s = math.cos(theta), math.sin(theta)
    s2 = prep.s2
    bt = np.column_stack(
        [
            c * s2[:, 0] - s * s2[:, 1] + x,
            s * s2[:, 0] + c * s2[:, 1] + y,
            c * s2[:, 2] - s * s2[:, 3] + x,
            s * s2[:, 2] + c * s2[:, 3] + y,
        ]
    )
    d_max = params.segment_distance_threshold * params.point_distance_tolerance
    mid2 = 0.5 * (bt[:, 0:2] + bt[:, 2:4])
    if len(prep.s1) * len(prep.s2) <= DENSE_PAIRS:
        prep.work.charge(len(prep.s1) * len(prep.s2))
        i, k = _dense_parallel(prep, theta, PAIR_ANGLE_LIMIT)
    else:
        i, k = _tree_pairs(prep, mid2, d_max)
        parallel = np.flatnonzero(
            np.abs(_wrapped(prep.phi1[i] - prep.phi2[k] - theta, prep.period)) <= PAIR_ANGLE_LIMIT
        )
        i, k = i[parallel], k[parallel]
    p = params
    return near_matching_values(
        *(prep.s1, bt, prep.mid1, prep.half1, mid2, prep.half2, i, k, d_max),
        *(p.point_distance_tolerance, p.segment_distance_threshold, p.penalization_base),
    )


SORT_AFTER = 8
"""One transformation's pairs are found by a pass over all of S1 x S2 this many times for the same
two maps; from then on, from the pairs sorted by rotation (sorting costs about that many passes)."""


def _dense_parallel(prep: PreparedPairs, theta: float, limit: float) -> tuple[IntArray, IntArray]:
    """All pairs (i, k) within ``limit`` of parallel under rotation ``theta``, in row order.

    A pass over the n1 x n2 pairs; once the same two maps have been asked SORT_AFTER times (a
    refinement evaluates them a few dozen times), the pairs sorted by the rotation that makes them
    parallel (as :func:`_blocks` sorts them for many candidates): one rotation's pairs are then a
    binary search away. Taken back in row order, the sums that follow add in the same order."""
    dense = prep.cache.get("dense")
    if dense is None:
        i, k = (a.ravel() for a in np.indices((len(prep.s1), len(prep.s2))))
        dense = prep.cache["dense"] = (i, k, _wrapped(prep.phi1[i] - prep.phi2[k], prep.period))
    i, k, rot = cast("tuple[IntArray, IntArray, Array]", dense)
    by_rotation = prep.cache.get("by_rotation")
    if by_rotation is None:
        asked = prep.cache["asked"] = cast(int, prep.cache.get("asked", 0)) + 1
        if asked < SORT_AFTER:
            rows = np.flatnonzero(np.abs(_wrapped(rot - theta, prep.period)) <= limit)
            return i[rows], k[rows]
        by_rotation = prep.cache["by_rotation"] = _by_rotation(rot, prep.period)
    order, ext = cast("tuple[IntArray, Array]", by_rotation)
    centre = math.remainder(theta, prep.period)
    lo = int(np.searchsorted(ext, centre - limit, side="left"))
    hi = int(np.searchsorted(ext, centre + limit, side="right"))
    chosen = np.zeros(len(i), dtype=bool)
    chosen[order[lo:hi]] = True
    rows = np.flatnonzero(chosen)
    return i[rows], k[rows]


PIECE = 1.0
"""S1's segments are indexed as pieces at most this long (m) in its k-d tree."""


def _tree_pairs(prep: PreparedPairs, mid2: Array, d_max: float) -> tuple[IntArray, IntArray]:
    """Pairs (i, k) whose segments may overlap, from a k-d tree of S1's pieces (large maps)."""
    tree = prep.cache.get("tree")
    if tree is None:
        counts = np.maximum(np.ceil(prep.len1 / PIECE).astype(np.int64), 1)
        owner = np.repeat(np.arange(len(prep.s1)), counts)
        frac = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + 0.5) / np.repeat(
            counts, counts
        )
        s = prep.s1[owner]
        points = s[:, 0:2] + (s[:, 2:4] - s[:, 0:2]) * frac[:, None]
        tree = (cKDTree(points), owner)
        prep.cache["tree"] = tree
    kd: cKDTree
    kd, owner = tree  # type: ignore[misc]
    hits = kd.query_ball_point(mid2, prep.half2 + 0.5 * PIECE + d_max)
    near = [len(h) for h in hits]
    prep.work.charge(PAIR_FOUND * (len(mid2) + sum(near)))
    k = np.repeat(np.arange(len(mid2)), near)
    i = owner[np.concatenate(hits).astype(np.int64)] if len(k) else np.zeros(0, np.int64)
    # each pair once, by S1 then S2 index: one integer key per pair sorts far faster than rows
    pairs = np.unique(i * len(mid2) + k)
    return pairs // len(mid2), pairs % len(mid2)


def transformation_value(prep: PreparedPairs, t: Array, params: IntegrationParams, refuse: bool = True) -> float:
    """The transformation value of one transformation (-1 when discarded; ``refuse=False`` skips
    steps 6-8, for maps whose seen free space judges crossings instead)."""
    tt = np.asarray(t, dtype=np.float64).reshape(1, 3)
    if refuse and refused(prep, tt, params)[0]:
        return -1.0
    return float(matched_pairs(prep, tt, params)[2].sum())
