"""The cheap descriptor that ranks which maps to integrate first: a pairwise geometric histogram.

Every pair of a map's walls adds the product of their lengths to a bin of (the angle between
them, folded to [0, 90] degrees; how far the second's midpoint lies from the first's line). Both
are unchanged by rotating and moving the map, so two maps of one place score alike however
their frames lie, and, unlike a histogram of wall directions, the histogram tells a 2 m corridor
from a 6 m hall in a building whose walls all run two ways (Evans, Thacker & Mayhew's pairwise
geometric histograms for line-based shape recognition, 1993, simplified to one distance per pair).

Measured on aces, fr079 and mit-csail cut in 8 against their whole-log maps:
docs/decisions/002-pose-graph.md, "The descriptor".
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core.geometry import Array, lengths

ANGLE_BINS = 4
"""Bins of the angle between two walls over [0, 90] degrees: parallel, near parallel, oblique,
square."""
MOST_WALLS = 400
"""A map's longest walls that make its histogram (the pairs of the rest weigh least, and a whole
building's map file holds thousands)."""


def pairwise_histogram(segments: Array, step: float, reach: float) -> Array:
    """The pairwise geometric histogram of ``(n, 4)`` walls: ``ANGLE_BINS`` x ``ceil(reach / step)``
    bins of distance ``step`` (m), distances beyond ``reach`` in the last; unit norm (zero for
    fewer than two walls). A pair's weight is shared between its two nearest distance bins."""
    dbins = max(math.ceil(reach / step), 1)
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    ln = lengths(seg)
    if len(seg) > MOST_WALLS:
        keep = np.argsort(-ln, kind="stable")[:MOST_WALLS]
        seg, ln = seg[keep], ln[keep]
    size = ANGLE_BINS * dbins
    if len(seg) < 2:
        return np.zeros(size)
    direction = np.arctan2(seg[:, 3] - seg[:, 1], seg[:, 2] - seg[:, 0])
    mid = 0.5 * (seg[:, :2] + seg[:, 2:])
    normal = np.column_stack([-np.sin(direction), np.cos(direction)])
    between = np.mod(direction[None, :] - direction[:, None], math.pi)
    between = np.minimum(between, math.pi - between)
    away = np.abs(np.einsum("ijk,ik->ij", mid[None, :, :] - mid[:, None, :], normal))
    a = np.minimum((between / (math.pi / 2) * ANGLE_BINS).astype(np.int64), ANGLE_BINS - 1) * dbins
    # shared between the two nearest distance bins (bin i's centre at (i + 1/2) step): walls a
    # whole number of steps apart, as a drawn building has, must not fall on either side of a
    # bin's edge by how the map is turned
    u = np.clip(away / step - 0.5, 0.0, dbins - 1.0)
    d = np.minimum(np.floor(u).astype(np.int64), dbins - 2) if dbins > 1 else np.zeros(u.shape, np.int64)
    share = u - d
    weight = ln[:, None] * ln[None, :]
    np.fill_diagonal(weight, 0.0)
    h: Array = np.bincount((a + d).ravel(), weights=(weight * (1.0 - share)).ravel(), minlength=size)
    if dbins > 1:
        h += np.bincount((a + d + 1).ravel(), weights=(weight * share).ravel(), minlength=size)
    norm = float(np.linalg.norm(h))
    return h / norm if norm > 0 else h


def similarity(h1: Array, h2: Array) -> float:
    """How alike two maps' histograms are: their cosine, 1 for the same."""
    return float(np.dot(h1, h2))
