"""Uncertainty-weighted fusion of walls seen by several maps (Ballesta et al. 2009, Section 4).

Ballesta et al. merge a landmark that two robots' maps hold with a stationary multivariable
Kalman filter, each robot's estimate weighed by its covariance (eqs. 6-8):

    K = P1 (P1 + P2)^-1,    x = x1 + K (x2 - x1),    P = (I - K) P1

(the paper prints ``x1 - x2`` in eq. 7: with that sign the estimate would move away from x2;
the filter it names moves towards it). The paper's Algorithm 5 fuses walls unweighted: every copy
counts by its length alone. Here a wall is a line estimate: its normal direction ``alpha`` and its
signed offset ``d`` from a reference point ``c`` near it (offsets from a far origin would couple
the two through the lever arm), with a 2 x 2 covariance from

- the **segment fit**: ``n`` points every ``spacing`` metres along a segment of length ``L``, each
  ``point_sigma`` off the wall, fix the offset to ``point_sigma^2 / n`` and the direction to
  ``12 point_sigma^2 / (n L^2)`` (least squares of a line through evenly spaced points);
- the **map's pose**: ``(x, y, theta)`` with covariance ``P``, propagated through the Jacobian of
  ``(alpha, d)`` with respect to it: a turn moves the wall's offset by its lever arm from the pose.

:func:`fuse` is eqs. 6-8 for two estimates; :func:`fuse_all` folds them in one after the other;
:func:`offset_information` gives each placed segment the weight a line fit of many copies needs
(:class:`~fleetmap.shared.core.walls.WallMap` ``add(..., weights=...)``) to be this filter's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D, lengths


@dataclass(frozen=True)
class LineEstimate:
    """A wall's line: normal direction ``alpha`` (rad) and offset ``d`` (m) from ``centre`` along
    that normal, with the ``(2, 2)`` covariance of ``(alpha, d)``."""

    alpha: float
    d: float
    covariance: Array
    centre: tuple[float, float]

    def at(self, centre: tuple[float, float]) -> LineEstimate:
        """The same line with its offset measured from another reference point."""
        n = np.array([math.cos(self.alpha), math.sin(self.alpha)])
        shift = np.subtract(centre, self.centre)
        # d' = d - shift . n(alpha); dd'/dalpha = 1 * dd/dalpha - shift . n'(alpha)
        jac = np.array([[1.0, 0.0], [-float(shift @ np.array([-n[1], n[0]])), 1.0]])
        return LineEstimate(self.alpha, self.d - float(shift @ n), jac @ self.covariance @ jac.T, centre)

    def distance(self, point: Array) -> float:
        """Signed distance of a point from the line."""
        n = np.array([math.cos(self.alpha), math.sin(self.alpha)])
        return float((np.asarray(point) - self.centre) @ n - self.d)


def segment_estimate(
    segment: Array,
    pose: Transform2D,
    pose_covariance: Array,
    point_sigma: float,
    spacing: float,
    centre: tuple[float, float] | None = None,
) -> LineEstimate:
    """The line of ``segment`` (in its map's frame) placed by ``pose``, with the covariance of the
    segment fit and of the pose (module docstring); offset from ``centre`` (default: the placed
    segment's midpoint)."""
    s = np.asarray(segment, dtype=np.float64).reshape(4)
    length = float(lengths(s[None])[0])
    placed = pose.apply(s[None])[0]
    u = (placed[2:4] - placed[0:2]) / length
    n = np.array([-u[1], u[0]])
    mid = 0.5 * (placed[0:2] + placed[2:4])
    c = np.asarray(centre if centre is not None else (float(mid[0]), float(mid[1])))
    points = max(length / spacing, 1.0)
    # The fit, about the segment's midpoint: offset and direction independent there.
    fit = np.diag([12.0 * point_sigma**2 / (points * length**2), point_sigma**2 / points])
    at_mid = LineEstimate(math.atan2(n[1], n[0]), 0.0, fit, (float(mid[0]), float(mid[1])))
    # The pose: d = (R p + t - c) . R n_l  =>  dd/dt = n, dd/dtheta = (t - c) . R(theta + pi/2) n_l.
    t = np.array([pose.x, pose.y])
    jac = np.array([[0.0, 0.0, 1.0], [n[0], n[1], float((t - mid) @ np.array([-n[1], n[0]]))]])
    moved = LineEstimate(at_mid.alpha, 0.0, at_mid.covariance + jac @ pose_covariance @ jac.T, at_mid.centre)
    return moved.at((float(c[0]), float(c[1])))


def fuse(a: LineEstimate, b: LineEstimate) -> LineEstimate:
    """Eqs. 6-8: ``b`` folded into ``a`` (both read from ``a``'s reference point)."""
    b = b.at(a.centre)
    x1 = np.array([a.alpha, a.d])
    x2 = np.array([b.alpha, b.d])
    # A line's direction is known up to a turn of 2 pi (both copies face the same way).
    x2[0] = x1[0] + math.remainder(x2[0] - x1[0], 2 * math.pi)
    gain = a.covariance @ np.linalg.inv(a.covariance + b.covariance)
    x = x1 + gain @ (x2 - x1)
    p = (np.eye(2) - gain) @ a.covariance
    return LineEstimate(float(x[0]), float(x[1]), 0.5 * (p + p.T), a.centre)


def fuse_all(estimates: list[LineEstimate]) -> LineEstimate:
    """All estimates of one wall folded in one after the other (the order does not matter)."""
    out = estimates[0]
    for e in estimates[1:]:
        out = fuse(out, e)
    return out


def offset_information(
    segments: Array, pose: Transform2D, pose_covariance: Array, point_sigma: float, spacing: float
) -> Array:
    """``(n,)``: per metre of each segment (in its map's frame, placed by ``pose``), the information
    (1 / m^2) on the placed wall's offset at its midpoint: the weight under which a length-weighted
    line fit of many copies (:class:`~fleetmap.shared.core.walls.WallMap`) weighs each copy as eqs.
    6-8 do. The offset's variance of :func:`segment_estimate` at the midpoint, for all segments at
    once (a global map weighs tens of thousands)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    length = np.maximum(lengths(seg), 1e-9)
    placed = pose.apply(seg)
    u = (placed[:, 2:4] - placed[:, 0:2]) / length[:, None]
    normal = np.column_stack([-u[:, 1], u[:, 0]])
    mid = 0.5 * (placed[:, 0:2] + placed[:, 2:4])
    points = np.maximum(length / spacing, 1.0)
    # as segment_estimate's: dd/dt = n, dd/dtheta = (t - mid) . R(pi/2) n
    lever = np.array([pose.x, pose.y]) - mid
    jac = np.column_stack([normal, lever[:, 1] * normal[:, 0] - lever[:, 0] * normal[:, 1]])
    variance = point_sigma**2 / points + np.einsum("ij,jk,ik->i", jac, np.asarray(pose_covariance), jac)
    return 1.0 / (variance * length)
