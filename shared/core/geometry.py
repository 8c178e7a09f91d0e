"""Plane geometry of segments and rigid transforms, vectorised over numpy arrays.

A set of segments is one ``(n, 4)`` float64 array of rows ``[x1, y1, x2, y2]``. Functions that
compare two segment sets broadcast: pass ``(n, 1, 4)`` and ``(1, m, 4)`` to get ``(n, m)``
results, or ``(t, n, 4)`` batches for t candidate transformations.

Segments are *oriented*: a segment extracted from a scan runs counter-clockwise around the
sensor, so the free space it was seen from lies on its left. Rigid transforms keep that, and the
integration engine uses it (a wall is not matched with the back of another).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[Any]
"""Arrays of the core: float64 for coordinates, int64 for indices, bool for masks."""

TWO_PI = 2.0 * math.pi
"""A full turn (rad)."""


def wrap_angle(a: Array | float) -> Array:
    """Angles wrapped to [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=np.float64) + math.pi, TWO_PI) - math.pi


def wrap_scalar(a: float) -> float:
    """One angle wrapped to [-pi, pi), bit for bit as :func:`wrap_angle` (Python's float ``%`` is
    numpy's ``mod``: fmod, then the divisor's sign) and twenty times faster: the pose graph composes
    transforms millions of times a solve."""
    return float((a + math.pi) % TWO_PI - math.pi)


@dataclass(frozen=True)
class Transform2D:
    """A rigid transform of the plane: ``p_A = R(theta) p_B + (x, y)``.

    As in the contracts, it maps coordinates of map B into the frame of map A; equivalently it is
    the pose of B's frame in A's frame.
    """

    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0

    @staticmethod
    def identity() -> Transform2D:
        return Transform2D(0.0, 0.0, 0.0)

    @staticmethod
    def from_array(v: Array | tuple[float, float, float]) -> Transform2D:
        return Transform2D(float(v[0]), float(v[1]), wrap_scalar(float(v[2])))

    def as_array(self) -> Array:
        return np.array([self.x, self.y, self.theta], dtype=np.float64)

    def as_matrix(self) -> Array:
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    def compose(self, other: Transform2D) -> Transform2D:
        """``self * other``: first ``other`` (C into B), then ``self`` (B into A): C into A."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Transform2D(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            wrap_scalar(self.theta + other.theta),
        )

    def inverse(self) -> Transform2D:
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Transform2D(-(c * self.x + s * self.y), s * self.x - c * self.y, wrap_scalar(-self.theta))

    def apply_points(self, points: Array) -> Array:
        return transform_points(points, self.x, self.y, self.theta)

    def apply(self, segments: Array) -> Array:
        return transform_segments(segments, self.x, self.y, self.theta)

    def to_dict(self) -> dict[str, float]:
        return {"x": self.x, "y": self.y, "theta": self.theta}

    def distance(self, other: Transform2D) -> tuple[float, float]:
        """Translation (m) and absolute rotation (rad) between two transforms."""
        return (
            math.hypot(self.x - other.x, self.y - other.y),
            abs(float(wrap_angle(self.theta - other.theta))),
        )


def transform_points(points: Array, x: float, y: float, theta: float) -> Array:
    c, s = math.cos(theta), math.sin(theta)
    p = np.asarray(points, dtype=np.float64)
    out = np.empty_like(p)
    out[..., 0] = c * p[..., 0] - s * p[..., 1] + x
    out[..., 1] = s * p[..., 0] + c * p[..., 1] + y
    return out


def transform_segments(segments: Array, x: float, y: float, theta: float) -> Array:
    """Segments ``(n, 4)`` moved by one transform."""
    seg = np.asarray(segments, dtype=np.float64)
    return transform_points(seg.reshape(-1, 2), x, y, theta).reshape(seg.shape)


def transform_segments_batch(segments: Array, transforms: Array) -> Array:
    """Segments ``(n, 4)`` moved by each of ``(t, 3)`` transforms: ``(t, n, 4)``."""
    seg = np.asarray(segments, dtype=np.float64)
    tr = np.asarray(transforms, dtype=np.float64)
    c = np.cos(tr[:, 2])[:, None]
    s = np.sin(tr[:, 2])[:, None]
    tx = tr[:, 0][:, None]
    ty = tr[:, 1][:, None]
    out = np.empty((tr.shape[0], seg.shape[0], 4))
    for k in (0, 2):
        px = seg[None, :, k]
        py = seg[None, :, k + 1]
        out[:, :, k] = c * px - s * py + tx
        out[:, :, k + 1] = s * px + c * py + ty
    return out


def pose_information_in_own_frame(information: Array, theta: float) -> Array:
    """A pose's information matrix on (x, y, theta) with x, y in the frame it is given in, turned
    into the pose's own frame (the pose heads ``theta`` in the frame it is given in): what a
    between factor of a pose graph takes, whose error is in the frame of its second pose
    (gtsam's ``BetweenFactor``: ``Local(measured, between(a, b))``)."""
    c, s = math.cos(theta), math.sin(theta)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r.T @ np.asarray(information, dtype=np.float64).reshape(3, 3) @ r


def lengths(segments: Array) -> Array:
    seg = np.asarray(segments, dtype=np.float64)
    return np.hypot(seg[..., 2] - seg[..., 0], seg[..., 3] - seg[..., 1])


def orientations(segments: Array) -> Array:
    """Direction of each segment, from its first to its second extreme, in [-pi, pi)."""
    seg = np.asarray(segments, dtype=np.float64)
    return np.arctan2(seg[..., 3] - seg[..., 1], seg[..., 2] - seg[..., 0])


def point_line_distance(segments: Array, points: Array) -> Array:
    """Distance from points ``(..., 2)`` to the lines supporting segments ``(..., 4)``."""
    seg = np.asarray(segments, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    dx = seg[..., 2] - seg[..., 0]
    dy = seg[..., 3] - seg[..., 1]
    length = np.hypot(dx, dy)
    cross = dx * (p[..., 1] - seg[..., 1]) - dy * (p[..., 0] - seg[..., 0])
    return np.abs(cross) / length


def segment_distance(s1: Array, s2: Array) -> Array:
    """d(s1, s2) of paper III-B (after Grimson 1990, Fig. 2).

    ``min(max(dist(s1, start(s2)), dist(s1, end(s2))), max(dist(s2, start(s1)), dist(s2, end(s1))))``
    where dist(s, p) is the distance from p to the line supporting s.
    """
    a = np.asarray(s1, dtype=np.float64)
    b = np.asarray(s2, dtype=np.float64)
    d_b_on_a = np.maximum(point_line_distance(a, b[..., 0:2]), point_line_distance(a, b[..., 2:4]))
    d_a_on_b = np.maximum(point_line_distance(b, a[..., 0:2]), point_line_distance(b, a[..., 2:4]))
    return np.minimum(d_b_on_a, d_a_on_b)


def segments_intersect(s1: Array, s2: Array) -> Array:
    """Whether the two closed segments have a point in common (broadcasting)."""
    a = np.asarray(s1, dtype=np.float64)
    b = np.asarray(s2, dtype=np.float64)

    def orient(px: Array, py: Array, qx: Array, qy: Array, rx: Array, ry: Array) -> Array:
        return np.sign((qx - px) * (ry - py) - (qy - py) * (rx - px))

    o1 = orient(a[..., 0], a[..., 1], a[..., 2], a[..., 3], b[..., 0], b[..., 1])
    o2 = orient(a[..., 0], a[..., 1], a[..., 2], a[..., 3], b[..., 2], b[..., 3])
    o3 = orient(b[..., 0], b[..., 1], b[..., 2], b[..., 3], a[..., 0], a[..., 1])
    o4 = orient(b[..., 0], b[..., 1], b[..., 2], b[..., 3], a[..., 2], a[..., 3])
    proper = (o1 * o2 <= 0) & (o3 * o4 <= 0)
    # Collinear pairs pass the sign test without touching: check that their extents overlap.
    collinear = (o1 == 0) & (o2 == 0)
    overlap_x = np.minimum(np.maximum(a[..., 0], a[..., 2]), np.maximum(b[..., 0], b[..., 2])) >= np.maximum(
        np.minimum(a[..., 0], a[..., 2]), np.minimum(b[..., 0], b[..., 2])
    )
    overlap_y = np.minimum(np.maximum(a[..., 1], a[..., 3]), np.maximum(b[..., 1], b[..., 3])) >= np.maximum(
        np.minimum(a[..., 1], a[..., 3]), np.minimum(b[..., 1], b[..., 3])
    )
    return np.where(collinear, overlap_x & overlap_y, proper)


def matching_value(
    s1: Array,
    s2: Array,
    point_distance_tolerance: float,
    segment_distance_threshold: float,
    penalization_base: float,
) -> Array:
    """Matching value of segment pairs, Algorithm 4 steps 9-17 (broadcasting).

    The average of the common parts of each segment with the other's projection on its line,
    penalised by ``base ** (d / tolerance)`` when the segments do not intersect, and zero when
    ``d / tolerance`` exceeds SEGMENTDISTANCETHRESHOLD.
    """
    a = np.asarray(s1, dtype=np.float64)
    b = np.asarray(s2, dtype=np.float64)
    # segment_distance, the common parts and segments_intersect, each quantity computed once: the
    # same arithmetic in the same order (so the same values), a third of the numpy calls (this
    # runs on every candidate's pairs and every refinement step).
    ax, ay, bx, by = a[..., 0], a[..., 1], b[..., 0], b[..., 1]
    dxa, dya = a[..., 2] - ax, a[..., 3] - ay
    dxb, dyb = b[..., 2] - bx, b[..., 3] - by
    la, lb = np.hypot(dxa, dya), np.hypot(dxb, dyb)
    # Cross products of each segment's direction with the other's ends, from its own start.
    b1x, b1y, b2x, b2y = bx - ax, by - ay, b[..., 2] - ax, b[..., 3] - ay
    a1x, a1y, a2x, a2y = ax - bx, ay - by, a[..., 2] - bx, a[..., 3] - by
    c1, c2 = dxa * b1y - dya * b1x, dxa * b2y - dya * b2x
    c3, c4 = dxb * a1y - dyb * a1x, dxb * a2y - dyb * a2x
    d = np.minimum(np.maximum(np.abs(c1) / la, np.abs(c2) / la), np.maximum(np.abs(c3) / lb, np.abs(c4) / lb))
    ratio = d / point_distance_tolerance
    mv = 0.5 * (
        _projection_overlap(dxa / la, dya / la, la, b1x, b1y, b2x, b2y)
        + _projection_overlap(dxb / lb, dyb / lb, lb, a1x, a1y, a2x, a2y)
    )
    o1, o2, o3, o4 = np.sign(c1), np.sign(c2), np.sign(c3), np.sign(c4)
    meet = (o1 * o2 <= 0) & (o3 * o4 <= 0)
    collinear = (o1 == 0) & (o2 == 0)
    if collinear.any():
        meet = np.where(collinear, segments_intersect(a, b), meet)
    penalty = np.where(meet, 1.0, np.power(penalization_base, ratio))
    return np.where(ratio > segment_distance_threshold, 0.0, mv * penalty)


def _projection_overlap(ux: Array, uy: Array, length: Array, p1x: Array, p1y: Array, p2x: Array, p2y: Array) -> Array:
    """Length of the common part of a segment and the other's projection on its line, from the
    segment's unit direction and length and the other's ends relative to its start."""
    t1 = p1x * ux + p1y * uy
    t2 = p2x * ux + p2y * uy
    lo = np.maximum(np.minimum(t1, t2), 0.0)
    hi = np.minimum(np.maximum(t1, t2), length)
    return np.maximum(hi - lo, 0.0)


def segment_points(segments: Array, spacing: float) -> tuple[Array, Array]:
    """Points sampled along segments every ``spacing`` metres (ends included) and their segment index."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    n = np.maximum(np.ceil(lengths(seg) / spacing).astype(np.int64), 1) + 1
    idx = np.repeat(np.arange(len(seg)), n)
    starts = np.cumsum(n) - n
    frac = (np.arange(n.sum()) - np.repeat(starts, n)) / np.repeat(n - 1, n)
    s = seg[idx]
    pts = s[:, 0:2] + (s[:, 2:4] - s[:, 0:2]) * frac[:, None]
    return pts, idx


def point_segment_distance(points: Array, segments: Array) -> Array:
    """Euclidean distance from points ``(..., 2)`` to segments ``(..., 4)`` (broadcasting)."""
    p = np.asarray(points, dtype=np.float64)
    s = np.asarray(segments, dtype=np.float64)
    dx = s[..., 2] - s[..., 0]
    dy = s[..., 3] - s[..., 1]
    l2 = dx * dx + dy * dy
    t = ((p[..., 0] - s[..., 0]) * dx + (p[..., 1] - s[..., 1]) * dy) / np.where(l2 > 0, l2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    return np.hypot(p[..., 0] - (s[..., 0] + t * dx), p[..., 1] - (s[..., 1] + t * dy))
