"""Ballesta et al.'s RANSAC aligner: known transforms recovered from landmark correspondences."""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.config import IntegrationParams, tuned
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import integrate
from fleetmap.shared.core.ransac import landmarks_of, ransac_align
from fleetmap.shared.core.segmap import SegmentMap

from tests.helpers import OMNI, ROOM, scan_map

RANSAC = tuned(IntegrationParams(), aligner="ransac")


def clutter(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` L-shaped pieces (two walls meeting at a corner) at random places in ROOM's extent:
    a corner and two ends each, landmarks the other map does not have."""
    out = []
    for _ in range(count):
        x, y = rng.uniform(1.0, 11.0), rng.uniform(1.0, 9.0)
        a = rng.uniform(-math.pi, math.pi)
        b = a + rng.uniform(0.6, 2.5)
        la, lb = rng.uniform(0.3, 0.8, size=2)
        out += [[x + la * math.cos(a), y + la * math.sin(a), x, y], [x, y, x + lb * math.cos(b), y + lb * math.sin(b)]]
    return np.array(out)


def test_ransac_finds_a_known_transform_with_30_percent_outlier_landmarks() -> None:
    rng = np.random.default_rng(7)
    truth = Transform2D(2.3, -1.4, 2.1)  # B's frame in A's
    a = SegmentMap(ROOM, ordered=False, oriented=False)
    world_b = np.vstack([ROOM + rng.normal(0.0, 0.01, ROOM.shape), clutter(rng, 5)])
    b = SegmentMap(truth.inverse().apply(world_b), ordered=False, oriented=False)
    # The share of B's landmarks with no landmark of A where the truth puts them: outliers.
    la, lb = landmarks_of(a.segments, RANSAC), landmarks_of(b.segments, RANSAC)
    placed = truth.apply_points(lb.points)
    nearest = np.min(np.hypot(*(placed[:, None, :] - la.points[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert np.mean(nearest > 0.1) >= 0.3

    found = ransac_align(a.segments, b.segments, RANSAC)
    dt, dr = found.transform.distance(truth)
    assert dt < 0.03 and dr < math.radians(0.5)
    r = integrate(a, b, RANSAC)
    dt, dr = r.transform.distance(truth)
    assert r.heuristic == "ransac" and r.valid
    assert dt < 0.02 and dr < math.radians(0.3)


def test_a_map_with_itself_is_the_identity() -> None:
    m = scan_map(ROOM, (4.5, 4.5, 0.3), OMNI, seed=3)
    r = integrate(m, m, RANSAC)
    assert r.valid
    dt, dr = r.transform.distance(Transform2D.identity())
    assert dt < 1e-6 and dr < 1e-6


def test_two_scans_of_a_room_are_aligned_from_their_landmarks() -> None:
    truth = Transform2D(1.2, 0.8, -1.9)
    pose_a = (4.5, 4.5, 0.4)
    pose_b = Transform2D(*pose_a).compose(truth)
    a = scan_map(ROOM, pose_a, OMNI, seed=1)
    b = scan_map(ROOM, (pose_b.x, pose_b.y, pose_b.theta), OMNI, seed=2)
    r = integrate(a, b, RANSAC)
    dt, dr = r.transform.distance(truth)
    assert r.valid and dt < 0.05 and dr < math.radians(1.0)
