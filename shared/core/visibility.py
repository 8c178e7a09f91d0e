"""Free-space consistency of a transformation (fleetmap, beyond the paper).

A scan (an ``ordered`` map) was taken from its frame's origin: between the sensor and each of its
segments lies space the laser saw to be free. Under a wrong transformation the other map's walls
land in that free space; under the right one they land on or behind the walls. This is the
paper's SEGMENTLENGTHREFUSE rule (a transformation that makes two long walls cross is discarded)
made precise: rather than asking whether two long segments cross, it measures how much wall
length of each map lies in the other's seen free space.

The seen free space is a *range profile*: for fine bearing bins around the sensor, the distance
to the nearest segment, and zero where no segment was seen (a gap is no evidence of free space:
the beams there may have returned nothing). It is narrowed to the smallest range over a few
neighbouring bins, so that a point next to the edge of an object, or on a wall seen at a grazing
angle, is not counted as seen through it.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core.candidates import ragged_ranges
from fleetmap.shared.core.geometry import Array, segment_points

BINS = 1440
"""Bearing bins of a range profile (0.25 degree)."""
WIDEN = 3
"""A bin's free range is the smallest over this many bins on either side."""
SAMPLE_SPACING = 0.05
"""Spacing of the points sampled along the other map's segments (m)."""


def range_profile(segments: Array, bins: int = BINS, widen: int = WIDEN) -> Array:
    """Free range from the origin in each bearing bin ``(bins,)``: the nearest segment, narrowed."""
    profile = np.full(bins, np.inf)
    if len(segments) == 0:
        return np.zeros(bins)
    width = 2 * math.pi / bins
    a0 = np.arctan2(segments[:, 1], segments[:, 0])
    a1 = np.arctan2(segments[:, 3], segments[:, 2])
    span = np.mod(a1 - a0 + math.pi, 2 * math.pi) - math.pi  # signed angular extent, < pi
    lo_a = np.where(span >= 0, a0, a0 + span)
    first = np.ceil((lo_a + math.pi) / width - 0.5).astype(np.int64)
    last = np.floor((lo_a + np.abs(span) + math.pi) / width - 0.5).astype(np.int64)
    owner, pos = ragged_ranges(first, last + 1)
    if len(owner) == 0:
        return np.zeros(bins)
    bearing = (pos + 0.5) * width - math.pi
    s = segments[owner]
    dx, dy = np.cos(bearing), np.sin(bearing)
    ex, ey = s[:, 2] - s[:, 0], s[:, 3] - s[:, 1]
    den = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (s[:, 0] * ey - s[:, 1] * ex) / den
    r = np.where(np.isfinite(r) & (r > 0), r, np.inf)
    np.minimum.at(profile, np.mod(pos, bins), r)
    profile[~np.isfinite(profile)] = 0.0
    if widen > 0:
        profile = np.min([np.roll(profile, k) for k in range(-widen, widen + 1)], axis=0)
    return profile


def _violations(profile: Array, points: Array, weights: Array, t: Array, margin: float) -> Array:
    """Length of ``points`` (moved by each transform in ``t``) inside the profile's free space."""
    bins = len(profile)
    c = np.cos(t[:, 2])[:, None]
    s = np.sin(t[:, 2])[:, None]
    qx = c * points[None, :, 0] - s * points[None, :, 1] + t[:, 0, None]
    qy = s * points[None, :, 0] + c * points[None, :, 1] + t[:, 1, None]
    r = np.hypot(qx, qy)
    b = np.floor((np.arctan2(qy, qx) + math.pi) / (2 * math.pi) * bins).astype(np.int64) % bins
    inside = r < profile[b] - margin
    return (inside * weights[None, :]).sum(axis=1)


def _inverse(t: Array) -> Array:
    c, s = np.cos(t[:, 2]), np.sin(t[:, 2])
    return np.column_stack([-(c * t[:, 0] + s * t[:, 1]), s * t[:, 0] - c * t[:, 1], -t[:, 2]])


class FreeSpace:
    """The free-space check between two maps, prepared once for many transformations.

    ``viewpoint1``/``viewpoint2`` say whether each map is a scan seen from its origin; a map that
    is not (a partial map) gives no free space, and nothing is counted against it.
    """

    def __init__(self, s1: Array, s2: Array, viewpoint1: bool, viewpoint2: bool, margin: float) -> None:
        self.margin = margin
        self.profile1 = range_profile(s1) if viewpoint1 else None
        self.profile2 = range_profile(s2) if viewpoint2 else None
        self.points1, w1 = self._samples(s1)
        self.points2, w2 = self._samples(s2)
        self.weights1, self.weights2 = w1, w2

    @staticmethod
    def _samples(segments: Array) -> tuple[Array, Array]:
        if len(segments) == 0:
            return np.zeros((0, 2)), np.zeros(0)
        pts, idx = segment_points(segments, SAMPLE_SPACING)
        counts = np.bincount(idx, minlength=len(segments))
        length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
        return pts, (length / counts)[idx]

    @property
    def active(self) -> bool:
        return self.profile1 is not None or self.profile2 is not None

    def violation(self, t: Array) -> Array:
        """Wall length (m) of each map in the other's seen free space, for each transformation."""
        tt = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(tt))
        if self.profile1 is not None:
            out += _violations(self.profile1, self.points2, self.weights2, tt, self.margin)
        if self.profile2 is not None:
            out += _violations(self.profile2, self.points1, self.weights1, _inverse(tt), self.margin)
        return out
