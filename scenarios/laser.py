"""A 2D laser range finder simulator, like the paper's SICK LMS 200 (Section V).

Defaults: 180 degree field of view, 1 degree resolution (181 beams, both ends included), 8 m
range, 1 cm Gaussian range noise; optional dropouts (a beam returns nothing) and spurious
returns (a beam returns a random range short of the wall). Ray-segment intersection is
vectorised over beams and walls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.geometry import Array
from fleetmap.shared.scans import RangeScan


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


def cast_rays(walls: Array, origin: Array, angles: Array) -> Array:
    """Distance along each ray to the nearest wall (inf where none), ``(b,)``."""
    if len(walls) == 0:
        return np.full(len(angles), np.inf)
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
    return np.where(hit, r, np.inf).min(axis=1)


def simulate_scan(
    walls: Array,
    pose: tuple[float, float, float],
    params: LaserParams | None = None,
    rng: np.random.Generator | None = None,
    stamp: float = 0.0,
) -> RangeScan:
    """One scan of ``walls`` from the laser pose ``(x, y, theta)`` in the world frame."""
    p = params or LaserParams()
    g = rng if rng is not None else np.random.default_rng()
    n = p.beams
    angle_min = -p.fov / 2.0
    rel = angle_min + np.arange(n) * p.resolution
    r = cast_rays(np.asarray(walls, dtype=np.float64), np.array(pose[:2], dtype=np.float64), rel + pose[2])
    if p.noise > 0:
        r = r + g.normal(0.0, p.noise, size=n)
    if p.spurious > 0:
        fake = g.random(n) < p.spurious
        r = np.where(fake, g.uniform(0.1, 1.0, size=n) * np.minimum(r, p.max_range), r)
    if p.dropout > 0:
        r = np.where(g.random(n) < p.dropout, np.inf, r)
    r = np.where((r > p.max_range) | (r <= 0), np.inf, r)
    return RangeScan(stamp, angle_min, p.resolution, p.max_range, r, (pose[0], pose[1], pose[2]))
