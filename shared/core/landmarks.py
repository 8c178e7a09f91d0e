"""Point landmarks of a segment map and their descriptors (Ballesta et al. 2009, Section 3.1, step 1).

Ballesta et al. align landmark maps: points with a descriptor each, matched by descriptor
similarity. A segment map's points that any viewpoint places alike are where walls end:

- **corners**: two walls that are not parallel (at least
  ``MIN_VERTEX_ANGLE`` apart) with an end of
  each within ``segment_distance_threshold * point_distance_tolerance`` of the other's (the paper's
  "touching" reach); the landmark is where their lines cross, which is where the extraction put the
  corner (:mod:`fleetmap.shared.core.extraction`);
- **ends**: the other segment ends (a door jamb, or a wall going out of sight).

Each landmark carries a *heading*, so that its descriptor does not turn with the map: a corner's
bisector, pointing between its two walls; an end's wall direction, pointing along the wall away
from the end. The descriptor is the local arrangement of walls around it: the wall length, sampled
along every segment, in each cell of a polar grid of a given radius in the landmark's frame
(a shape context, Belongie et al. 2002, as FLIRT's beta-grid describes laser interest points,
Tipaldi & Arras 2010), normalised and square-rooted so that the Euclidean distance between two
descriptors is the Hellinger distance of the two arrangements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.core.candidates import IntArray
from fleetmap.shared.core.geometry import Array, lengths, segment_points
from scipy.spatial import cKDTree

CORNER, END = 0, 1
"""Landmark kinds: a corner is matched only to a corner, an end only to an end."""

RADIAL_EDGES = (0.0, 0.25, 0.5, 1.0, 2.0)
"""Radial cell edges of the descriptor, as shares of the descriptor radius (log-polar, as a shape
context: near walls are told apart finely, far ones coarsely)."""

SECTORS = 12
"""Angular cells of the descriptor (30 degrees each)."""

SAMPLE_SPACING = 0.05
"""Metres between the wall points the descriptor counts."""


@dataclass(frozen=True)
class Landmarks:
    """A map's landmarks: ``points`` ``(n, 2)``, ``headings`` ``(n,)`` (rad), ``kinds`` ``(n,)``
    (:data:`CORNER` or :data:`END`) and ``descriptors`` ``(n, d)``."""

    points: Array
    headings: Array
    kinds: IntArray
    descriptors: Array

    def __len__(self) -> int:
        return int(self.points.shape[0])


def find_landmarks(segments: Array, reach: float, min_angle: float, radius: float) -> Landmarks:
    """The corners and ends of ``segments`` ``(n, 4)`` with their descriptors (module docstring)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    seg = seg[lengths(seg) > 1e-9]
    ends = seg.reshape(-1, 2)  # row 2s + e: end e (0 start, 1 end) of segment s
    if len(ends) == 0:
        return Landmarks(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros((0, _size())))
    # Direction along each segment away from each of its ends.
    d = seg[:, 2:4] - seg[:, 0:2]
    u = d / lengths(seg)[:, None]
    away = np.stack([u, -u], axis=1).reshape(-1, 2)
    pairs = cKDTree(ends).query_pairs(reach, output_type="ndarray")
    pairs = pairs[pairs[:, 0] // 2 != pairs[:, 1] // 2]
    a, b = pairs[:, 0], pairs[:, 1]
    cos = np.einsum("ij,ij->i", away[a], away[b])
    corner = np.abs(cos) <= math.cos(min_angle)
    a, b = a[corner], b[corner]
    cross = _line_crossings(ends[a], away[a], ends[b], away[b])
    near = (np.hypot(*(cross - ends[a]).T) <= reach) & (np.hypot(*(cross - ends[b]).T) <= reach)
    a, b, cross = a[near], b[near], cross[near]
    bisector = away[a] + away[b]
    corners = cross
    corner_headings = np.arctan2(bisector[:, 1], bisector[:, 0])
    used = np.zeros(len(ends), dtype=bool)
    used[a] = used[b] = True
    free = np.flatnonzero(~used)
    points = np.vstack([corners, ends[free]])
    headings = np.concatenate([corner_headings, np.arctan2(away[free, 1], away[free, 0])])
    kinds = np.concatenate([np.full(len(corners), CORNER), np.full(len(free), END)]).astype(np.int64)
    return Landmarks(points, headings, kinds, describe(seg, points, headings, radius))


def _line_crossings(p: Array, u: Array, q: Array, v: Array) -> Array:
    """Where the line through ``p`` along ``u`` crosses the line through ``q`` along ``v`` (rows)."""
    det = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    w = q - p
    t = (w[:, 0] * v[:, 1] - w[:, 1] * v[:, 0]) / det
    return p + t[:, None] * u


def _size() -> int:
    return (len(RADIAL_EDGES) - 1) * SECTORS


def describe(segments: Array, points: Array, headings: Array, radius: float) -> Array:
    """The descriptor of each landmark ``(points[i], headings[i])``: wall length per polar cell of
    ``radius`` in the landmark's frame, normalised, square-rooted (module docstring)."""
    out = np.zeros((len(points), _size()))
    if len(points) == 0 or len(segments) == 0:
        return out
    wall, owner = segment_points(segments, SAMPLE_SPACING)
    weight = (lengths(segments) / np.bincount(owner, minlength=len(segments)))[owner]
    near = cKDTree(wall).query_ball_point(points, radius)
    counts = np.array([len(n) for n in near])
    which = np.repeat(np.arange(len(points)), counts)
    hits = np.fromiter((j for n in near for j in n), dtype=np.int64, count=int(counts.sum()))
    rel = wall[hits] - points[which]
    r = np.hypot(rel[:, 0], rel[:, 1])
    bearing = np.mod(np.arctan2(rel[:, 1], rel[:, 0]) - headings[which], 2 * math.pi)
    ring = np.searchsorted(np.asarray(RADIAL_EDGES[1:-1]) * radius, r, side="right")
    sector = np.minimum((bearing / (2 * math.pi) * SECTORS).astype(np.int64), SECTORS - 1)
    np.add.at(out, (which, ring * SECTORS + sector), weight[hits])
    total = out.sum(axis=1, keepdims=True)
    return np.sqrt(out / np.where(total > 0, total, 1.0))
