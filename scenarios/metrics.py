"""Ground-truth scores of a merged map (pure numpy: arrays in, numbers out).

- **Map error**: points sampled along the merged map's segments (every ``spacing``), each at its
  distance to the nearest true wall; the length-weighted mean, 95th percentile and root mean
  square, in metres.
- **Coverage**: the fraction of the *visible* wall length (the parts of the walls that the
  simulated scans hit, :func:`visible_walls`) that lies within ``tolerance`` of the merged map.
- **Pose errors**: the merged map's frame ("global") is that of an anchor local map, which the
  algorithms place without knowing the world. It is tied to the world through the anchor's true
  pose: ``T_world_global = T_world_anchor_true * T_global_anchor_est^-1``
  (:func:`world_from_global`); a placed local map's (or a relocalized robot's) estimated pose
  ``T_global_x``, carried into the world, is compared with its true pose: the translation (m) and
  rotation (degrees) between the two.

All three are 0 (coverage 1) for the true map and grow with any perturbation of it.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from fleetmap.scenarios.laser import LaserParams, true_ranges
from fleetmap.shared.core.geometry import Array, Transform2D, lengths, point_segment_distance, segment_points

K = TypeVar("K", bound=Hashable)

CHUNK = 1 << 21
"""Point-segment distance pairs computed at once (bounds the memory of a large map)."""


@dataclass(frozen=True)
class MapError:
    """Distance from the merged map to the true walls (m)."""

    mean: float
    p95: float
    max: float
    rms: float = math.nan
    """The root mean square (Dugarjav & Lee 2015, Table I's score)."""


@dataclass(frozen=True)
class PoseError:
    translation_m: float
    rotation_deg: float


def nearest_distance(points: Array, segments: Array) -> Array:
    """Distance from each point ``(m, 2)`` to the nearest of ``segments`` ``(n, 4)`` (inf if none)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    s = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(s) == 0:
        return np.full(len(p), np.inf)
    out = np.empty(len(p))
    step = max(1, CHUNK // len(s))
    for i in range(0, len(p), step):
        out[i : i + step] = point_segment_distance(p[i : i + step, None, :], s[None, :, :]).min(axis=1)
    return out


def _weighted_samples(segments: Array, spacing: float) -> tuple[Array, Array]:
    """Points along segments and the wall length each one stands for."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    points, idx = segment_points(seg, spacing)
    per_segment = np.bincount(idx, minlength=len(seg))
    return points, lengths(seg)[idx] / per_segment[idx]


def weighted_quantile(values: Array, weights: Array, q: float) -> float:
    order = np.argsort(values)
    v, w = values[order], weights[order]
    cum = np.cumsum(w)
    return float(v[min(int(np.searchsorted(cum, q * cum[-1])), len(v) - 1)])


def map_error(segments: Array, walls: Array, spacing: float = 0.02) -> MapError:
    """How far the merged map's segments (world frame) lie from the true walls."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(seg) == 0:
        return MapError(math.nan, math.nan, math.nan)
    points, weights = _weighted_samples(seg, spacing)
    d = nearest_distance(points, walls)
    return MapError(
        float(np.average(d, weights=weights)),
        weighted_quantile(d, weights, 0.95),
        float(d.max()),
        math.sqrt(float(np.average(d * d, weights=weights))),
    )


ALIGN_SPACING = 0.05
"""Metres between the wall points the best-fit alignment of :func:`aligned_map_error` uses."""
ALIGN_REACH = 0.5
"""A point farther than this (m) from every true wall counts as this far in the fit (robust: a
wrongly merged piece does not drag the alignment)."""


def aligned_map_error(segments: Array, walls: Array, spacing: float = 0.02) -> tuple[MapError, Transform2D]:
    """:func:`map_error` after the rigid motion that lays the map best on the true walls (robust
    least squares from where the map is), and that motion. A pose-free map's frame is arbitrary:
    placed by one submap's true pose (:func:`world_from_global`), a small heading error of that
    submap turns the whole map about it, which this leaves out, as trajectory tools align an
    estimate before they score it."""
    from scipy.optimize import least_squares

    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(seg) == 0:
        return MapError(math.nan, math.nan, math.nan), Transform2D.identity()
    points, weights = _weighted_samples(seg, ALIGN_SPACING)
    root = np.sqrt(weights)

    def residuals(x: Array) -> Array:
        moved = Transform2D(float(x[0]), float(x[1]), float(x[2])).apply_points(points)
        return root * np.minimum(nearest_distance(moved, walls), ALIGN_REACH)

    fit = least_squares(residuals, np.zeros(3), loss="soft_l1", f_scale=0.05, x_scale=[1.0, 1.0, 0.05])
    motion = Transform2D(float(fit.x[0]), float(fit.x[1]), float(fit.x[2]))
    return map_error(motion.apply(seg), walls, spacing), motion


def visible_walls(walls: Array, poses: Iterable[Transform2D], laser: LaserParams, min_hits: int = 3) -> Array:
    """The parts of the walls the laser hits from ``poses`` (noise-free), as segments ``(k, 4)``.

    A part is the stretch of one wall between the first and last of a run of consecutive beams
    that hit it; runs of fewer than ``min_hits`` beams are left out (the extraction makes no
    segment of them either). Parts of one wall seen from several poses are joined, so each bit of
    visible wall is counted once.
    """
    w = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    wall_of, lo, hi = [], [], []
    direction = w[:, 2:4] - w[:, 0:2]
    squared = (direction**2).sum(axis=1)
    for pose in poses:
        r, idx = true_ranges(w, (pose.x, pose.y, pose.theta), laser)
        # Runs of consecutive beams on the same wall.
        cut = np.flatnonzero(np.diff(idx) != 0) + 1
        starts = np.concatenate([[0], cut])
        stops = np.concatenate([cut, [len(idx)]])
        keep = (idx[starts] >= 0) & (stops - starts >= min_hits)
        first, last, k = starts[keep], stops[keep] - 1, idx[starts[keep]]
        angles = laser.beam_angles() + pose.theta
        # Where the first and last beams of each run hit, as fractions along the wall.
        ends = []
        for beam in (first, last):
            hit = np.column_stack([pose.x + r[beam] * np.cos(angles[beam]), pose.y + r[beam] * np.sin(angles[beam])])
            ends.append(((hit - w[k, 0:2]) * direction[k]).sum(axis=1) / squared[k])
        wall_of.append(k)
        lo.append(np.clip(np.minimum(*ends), 0.0, 1.0))
        hi.append(np.clip(np.maximum(*ends), 0.0, 1.0))
    if not wall_of or not sum(len(k) for k in wall_of):
        return np.zeros((0, 4))
    return _union(w, np.concatenate(wall_of), np.concatenate(lo), np.concatenate(hi))


def _union(walls: Array, wall_of: Array, lo: Array, hi: Array) -> Array:
    """Intervals ``[lo, hi]`` (fractions along ``walls[wall_of]``) joined where they overlap, as segments."""
    # Offsetting each wall's fractions by 2 * its row orders all intervals on one line, so one
    # running maximum finds where a new group starts.
    order = np.lexsort((lo, wall_of))
    a = lo[order] + 2.0 * wall_of[order]
    b = hi[order] + 2.0 * wall_of[order]
    reach = np.maximum.accumulate(b)
    new = np.concatenate([[True], a[1:] > reach[:-1] + 1e-9])
    starts = a[new]
    stops = np.maximum.reduceat(b, np.flatnonzero(new))
    rows = wall_of[order][new]
    f0, f1 = starts - 2.0 * rows, stops - 2.0 * rows
    seg = walls[rows]
    d = seg[:, 2:4] - seg[:, 0:2]
    out = np.hstack([seg[:, 0:2] + d * f0[:, None], seg[:, 0:2] + d * f1[:, None]])
    return out[lengths(out) > 1e-9]


def coverage(segments: Array, visible: Array, tolerance: float = 0.10, spacing: float = 0.05) -> float:
    """Fraction of the visible wall length within ``tolerance`` of the merged map (world frame)."""
    vis = np.asarray(visible, dtype=np.float64).reshape(-1, 4)
    if len(vis) == 0:
        return math.nan
    points, weights = _weighted_samples(vis, spacing)
    covered = nearest_distance(points, segments) <= tolerance
    return float(weights[covered].sum() / weights.sum())


def world_from_global(anchor_true: Transform2D, anchor_estimated: Transform2D) -> Transform2D:
    """``T_world_global`` from the anchor map's true pose (world) and estimated pose (global frame)."""
    return anchor_true.compose(anchor_estimated.inverse())


def pose_error(estimated: Transform2D, true: Transform2D, world_global: Transform2D) -> PoseError:
    """Error of a pose estimated in the global frame against its true pose in the world frame."""
    translation, rotation = world_global.compose(estimated).distance(true)
    return PoseError(translation, math.degrees(rotation))


def pose_errors(
    estimated: Mapping[K, Transform2D | None], true: Mapping[K, Transform2D], world_global: Transform2D
) -> dict[K, PoseError | None]:
    """:func:`pose_error` of every estimated pose that has a truth (None where it was not placed)."""
    return {
        key: None if est is None else pose_error(est, true[key], world_global)
        for key, est in estimated.items()
        if key in true
    }


@dataclass(frozen=True)
class MapScore:
    error: MapError
    coverage: float


def score_map(segments_global: Array, world_global: Transform2D, walls: Array, visible: Array) -> MapScore:
    """Map error and coverage of a merged map given in the global frame."""
    seg = world_global.apply(np.asarray(segments_global, dtype=np.float64).reshape(-1, 4))
    return MapScore(map_error(seg, walls), coverage(seg, visible))
