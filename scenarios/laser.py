"""A 2D laser range finder simulator, like the paper's SICK LMS 200 (Section V).

Defaults: 180 degree field of view, 1 degree resolution (181 beams, both ends included), 8 m
range, 1 cm Gaussian range noise; optional dropouts (a beam returns nothing) and spurious
returns (a beam returns a random range short of the wall). Ray-segment intersection is
vectorised over beams and walls; walls out of the laser's reach are dropped first, so the cost
of a scan follows what the laser can see, not the size of the building.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.core.geometry import Array, point_segment_distance
from fleetmap.shared.core.rangescan import RangeScan


@dataclass(frozen=True)
class LaserParams:
    fov: float = math.pi
    """Field of view (rad), centred on the laser's x axis."""
    resolution: float = math.radians(1.0)
    """Angle between consecutive beams (rad)."""
    max_range: float = 8.0
    """Beyond this the laser returns nothing (m)."""
    noise: float = 0.01
    """Standard deviation of the Gaussian range noise (m)."""
    dropout: float = 0.0
    """Probability that a beam returns nothing."""
    spurious: float = 0.0
    """Probability that a beam returns a random range short of the wall (a person, a chair leg)."""

    @property
    def beams(self) -> int:
        return round(self.fov / self.resolution) + 1

    def beam_angles(self) -> Array:
        """Direction of each beam in the laser's frame, first beam to the right."""
        return -self.fov / 2.0 + np.arange(self.beams) * self.resolution


def ray_hits(walls: Array, origin: Array, angles: Array) -> tuple[Array, Array]:
    """Distance along each ray to the nearest wall (inf where none) and that wall's row (-1), ``(b,)`` each."""
    if len(walls) == 0:
        return np.full(len(angles), np.inf), np.full(len(angles), -1, dtype=np.int64)
    dx = np.cos(angles)[:, None]
    dy = np.sin(angles)[:, None]
    ax, ay = walls[None, :, 0], walls[None, :, 1]
    ex, ey = walls[None, :, 2] - walls[None, :, 0], walls[None, :, 3] - walls[None, :, 1]
    # Solve origin + r * d = a + s * e for r >= 0 and 0 <= s <= 1.
    den = dx * ey - dy * ex
    wx, wy = ax - origin[0], ay - origin[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (wx * ey - wy * ex) / den
        s = (wx * dy - wy * dx) / den
    hit = (np.abs(den) > 1e-12) & (r > 1e-9) & (s >= 0.0) & (s <= 1.0)
    r = np.where(hit, r, np.inf)
    nearest = r.argmin(axis=1)
    dist = r[np.arange(len(angles)), nearest]
    return dist, np.where(np.isfinite(dist), nearest, -1)


def cast_rays(walls: Array, origin: Array, angles: Array) -> Array:
    """Distance along each ray to the nearest wall (inf where none), ``(b,)``."""
    return ray_hits(walls, origin, angles)[0]


def walls_in_reach(walls: Array, origin: Array, max_range: float) -> Array:
    """Row indices of the walls with a point within ``max_range`` of ``origin``."""
    w = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    return np.flatnonzero(point_segment_distance(np.asarray(origin, dtype=np.float64)[None, :], w) <= max_range)


def true_ranges(walls: Array, pose: tuple[float, float, float], params: LaserParams) -> tuple[Array, Array]:
    """Noise-free range of every beam from the laser ``pose`` (inf: no wall within range) and the
    row of ``walls`` it hits (-1: none)."""
    w = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    origin = np.array(pose[:2], dtype=np.float64)
    near = walls_in_reach(w, origin, params.max_range)
    r, idx = ray_hits(w[near], origin, params.beam_angles() + pose[2])
    beyond = r >= params.max_range
    return np.where(beyond, np.inf, r), np.where(beyond | (idx < 0), -1, near[np.maximum(idx, 0)])


def noisy_ranges(ranges: Array, params: LaserParams, rng: np.random.Generator) -> Array:
    """Gaussian noise, spurious returns and dropouts applied to true ranges (inf: no return)."""
    n = len(ranges)
    r = np.asarray(ranges, dtype=np.float64)
    if params.noise > 0:
        r = r + rng.normal(0.0, params.noise, size=n)
    if params.spurious > 0:
        fake = rng.random(n) < params.spurious
        r = np.where(fake, rng.uniform(0.1, 1.0, size=n) * np.minimum(r, params.max_range), r)
    if params.dropout > 0:
        r = np.where(rng.random(n) < params.dropout, np.inf, r)
    return np.where((r >= params.max_range) | (r <= 0), np.inf, r)


def simulate_scan(
    walls: Array,
    pose: tuple[float, float, float],
    params: LaserParams | None = None,
    rng: np.random.Generator | None = None,
    stamp: float = 0.0,
) -> RangeScan:
    """One scan of ``walls`` from the laser pose ``(x, y, theta)`` in the world frame.

    The pose is kept in the scan's ``odom`` (ground truth for benchmarks; the algorithms never read it).
    """
    p = params or LaserParams()
    r = noisy_ranges(true_ranges(walls, pose, p)[0], p, rng if rng is not None else np.random.default_rng())
    return RangeScan(stamp, -p.fov / 2.0, p.resolution, p.max_range, r, (pose[0], pose[1], pose[2]))
