"""People walking past a robot, put into its scans on purpose: legs that hide the walls behind them."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pytest
from fleetmap.scenarios.crowd import APPEAR, LEG_RADIUS, _occluded, walk_people
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.rangescan import RangeScan


@dataclass(frozen=True)
class Reading:
    index: int
    stamp: float
    scan: RangeScan
    odometry: Transform2D | None


def corridor(n: int = 300, period: float = 0.2) -> list[Reading]:
    """A robot driving along x at 1 m/s, every beam on a wall 3 m away (a 181-beam half circle)."""
    scan = RangeScan(0.0, -math.pi / 2, math.pi / 180, 30.0, np.full(181, 3.0))
    return [Reading(k, period * k, scan, Transform2D(period * k, 0.0, 0.0)) for k in range(n)]


def test_a_leg_ahead_hides_the_wall_behind_it_and_nothing_else() -> None:
    angles = np.linspace(-math.pi / 2, math.pi / 2, 181)
    ranges = np.full(181, 3.0)
    ranges[0] = math.inf  # no return
    out = _occluded(ranges, angles, np.array([[2.0, 0.0], [0.0, -1.0]]), range_max=30.0)
    assert out[90] == pytest.approx(2.0 - LEG_RADIUS)
    hidden = np.flatnonzero(out != ranges)
    # a 12 cm leg 2 m ahead spans 3-4 beams a degree apart; the one at the right edge, 1 m away, 7
    assert set(range(89, 92)) <= set(hidden) and len(hidden) <= 12
    assert out[0] == pytest.approx(1.0 - LEG_RADIUS, abs=0.01), "a beam with no return returns on a leg"
    assert np.all(out <= ranges)


def test_people_hide_a_few_beams_of_most_scans_and_change_nothing_else() -> None:
    scans = corridor()
    walked = list(walk_people(scans, 3, seed=1))
    assert [(s.index, s.stamp, s.odometry) for s in walked] == [(s.index, s.stamp, s.odometry) for s in scans]
    hidden = np.array([np.sum(w.scan.ranges < s.scan.ranges) for w, s in zip(walked, scans, strict=True)])
    assert np.mean(hidden > 0) > 0.5, "three people are in view of most scans"
    assert np.median(hidden[hidden > 0]) < 30, "a few legs hide a few beams"
    nearest = min(float(np.min(w.scan.ranges)) for w in walked)
    assert nearest < APPEAR[1] and all(np.min(w.scan.ranges) > 0 for w in walked)
    assert list(walk_people(scans, 0)) == scans
    again = list(walk_people(scans, 3, seed=1))
    assert all(np.array_equal(a.scan.ranges, b.scan.ranges) for a, b in zip(again, walked, strict=True))
    with pytest.raises(ValueError, match="people: -1"):
        list(walk_people(scans, -1))


def test_people_walk_in_the_world_not_with_the_robot() -> None:
    # the robot drives at 5 m/s (1 m a scan) past one person walking at 1.4 m/s at most: where the
    # legs are seen, in the world (by the robot's odometry), moves 0.28 m a scan at most (and the
    # legs' spacing), never the robot's metre
    scans = corridor(period=0.2)
    fast = [Reading(s.index, s.stamp, s.scan, Transform2D(5.0 * s.stamp, 0.0, 0.0)) for s in scans]
    walked = list(walk_people(fast, 1, seed=2))
    seen: list[tuple[int, np.ndarray]] = []
    for w in walked:
        hit = np.flatnonzero(w.scan.ranges < 3.0)
        if len(hit):
            a = w.scan.angle_min + w.scan.angle_increment * hit
            r = w.scan.ranges[hit]
            local = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
            seen.append((w.index, w.odometry.apply_points(local).mean(axis=0)))
    steps = [float(np.hypot(*(q - p))) for (i, p), (j, q) in itertools.pairwise(seen) if j == i + 1]
    assert len(steps) > 10
    assert np.median(steps) < 0.5, "a walking person, not one carried along at the robot's speed"
