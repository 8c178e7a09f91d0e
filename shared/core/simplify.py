"""Map simplification: one segment per stretch of wall (fleetmap, beyond the paper).

A partial map built from real scans keeps many short, overlapping segments for one wall: fusion
(Algorithm 5) replaces the segments of a matching chain by a polyline, but real scans are cut
into pieces of about 10 cm (clutter, range quantisation), and a chain only forms between pieces
that already agree. The paper notes the problem for the tree method ("spurious" segments, IV-B,
Fig. 7). Left alone, a local map of a hundred scans holds a thousand segments and several copies
of each wall: integrating two such maps is slow, and their total length, which validity is
measured against, counts every wall several times.

:func:`simplify` groups segments that lie on one line (every extreme within ``tolerance`` of the
group's fitted line, directions within ``angle_tolerance``, the same side facing the sensor for
oriented maps) and whose extents along it overlap or leave gaps under ``gap``; each group becomes
the stretches of its fitted line that its members cover. Seeds are taken longest first, so the
long walls set the lines. A segment that joins no group is kept as it is.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core.geometry import Array, lengths
from fleetmap.shared.core.segmap import SegmentMap

SIMPLIFY_TOLERANCE = 0.05
"""Partial maps: segments within this (m) of one line become one segment per covered stretch (0:
never simplify): a submap's copies of one wall, each scan's a little apart, become one."""
REFIT_ROUNDS = 4
"""Rounds of growing a group and refitting its line."""


def _fit(seg: Array, w: Array) -> tuple[Array, Array]:
    """Length-weighted total least squares line through segments: a point and a unit direction."""
    pts = np.vstack([seg[:, 0:2], seg[:, 2:4]])
    ww = np.concatenate([w, w])
    c = (pts * ww[:, None]).sum(axis=0) / ww.sum()
    d = pts - c
    cov = (d * ww[:, None]).T @ d
    # Second moment of each segment about its own midpoint counts too (a long segment is a line).
    u = seg[:, 2:4] - seg[:, 0:2]
    cov += (u * (w / 12.0)[:, None]).T @ u
    _, evecs = np.linalg.eigh(cov)
    return c, evecs[:, 1]


def simplify(
    m: SegmentMap,
    tolerance: float = 0.05,
    angle_tolerance: float = 0.1,
    gap: float = 0.3,
    short_length: float = 0.5,
    min_short_cos: float = 0.3,
) -> SegmentMap:
    """``m`` with the segments of each stretch of wall replaced by one segment per covered stretch."""
    seg = np.asarray(m.segments, dtype=np.float64)
    n = len(seg)
    if n < 2:
        return SegmentMap(seg.copy(), ordered=False, oriented=m.oriented, extras=dict(m.extras))
    ln = lengths(seg)
    direction = (seg[:, 2:4] - seg[:, 0:2]) / np.maximum(ln, 1e-12)[:, None]
    free = np.ones(n, dtype=bool)
    out: list[Array] = []
    cos_tol = math.cos(angle_tolerance)
    for s in np.argsort(-ln, kind="stable"):
        if not free[s]:
            continue
        group = np.array([s])
        c, u = seg[s, 0:2], direction[s]
        for _ in range(REFIT_ROUNDS):
            nrm = np.array([-u[1], u[0]])
            cand = np.flatnonzero(free)
            a = seg[cand, 0:2] - c
            b = seg[cand, 2:4] - c
            dot = direction[cand] @ u
            # Long segments must be near parallel; a short one only has to lie within tolerance
            # (its direction is noise) and, on an oriented map, face the same way.
            short = ln[cand] < short_length
            aligned = (dot if m.oriented else np.abs(dot)) >= np.where(short, min_short_cos, cos_tol)
            near = aligned & (np.abs(a @ nrm) <= tolerance) & (np.abs(b @ nrm) <= tolerance)
            cand = cand[near | (cand == s)]
            # Along the line: keep the candidates whose extents chain to the seed's within ``gap``.
            ta, tb = (seg[cand, 0:2] - c) @ u, (seg[cand, 2:4] - c) @ u
            lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
            order = np.argsort(lo, kind="stable")
            keep = _chained(lo[order], hi[order], int(np.flatnonzero(cand[order] == s)[0]), gap)
            new_group = np.sort(cand[order][keep])
            if len(new_group) == len(group) and np.array_equal(new_group, group):
                break
            group = new_group
            c, u_fit = _fit(seg[group], ln[group])
            u = u_fit if u_fit @ direction[s] >= 0 else -u_fit
        free[group] = False
        if len(group) == 1:
            out.append(seg[group])
            continue
        ta, tb = (seg[group, 0:2] - c) @ u, (seg[group, 2:4] - c) @ u
        lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
        for start, end in _union(lo, hi, gap):
            if end - start > 1e-6:
                out.append(np.array([[*(c + start * u), *(c + end * u)]]))
    return SegmentMap(np.vstack(out), ordered=False, oriented=m.oriented, extras=dict(m.extras))


def _chained(lo: Array, hi: Array, seed: int, gap: float) -> Array:
    """Mask of the intervals (sorted by ``lo``) connected to interval ``seed`` by gaps under ``gap``."""
    reach = np.maximum.accumulate(hi)
    # Runs of intervals each starting within ``gap`` of everything before it.
    breaks = np.concatenate([[False], lo[1:] > reach[:-1] + gap])
    run = np.cumsum(breaks)
    return run == run[seed]


def _union(lo: Array, hi: Array, gap: float) -> list[tuple[float, float]]:
    """The union of intervals, with gaps under ``gap`` bridged."""
    order = np.argsort(lo, kind="stable")
    spans: list[tuple[float, float]] = []
    for a, b in zip(lo[order], hi[order], strict=True):
        if spans and a <= spans[-1][1] + gap:
            spans[-1] = (spans[-1][0], max(spans[-1][1], float(b)))
        else:
            spans.append((float(a), float(b)))
    return spans
