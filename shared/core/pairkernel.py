"""The matching value of a transformation's candidate pairs, compiled (Algorithm 4, steps 9-17).

Every transformation the paper's integration values, and every step of its least-squares
refinement, takes the pairs of segments near parallel under the transformation, keeps those whose
midpoints are near enough to overlap, and gives each its matching value
(:func:`fleetmap.shared.core.geometry.matching_value`). In numpy that is three dozen passes over
the pairs for each transformation; on mit-csail cut in 8 it was 10 of the 46 s its 467
integrations took (`matched_pairs` less the pairs' selection). One compiled loop (Numba) does the
same arithmetic, pair by pair, in the same order: the same values to the bit.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
call (:mod:`fleetmap.shared.core.compiled`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array


def _build() -> Callable[..., int]:
    # one function, calling no other built here (:mod:`fleetmap.shared.core.compiled`)
    import numba

    @numba.njit(cache=True, nogil=True)
    def values(s1, bt, mid1, half1, mid2, half2, i, k, d_max, tolerance, threshold, base, out_i, out_k, out_mv):
        n = 0
        for r in range(len(i)):
            p, q = i[r], k[r]
            dx = mid1[p, 0] - mid2[q, 0]
            dy = mid1[p, 1] - mid2[q, 1]
            reach = half1[p] + half2[q] + d_max
            if not dx * dx + dy * dy <= reach * reach:
                continue
            a0, a1, a2, a3 = s1[p, 0], s1[p, 1], s1[p, 2], s1[p, 3]
            b0, b1, b2, b3 = bt[q, 0], bt[q, 1], bt[q, 2], bt[q, 3]
            dxa, dya = a2 - a0, a3 - a1
            dxb, dyb = b2 - b0, b3 - b1
            la, lb = np.hypot(dxa, dya), np.hypot(dxb, dyb)
            b1x, b1y, b2x, b2y = b0 - a0, b1 - a1, b2 - a0, b3 - a1
            a1x, a1y, a2x, a2y = a0 - b0, a1 - b1, a2 - b0, a3 - b1
            c1, c2 = dxa * b1y - dya * b1x, dxa * b2y - dya * b2x
            c3, c4 = dxb * a1y - dyb * a1x, dxb * a2y - dyb * a2x
            d = min(max(abs(c1) / la, abs(c2) / la), max(abs(c3) / lb, abs(c4) / lb))
            ratio = d / tolerance
            # the common part of each segment with the other's projection on its line
            ux, uy = dxa / la, dya / la
            t1, t2 = b1x * ux + b1y * uy, b2x * ux + b2y * uy
            common_a = max(min(max(t1, t2), la) - max(min(t1, t2), 0.0), 0.0)
            ux, uy = dxb / lb, dyb / lb
            t1, t2 = a1x * ux + a1y * uy, a2x * ux + a2y * uy
            common_b = max(min(max(t1, t2), lb) - max(min(t1, t2), 0.0), 0.0)
            mv = 0.5 * (common_a + common_b)
            o1, o2, o3, o4 = np.sign(c1), np.sign(c2), np.sign(c3), np.sign(c4)
            if o1 == 0 and o2 == 0:
                # collinear: only their extents say whether they meet (geometry.segments_intersect)
                meet = min(max(a0, a2), max(b0, b2)) >= max(min(a0, a2), min(b0, b2)) and min(
                    max(a1, a3), max(b1, b3)
                ) >= max(min(a1, a3), min(b1, b3))
            else:
                meet = o1 * o2 <= 0 and o3 * o4 <= 0
            penalty = 1.0 if meet else base**ratio
            value = 0.0 if ratio > threshold else mv * penalty
            if value > 0:
                out_i[n], out_k[n], out_mv[n] = p, q, value
                n += 1
        return n

    return values


_values = Compiled(_build)


def near_matching_values(
    s1: Array,
    bt: Array,
    mid1: Array,
    half1: Array,
    mid2: Array,
    half2: Array,
    i: Array,
    k: Array,
    d_max: float,
    tolerance: float,
    threshold: float,
    base: float,
) -> tuple[Array, Array, Array]:
    """Of the pairs ``(i[r], k[r])`` (S1's segment, S2's moved, ``bt``), those whose midpoints lie
    within their half lengths and ``d_max`` of each other with a positive matching value
    (POINTDISTANCETOLERANCE ``tolerance``, SEGMENTDISTANCETHRESHOLD ``threshold``, the penalisation
    ``base``): their ``i``, ``k`` and value, in the pairs' order."""
    out_i = np.empty(len(i), np.int64)
    out_k = np.empty(len(i), np.int64)
    out_mv = np.empty(len(i), np.float64)
    if len(i) == 0:
        return out_i, out_k, out_mv
    n = _values(
        np.ascontiguousarray(s1, dtype=np.float64),
        np.ascontiguousarray(bt, dtype=np.float64),
        np.ascontiguousarray(mid1, dtype=np.float64),
        np.ascontiguousarray(half1, dtype=np.float64),
        np.ascontiguousarray(mid2, dtype=np.float64),
        np.ascontiguousarray(half2, dtype=np.float64),
        np.ascontiguousarray(i, dtype=np.int64),
        np.ascontiguousarray(k, dtype=np.int64),
        float(d_max),
        float(tolerance),
        float(threshold),
        float(base),
        out_i,
        out_k,
        out_mv,
    )
    return out_i[:n], out_k[:n], out_mv[:n]
