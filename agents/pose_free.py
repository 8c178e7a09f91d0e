"""The paper's pose-free integration inside tracking (pure: segments in, a start out).

Registration finds the nearest minimum of the walls to where it starts; pose-free integration
(paper III-E, Algorithm 1) finds where a scan fits whatever the start. The tracker uses it twice:

- **the step from the last scan the walls placed** (:func:`stepped`; a carried scan's view fixed
  nothing, and its pose is a guess): where the motion model measures nothing
  (no odometry, and constant velocity over a sparse log's second between scans is a guess 1.5 m
  wide), the scan integrated on the previous placed scan measures the step, as the pivot method
  places each scan on the one before it (paper IV-C, Algorithm 6). Down a corridor logged a scan
  every one to three metres, registration from constant velocity slid to where the robot had
  stood (orebro-corrected scans 27-36, 2-4.5 m short a step), and the velocity it then measured
  predicted the next step short too; the scan pair integrates right and valid at 204 of that
  log's 236 steps (``benchmarks/scan_pairs.py``);
- **a scan re-acquired on its submap** (:func:`reacquired`): no start of the motion models fitted,
  and the scan is searched on the submap's own segments within the robot's reach.

Each answer is a start for registration on the submap, with :func:`loose` as its prior: the
integration puts the scan within registration's reach, the walls decide where in it.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.integration import Integration, Window, integrate
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.validity import is_valid

__all__ = ["LOOSE_ROTATION", "LOOSE_TRANSLATION", "ambiguous", "loose", "paired", "reacquired", "stepped"]

LOOSE_TRANSLATION = 0.25
"""Standard deviation (m) of a start found by pose-free integration, as a prior: a quarter of
registration's reach (``MAX_CORRESPONDENCE``), so that the walls, not the start, place the scan."""
LOOSE_ROTATION = 0.1
"""Standard deviation (rad) of its heading, likewise."""


def loose() -> Array:
    """The information of a start found by pose-free integration (:data:`LOOSE_TRANSLATION`,
    :data:`LOOSE_ROTATION`)."""
    t = 1.0 / LOOSE_TRANSLATION**2
    return np.diag([t, t, 1.0 / LOOSE_ROTATION**2])


def _scan_map(segments: Array) -> SegmentMap:
    return SegmentMap(segments, ordered=True, oriented=True)


def stepped(previous: Array, segments: Array, reach: float, params: IntegrationParams) -> Transform2D | None:
    """The scan's pose in the frame of the previous placed scan, whose segments are ``previous``:
    the best transformation of the two scans' pose-free integration within ``reach`` (m, any
    heading) of where the previous one was taken, or None where it is not valid (its value too low,
    its walls in the other scan's seen free space, or another transformation nearly as good)."""
    found = paired(previous, segments, reach, params)
    return found.transform if found is not None and found.valid else None


def paired(previous: Array, segments: Array, reach: float, params: IntegrationParams) -> Integration | None:
    """The two scans' pose-free integration of :func:`stepped`, valid or not (None: a scan without
    walls)."""
    if len(previous) == 0 or len(segments) == 0:
        return None
    window = Window(Transform2D(), reach, math.pi)
    return integrate(_scan_map(previous), _scan_map(segments), params, window=window)


def ambiguous(previous: Array, segments: Array, found: Integration, params: IntegrationParams) -> bool:
    """Whether the pair's integration ``found`` (:func:`paired`) would be valid but for a rival
    nearly as good (the validity rule with no runner-up: :func:`~fleetmap.shared.core.validity.is_valid`).
    Its best then fits the pair's walls as a valid one does, and along a corridor whose doors repeat
    it is often right (orebro-corrected, scans 150 -> 151: the best 0.09 m off, a rival 2.5 m back
    at 0.9 of its value); one of too little value, or with walls in the other scan's seen free
    space, is not."""
    if found.valid:
        return False
    return is_valid(found.value, found.violation, 0.0, _scan_map(previous), _scan_map(segments), params)


def _near(m: SegmentMap, pose: Transform2D, radius: float) -> SegmentMap:
    """The segments of ``m`` with an end within ``radius`` (box) of ``pose``."""
    seg = m.segments
    close = (np.abs(seg[:, 0:4:2] - pose.x) <= radius).any(axis=1) & (np.abs(seg[:, 1:4:2] - pose.y) <= radius).any(
        axis=1
    )
    return SegmentMap(seg[close], ordered=False, oriented=m.oriented)


def reacquired(
    built: SegmentMap, segments: Array, last: Transform2D, reach: float, max_range: float, params: IntegrationParams
) -> Transform2D | None:
    """The scan's pose in the frame of a submap whose segments are ``built``: the best
    transformation of its pose-free integration on the submap's segments near ``last`` (the last
    placed pose, the submap's frame), within ``reach`` (m, any heading), or None where it is not valid."""
    if len(built) == 0:
        return None
    close = _near(built, last, reach + max_range)
    if len(close) == 0:
        return None
    found = integrate(close, _scan_map(segments), params, window=Window(last, reach, math.pi))
    return found.transform if found.valid else None
