"""Scan-to-submap registration, the see-through check, the motion models and the wall map: on
simulated scans of known poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleetmap.agents.fitcheck import MAX_SEE_THROUGH, MIN_MATCHED_SHARE
from fleetmap.agents.tracker import Tracker
from fleetmap.scenarios import get_world
from fleetmap.scenarios.laser import LaserParams, simulate_scan
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core import tracking
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Transform2D, lengths
from fleetmap.shared.core.motion import from_odometry, odometry_increment
from fleetmap.shared.core.tracking import (
    SAMPLE_SPACING,
    VOXEL_SIZE,
    ReferenceMap,
    register,
    sample_segments,
    see_through,
)
from fleetmap.shared.core.walls import WallMap

from tests.helpers import set_constant

PARAMS = TrackingParams()
LOOSE = np.diag([1 / 0.5**2, 1 / 0.5**2, 1 / 0.3**2])
"""A prior that barely pulls: the walls decide."""


LASER = LaserParams()


def scan_at(walls, pose, seed=0):
    return simulate_scan(walls, (pose.x, pose.y, pose.theta), LASER, np.random.default_rng(seed))


def submap_of(walls, poses):
    """A reference map of scans taken at ``poses``, in the first one's frame (true poses)."""
    reference = ReferenceMap(VOXEL_SIZE)
    frame = poses[0]
    for k, pose in enumerate(poses):
        samples = sample_segments(extract_segments(scan_at(walls, pose, seed=k)), SAMPLE_SPACING)
        reference.insert(samples.moved(frame.inverse().compose(pose)))
    return reference, frame


@pytest.fixture(scope="module")
def office():
    return get_world("office").walls


@pytest.mark.parametrize(
    "offset",
    [Transform2D(0.15, -0.10, 0.05), Transform2D(-0.3, 0.2, -0.12), Transform2D(0.0, 0.0, math.radians(10))],
)
def test_a_scan_predicted_off_is_registered_where_it_was_taken(office, offset):
    # corridor of the office floor, looking along it past a junction
    poses = [Transform2D(8.0 + 0.2 * k, 7.0, 0.0) for k in range(5)]
    reference, frame = submap_of(office, poses)
    true = Transform2D(9.3, 7.1, 0.08)
    samples = sample_segments(extract_segments(scan_at(office, true, seed=99)), SAMPLE_SPACING)
    truth = frame.inverse().compose(true)
    start = truth.compose(offset)
    reg = register(samples, reference, start, start, LOOSE, PARAMS)
    dt, dr = reg.pose.distance(truth)
    assert dt < 0.02 and math.degrees(dr) < 0.3, (dt, math.degrees(dr))
    assert reg.matched_share > 0.8 and reg.rms < 0.02
    through, visible = see_through(reference, scan_at(office, true, seed=99), reg.pose, 20.0)
    assert visible > 5.0 and through < 0.05 * visible


def test_a_featureless_corridor_leaves_the_translation_along_it_to_the_prior():
    # two parallel walls 2 m apart, 60 m long: a laser of 8 m sees no end
    walls = np.array([[-30.0, -1.0, 30.0, -1.0], [30.0, 1.0, -30.0, 1.0]])
    poses = [Transform2D(0.2 * k, 0.0, 0.0) for k in range(6)]
    reference, _ = submap_of(walls, poses)
    true = Transform2D(1.5, 0.05, 0.02)
    samples = sample_segments(extract_segments(scan_at(walls, true)), SAMPLE_SPACING)
    prior = Transform2D(1.8, -0.1, 0.0)  # odometry 30 cm long, 15 cm to the side, 1 degree off
    information = from_odometry(Transform2D(0.3, 0.0, 0.0)).information()
    reg = register(samples, reference, prior, prior, information, PARAMS)
    assert reg.pose.x == pytest.approx(prior.x, abs=0.01), "along the corridor the prior decides"
    assert reg.pose.y == pytest.approx(true.y, abs=0.01), "across it the walls do"
    assert reg.pose.theta == pytest.approx(true.theta, abs=math.radians(0.3))
    # the walls' own information is nearly nothing along the corridor
    values, vectors = np.linalg.eigh(reg.scan_information[:2, :2])
    assert values[0] < 1e-3 * values[1] and abs(vectors[0, 0]) > 0.99


def test_a_scan_taken_elsewhere_sees_through_the_submaps_walls(office):
    poses = [Transform2D(8.0 + 0.2 * k, 7.0, 0.0) for k in range(5)]
    reference, _ = submap_of(office, poses)
    elsewhere = Transform2D(16.0, 4.4, -1.0)  # in a south room
    scan = scan_at(office, elsewhere)
    samples = sample_segments(extract_segments(scan), SAMPLE_SPACING)
    start = Transform2D(1.0, 0.0, 0.0)  # where odometry says the robot is: it was carried
    reg = register(samples, reference, start, start, LOOSE, PARAMS)
    through, visible = see_through(reference, scan, reg.pose, 20.0)
    fits = reg.matched_share >= MIN_MATCHED_SHARE and through <= MAX_SEE_THROUGH * visible
    assert not fits, (reg.matched_share, through, visible)


def test_odometry_that_jumps_or_is_not_a_number_is_no_measurement():
    a = Transform2D(1.0, 2.0, 0.3)
    step, why = odometry_increment(a, a.compose(Transform2D(0.1, 0.0, 0.05)), 0.1, 3.0)
    assert step is not None and why is None and step.x == pytest.approx(0.1)
    step, why = odometry_increment(a, Transform2D(50.0, 2.0, 0.3), 0.1, 3.0)
    assert step is None and "jumped" in why
    step, why = odometry_increment(a, Transform2D(math.nan, 2.0, 0.3), 0.1, 3.0)
    assert step is None and "finite" in why


def test_a_reference_cell_seen_from_both_sides_of_a_thin_wall_matches_nothing():
    reference = ReferenceMap(0.05)
    wall = np.array([[0.0, 0.0, 2.0, 0.0]])  # free space above (left of the direction)
    reference.insert(sample_segments(wall, 0.05))
    reference.insert(sample_segments(wall[:, [2, 3, 0, 1]], 0.05))  # the same wall seen from below
    index, _ = reference.nearest(np.array([[1.0, 0.02]]), 0.5)
    assert index[0] == -1


def test_the_wall_map_keeps_one_segment_per_stretch_of_wall():
    walls = WallMap(tolerance=0.05)
    rng = np.random.default_rng(3)
    # a 10 m wall seen in 40 overlapping noisy pieces, and a parallel one 1 m off
    for _ in range(40):
        x0 = rng.uniform(0, 8)
        y0, y1 = rng.normal(0, 0.01, 2)
        walls.add(np.array([[x0, y0, x0 + 2.0, y1], [x0 + 2.0, 1.0, x0, 1.0]]))
    seg = walls.segments
    assert len(seg) == 2
    lower = seg[np.argmin(np.abs(seg[:, 1]))]
    assert lower[0] == pytest.approx(min(seg[:, 0]), abs=0.5) and abs(lower[1]) < 0.02
    assert lower[2] > lower[0], "it keeps the side the sensor saw it from"
    # the other side of the lower wall, seen from below, is another wall
    walls.add(np.array([[5.0, -0.02, 3.0, -0.02]]))
    assert len(walls.segments) == 3


def test_a_person_who_walked_off_is_not_a_wall_of_the_submap(office):
    # down the office corridor; for the first scans a person stands 2.5 m ahead, to the left,
    # then walks off: the later scans see the corridor's wall through where they stood
    person = np.array([[10.4, 7.4, 10.4, 7.7], [10.4, 7.7, 10.7, 7.7], [10.7, 7.7, 10.7, 7.4], [10.7, 7.4, 10.4, 7.4]])
    tracker = Tracker(odometry=False)
    for k in range(12):
        pose = Transform2D(8.0 + 0.15 * k, 7.0, 0.0)
        walls = np.vstack([office, person]) if k < 3 else office
        scan = scan_at(walls, pose, seed=k)
        tracker.add(k, 0.1 * k, scan, extract_segments(scan))
    submap = tracker.matching
    assert submap is not None and submap.inserted >= 6
    kept = submap.segment_map().segments
    every = submap.walls.segments
    assert len(every) > len(kept), "the person was seen: the wall map holds them"

    def near(segments, x, y, r):
        mid = (segments[:, 0:2] + segments[:, 2:4]) / 2
        return int((np.hypot(mid[:, 0] - x, mid[:, 1] - y) < r).sum())

    # the submap's frame is the first scan's pose (8, 7): the person is 2.4-2.7 m ahead of it
    assert near(every, 2.55, 0.55, 0.4) > 0
    assert near(kept, 2.55, 0.55, 0.4) == 0, "the scans that saw through them dropped the person"
    # the corridor's walls stay: as much wall length as without the person, within 5 %
    clean = Tracker(odometry=False)
    for k in range(12):
        scan = scan_at(office, Transform2D(8.0 + 0.15 * k, 7.0, 0.0), seed=k)
        clean.add(k, 0.1 * k, scan, extract_segments(scan))
    assert clean.matching is not None
    assert lengths(kept).sum() == pytest.approx(lengths(clean.matching.segment_map().segments).sum(), rel=0.05)


def test_point_to_line_registers_walls_bent_to_a_30_cm_radius_without_bias(monkeypatch):
    # Two arcs of 0.3 m radius about different centres (cheap: well under a second). A cell's mean
    # lies 0.4 mm inside such a wall, and a scan point as far inside its cell's tangent: the two
    # cancel, so the tangent line needs no curve (Armesto et al.'s second order; record 012).
    def arc(cx, cy, a0, a1):
        a = np.linspace(a0, a1, 200)
        pts = np.column_stack([cx + 0.3 * np.cos(a), cy + 0.3 * np.sin(a)])
        return np.hstack([pts[:-1], pts[1:]])

    world = np.vstack([arc(0.0, 3.0, -0.2 * math.pi, -0.8 * math.pi), arc(3.0, 0.0, 0.8 * math.pi, 1.2 * math.pi)])
    reference = ReferenceMap(VOXEL_SIZE)
    reference.insert(sample_segments(world, 0.01))
    truth = Transform2D(0.05, -0.04, 0.03)
    scan = sample_segments(truth.inverse().apply(world), SAMPLE_SPACING)
    start = truth.compose(Transform2D(0.1, -0.1, 0.05))
    for name, value in (("CONVERGENCE_TRANSLATION", 1e-7), ("CONVERGENCE_ROTATION", 1e-7), ("MAX_ITERATIONS", 60)):
        set_constant(monkeypatch, tracking, name, value)
    reg = register(scan, reference, start, start, np.zeros((3, 3)), PARAMS)
    dt, dr = reg.pose.distance(truth)
    assert reg.converged and dt < 1e-4 and dr < math.radians(0.005), (dt, math.degrees(dr))


def test_the_beam_test_tells_a_wall_passed_through_from_one_hit_one_hidden_and_one_out_of_sight():
    from fleetmap.shared.core.rangescan import RangeScan

    # a wall 2 m ahead of the laser at the origin, facing it, 5 m long: 9 samples
    points = np.column_stack([np.full(9, 2.0), np.linspace(-0.2, 0.2, 9)])
    normals = np.tile([-1.0, 0.0], (9, 1))
    support = np.full(9, 5.0)

    def scan(reading: float) -> RangeScan:
        return RangeScan(0.0, -math.pi / 2, math.pi / 180, 30.0, np.full(181, reading))

    here = Transform2D(0.0, 0.0, 0.0)
    for reading, expected in ((3.0, "through"), (2.05, "hit"), (1.0, "visible"), (math.nan, "none")):
        visible, through, hit = tracking.beam_test(points, normals, support, scan(reading), here, 20.0)
        said = "through" if through.all() else "hit" if hit.all() else "visible" if visible.all() else "none"
        assert said == expected and (visible.all() or not visible.any()), (reading, visible, through, hit)
    # from behind the wall, looking back at it, its face is turned away: out of sight
    visible, _, _ = tracking.beam_test(points, normals, support, scan(3.0), Transform2D(4.0, 0.0, math.pi), 20.0)
    assert not visible.any()
    # beyond the laser's reach, or beyond the caller's max range, nothing is seen
    visible, _, _ = tracking.beam_test(points, normals, support, scan(3.0), here, 1.5)
    assert not visible.any()
    # a wall 0.4 m long, hit by one scan and passed through by two: 0.4 m seen, 0.8 m through
    # (a wall segment faces the side its normal is on: left of its direction)
    seen, passed = tracking.wall_evidence(
        np.array([[2.0, -0.2, 2.0, 0.2]]), [(scan(r), here) for r in (3.0, 2.05, 3.0)], 20.0
    )
    assert seen.tolist() == pytest.approx([0.4]) and passed.tolist() == pytest.approx([0.8])
