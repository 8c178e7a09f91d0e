"""A robot's scans with people walking past it (issue 48's test data: clutter that moves).

A laser in a building sees people as well as walls. At the laser's height a person is two legs, each
a small arc that hides the wall behind it. People walk past the robot, stand in its way, cross its
path. :func:`walk_people` puts such people into a source's scans: each scan's ranges are the
log's own, shortened where a leg stands in a beam's way. It changes nothing else: not the stamps,
not the odometry, not the order.

The people walk in the world, not with the robot. A person appears in the laser's field of view,
1-5 m away (:data:`APPEAR`), walks a straight line at 0.5-1.4 m/s (:data:`SPEED`, a walking pace)
for 3-15 s (:data:`LIFETIME`), and is replaced by another when that time is up or when they are
more than :data:`GONE` m from the laser. The robot's pose in the world is its odometry, read at
the scan's time (the odometry drifts, but not over a person's few seconds). A source with no
clock (stamps that do not increase) is walked through at one second a scan, and a scan with no
odometry reading is placed where the last reading put the robot.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import random
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

import numpy as np
from fleetmap.scenarios.clocks import OdometryTrack
from fleetmap.shared.core.geometry import Transform2D

LEG_RADIUS = 0.06
"""A leg at the laser's height (m): a calf is 10-13 cm across."""
LEG_SPACING = 0.3
"""Between a person's two legs (m), across the way they walk."""
APPEAR = (1.0, 5.0)
"""How far from the laser a person appears (m), anywhere in its field of view."""
SPEED = (0.5, 1.4)
"""A walking pace (m/s)."""
LIFETIME = (3.0, 15.0)
"""How long a person walks in view (s) before another takes their place."""
GONE = 8.0
"""A person farther than this from the laser (m) is replaced."""

S = TypeVar("S")


@dataclasses.dataclass
class _Person:
    x: float
    y: float
    heading: float
    speed: float
    born: float
    until: float

    def legs(self, t: float) -> list[tuple[float, float]]:
        """Where the two legs are at time ``t`` (world frame)."""
        walked = self.speed * (t - self.born)
        cx = self.x + walked * math.cos(self.heading)
        cy = self.y + walked * math.sin(self.heading)
        dx, dy = -math.sin(self.heading) * LEG_SPACING / 2, math.cos(self.heading) * LEG_SPACING / 2
        return [(cx + dx, cy + dy), (cx - dx, cy - dy)]


def walk_people(scans: Iterable[S], people: int, seed: int = 0) -> Iterator[S]:
    """The scans with ``people`` people walking past the robot (the module). ``people`` 0 gives the
    scans as they are. Each scan needs a ``scan`` with ``ranges``, ``angle_min`` and
    ``angle_increment`` (a :class:`~fleetmap.shared.core.rangescan.RangeScan`), and ``stamp`` and
    ``odometry`` fields. The same ``seed`` walks the same people."""
    if people < 0:
        raise ValueError(f"people: {people} (must be 0 or more)")
    items = list(scans)
    if people == 0 or not items:
        yield from items
        return
    stamps = [float(s.stamp) for s in items]  # type: ignore[attr-defined]
    if any(b <= a for a, b in itertools.pairwise(stamps)):
        stamps = [float(i) for i in range(len(items))]
    track = OdometryTrack(stamps, [s.odometry for s in items])  # type: ignore[attr-defined]
    rng = random.Random(seed)
    crowd: list[_Person | None] = [None] * people
    pose = Transform2D()
    for s, t in zip(items, stamps, strict=True):
        pose = track.at(t) or pose
        scan = s.scan  # type: ignore[attr-defined]
        angles = scan.angle_min + scan.angle_increment * np.arange(len(scan.ranges))
        field = (float(angles[0]), float(angles[-1]))
        legs = []
        for k, person in enumerate(crowd):
            if person is None or t >= person.until or _distance(person, t, pose) > GONE:
                person = crowd[k] = _appear(rng, pose, t, field)
            legs += person.legs(t)
        in_laser = pose.inverse().apply_points(np.array(legs))
        ranges = _occluded(np.asarray(scan.ranges, dtype=float), angles, in_laser, scan.range_max)
        yield _with_ranges(s, dataclasses.replace(scan, ranges=ranges))


def _appear(rng: random.Random, pose: Transform2D, t: float, field: tuple[float, float]) -> _Person:
    """A person somewhere in the laser's field of view, walking any way."""
    bearing, distance = rng.uniform(*field), rng.uniform(*APPEAR)
    x, y = pose.apply_points(np.array([[distance * math.cos(bearing), distance * math.sin(bearing)]]))[0]
    return _Person(
        float(x), float(y), rng.uniform(-math.pi, math.pi), rng.uniform(*SPEED), t, t + rng.uniform(*LIFETIME)
    )


def _distance(person: _Person, t: float, pose: Transform2D) -> float:
    (x, y), _ = person.legs(t)
    return math.hypot(x - pose.x, y - pose.y)


def _occluded(ranges: np.ndarray, angles: np.ndarray, legs: np.ndarray, range_max: float) -> np.ndarray:
    """``ranges`` shortened where a beam meets a leg (circles of :data:`LEG_RADIUS` at ``legs``,
    the laser's frame) before its own return; a beam with no return that meets one returns there."""
    out = ranges.copy()
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    for cx, cy in legs:
        along = u @ np.array([cx, cy])
        across2 = cx * cx + cy * cy - along * along
        hit = (along > 0) & (across2 <= LEG_RADIUS * LEG_RADIUS)
        hit &= along < range_max
        near = along - np.sqrt(np.maximum(LEG_RADIUS * LEG_RADIUS - across2, 0.0))
        hit &= near > 0  # (a laser inside a leg: the robot drove into someone, which no log shows)
        returned = np.isfinite(out) & (out > 0) & (out < range_max)
        shorter = hit & (~returned | (near < out))
        out[shorter] = near[shorter]
    return out


def _with_ranges(item: S, scan: Any) -> S:
    return dataclasses.replace(item, scan=scan)  # type: ignore[type-var]
