"""The laser simulator: known distances, the configured noise and dropouts, the far-wall shortcut."""

from __future__ import annotations

import math

import numpy as np
from fleetmap.scenarios.laser import LaserParams, cast_rays, ray_hits, simulate_scan, true_ranges
from fleetmap.scenarios.worlds import get_world

# A long wall 3 m in front of the origin (x = 3) and a short one behind it.
WALLS = np.array([[3.0, -20.0, 3.0, 20.0], [-2.0, -1.0, -2.0, 1.0]])


def test_a_ray_to_a_known_wall_returns_its_distance() -> None:
    angles = np.array([0.0, math.pi / 4, -math.pi / 3, math.pi, math.pi / 2])
    r = cast_rays(WALLS, np.zeros(2), angles)
    np.testing.assert_allclose(r[:4], [3.0, 3.0 * math.sqrt(2), 6.0, 2.0], rtol=1e-12)
    assert r[4] == np.inf  # parallel to both walls: nothing there
    _, idx = ray_hits(WALLS, np.zeros(2), angles)
    assert idx.tolist() == [0, 0, 0, 1, -1]


def test_a_noise_free_scan_sees_the_wall_at_the_right_range_from_any_pose() -> None:
    # Laser at (1, 2) looking along +y at a wall y = 5: the centre beam reads 3 m, beam k reads 3 / cos(a_k).
    wall = np.array([[-50.0, 5.0, 50.0, 5.0]])
    scan = simulate_scan(wall, (1.0, 2.0, math.pi / 2), LaserParams(noise=0.0), np.random.default_rng(0))
    a = scan.angle_min + np.arange(len(scan.ranges)) * scan.angle_increment
    assert len(scan.ranges) == 181 and math.isclose(scan.angle_increment, math.radians(1.0))
    expected = 3.0 / np.cos(a)
    seen = expected < 8.0
    np.testing.assert_allclose(scan.ranges[seen], expected[seen], rtol=1e-9)
    assert np.isinf(scan.ranges[~seen]).all() and seen.sum() == 2 * 67 + 1  # |a| < acos(3/8) = 67.98 deg


def test_range_noise_has_the_configured_spread() -> None:
    laser = LaserParams(fov=math.radians(60), noise=0.01)
    rng = np.random.default_rng(1)
    true = true_ranges(WALLS, (0.0, 0.0, 0.0), laser)[0]
    errors = np.concatenate(
        [simulate_scan(WALLS, (0.0, 0.0, 0.0), laser, rng).ranges - true for _ in range(400)]
    )  # 24 400 readings: the standard deviation is known to 0.5 %, the mean to 0.0001 m
    assert 0.0095 < errors.std() < 0.0105
    assert abs(errors.mean()) < 0.0003


def test_dropouts_happen_at_the_configured_rate_and_spurious_returns_fall_short() -> None:
    laser = LaserParams(fov=math.radians(60), noise=0.0, dropout=0.2, spurious=0.1)
    rng = np.random.default_rng(2)
    true = true_ranges(WALLS, (0.0, 0.0, 0.0), laser)[0]
    scans = np.array([simulate_scan(WALLS, (0.0, 0.0, 0.0), laser, rng).ranges for _ in range(400)])
    dropped = np.isinf(scans).mean()
    assert 0.19 < dropped < 0.21
    returned = scans[np.isfinite(scans)]
    short = returned < np.broadcast_to(true, scans.shape)[np.isfinite(scans)] - 1e-9
    assert 0.09 < short.mean() < 0.11  # spurious among the returns: 0.1 of the beams, none dropped
    assert (returned > 0).all()


def test_far_walls_are_skipped_without_changing_any_reading() -> None:
    # The warehouse (hundreds of walls): reading only the walls within range gives the same scan
    # as casting every ray against every wall.
    world = get_world("warehouse")
    laser = LaserParams()
    for pose in [(12.75, 10.0, 1.2), (20.0, 5.3, 0.0), (30.25, 14.7, -2.0)]:
        fast, idx = true_ranges(world.walls, pose, laser)
        full = cast_rays(world.walls, np.array(pose[:2]), laser.beam_angles() + pose[2])
        full = np.where(full >= laser.max_range, np.inf, full)
        np.testing.assert_array_equal(fast, full)
        assert (idx[np.isfinite(fast)] >= 0).all() and (idx[np.isinf(fast)] == -1).all()
