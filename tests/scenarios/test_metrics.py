"""Ground-truth metrics: zero for the true map, growing with a known perturbation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleetmap.scenarios.fleet import plan
from fleetmap.scenarios.laser import LaserParams
from fleetmap.scenarios.loader import load_scenario
from fleetmap.scenarios.metrics import (
    aligned_map_error,
    coverage,
    map_error,
    pose_errors,
    score_map,
    visible_walls,
    world_from_global,
)
from fleetmap.scenarios.truth import ground_truth
from fleetmap.scenarios.worlds import get_world
from fleetmap.shared.core.geometry import Transform2D, lengths


def shifted_along_normals(walls: np.ndarray, d: float) -> np.ndarray:
    """Every wall moved by ``d`` along its own normal: every point of it ends up d from where it was."""
    direction = walls[:, 2:4] - walls[:, 0:2]
    normal = np.column_stack([-direction[:, 1], direction[:, 0]]) / lengths(walls)[:, None]
    return walls + d * np.hstack([normal, normal])


@pytest.fixture(scope="module")
def department() -> tuple[np.ndarray, np.ndarray]:
    sc = load_scenario("department")
    return sc.world.walls, ground_truth(sc).visible


def test_the_true_map_scores_zero_error_and_full_coverage(department: tuple[np.ndarray, np.ndarray]) -> None:
    walls, visible = department
    err = map_error(walls, walls)
    assert err.mean < 1e-12 and err.p95 < 1e-12 and err.max < 1e-12  # zero up to rounding
    assert coverage(walls, visible) == 1.0 and coverage(visible, visible) == 1.0


def test_walls_shifted_by_5_cm_give_a_mean_error_of_5_cm(department: tuple[np.ndarray, np.ndarray]) -> None:
    walls, visible = department
    err = map_error(shifted_along_normals(walls, 0.05), walls)
    # Points near a corner can be closer to the neighbouring wall than to their own.
    assert 0.045 < err.mean <= 0.05 + 1e-9 and err.p95 == pytest.approx(0.05, abs=1e-6)
    assert coverage(shifted_along_normals(walls, 0.05), visible) > 0.99  # still within 10 cm
    errors = [map_error(shifted_along_normals(walls, d), walls).mean for d in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert errors == sorted(errors) and errors[0] < 1e-12 and errors[-1] > 0.15


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_the_aligned_error_leaves_out_the_frame_not_the_shape(department: tuple[np.ndarray, np.ndarray]) -> None:
    walls, _ = department
    # the true map placed by a submap whose heading was half a degree off, 20 m from its far end:
    # about 10 cm there, but the shape is exact
    turned = Transform2D(0.05, -0.03, math.radians(0.5)).apply(walls)
    assert map_error(turned, walls).mean > 0.05
    err, motion = aligned_map_error(turned, walls)
    assert err.mean < 0.005, err
    back = motion.compose(Transform2D(0.05, -0.03, math.radians(0.5)))
    assert abs(back.theta) < math.radians(0.05) and math.hypot(back.x, back.y) < 0.02
    # a map whose walls are 5 cm off along their normals stays 5 cm off: no motion makes it fit
    shifted, _ = aligned_map_error(shifted_along_normals(walls, 0.05), walls)
    assert shifted.mean > 0.035


def test_coverage_counts_the_visible_length_the_map_has(department: tuple[np.ndarray, np.ndarray]) -> None:
    walls, visible = department
    half = walls[walls[:, 0] + walls[:, 2] < 2 * 8.0]  # the lab only (midpoints west of x = 8)
    in_lab = visible[(visible[:, 0] + visible[:, 2]) / 2 < 7.9]
    expected = lengths(in_lab).sum() / lengths(visible).sum()
    assert coverage(half, visible) == pytest.approx(expected, abs=0.03)
    assert 0.05 < coverage(half, visible) < 0.6
    assert coverage(np.zeros((0, 4)), visible) == 0.0


def test_visible_parts_are_what_the_beams_hit() -> None:
    # One pose 2 m from a 10 m wall, facing it: the whole wall is within the 8 m range.
    wall = np.array([[2.0, -5.0, 2.0, 5.0], [-1.0, -1.0, -1.0, 1.0]])  # the second one is behind the laser
    vis = visible_walls(wall, [Transform2D(0.0, 0.0, 0.0)], LaserParams())
    assert len(vis) == 1 and np.allclose(vis[0, [0, 2]], 2.0)
    assert vis[0, 1] == pytest.approx(-5.0, abs=0.2) and vis[0, 3] == pytest.approx(5.0, abs=0.2)
    far = visible_walls(wall, [Transform2D(-7.5, 0.0, 0.0)], LaserParams())
    assert len(far) == 1 and np.allclose(far[0, [0, 2]], -1.0)  # the near wall hides the far one
    # Seen again from further along, the wall is one part, counted once.
    long_wall = np.array([[2.0, -20.0, 2.0, 20.0]])
    poses = [Transform2D(0.0, y, 0.0) for y in (0.0, 3.0, 20.0)]
    both = visible_walls(long_wall, poses, LaserParams())
    reach = 2.0 * math.tan(math.radians(75.0))  # the last whole-degree beam within 8 m
    np.testing.assert_allclose(
        np.sort(both[:, [1, 3]], axis=1), [[-reach, 3.0 + reach], [20.0 - reach, 20.0]], atol=1e-9
    )


def test_pose_errors_are_measured_after_anchoring_the_global_frame() -> None:
    # Local maps whose frames are scans of the department loop; the global frame is map "a"'s.
    sc = load_scenario("department")
    scans = plan(sc, "r1")
    true = {"a": scans[3].pose, "b": scans[10].pose, "c": scans[20].pose}
    anchor = true["a"]
    exact = {k: anchor.inverse().compose(p) for k, p in true.items()}
    w = world_from_global(true["a"], exact["a"])
    assert all(
        e is not None and e.translation_m < 1e-9 and e.rotation_deg < 1e-9 for e in pose_errors(exact, true, w).values()
    )
    # A map placed 10 cm and 2 degrees off (in its own frame) shows exactly that error.
    off = dict(exact, b=exact["b"].compose(Transform2D(0.06, 0.08, math.radians(2.0))), c=None)
    errors = pose_errors(off, true, w)
    assert errors["a"] is not None and errors["a"].translation_m < 1e-9
    assert errors["b"] is not None and errors["b"].translation_m == pytest.approx(0.10)
    assert errors["b"].rotation_deg == pytest.approx(2.0)
    assert errors["c"] is None
    # The anchor's own estimate need not be the identity: the errors do not change.
    moved = Transform2D(3.0, -1.0, 0.7)
    shifted = {k: moved.compose(p) if p is not None else None for k, p in off.items()}
    again = pose_errors(shifted, true, world_from_global(true["a"], moved.compose(exact["a"])))
    assert again["b"] is not None and again["b"].translation_m == pytest.approx(0.10)


def test_a_map_in_the_anchors_frame_scores_zero_and_a_turned_one_does_not() -> None:
    world = get_world("office")
    sc = load_scenario("office")
    visible = ground_truth(sc).visible
    anchor = plan(sc, "r2")[5].pose
    in_global = anchor.inverse().apply(world.walls)
    right = score_map(in_global, world_from_global(anchor, Transform2D()), world.walls, visible)
    assert right.error.mean < 1e-9 and right.coverage == 1.0
    turned = [
        score_map(
            Transform2D(0, 0, math.radians(deg)).apply(in_global),
            world_from_global(anchor, Transform2D()),
            world.walls,
            visible,
        )
        for deg in (0.5, 2.0)
    ]
    assert 0.0 < turned[0].error.mean < turned[1].error.mean and turned[1].coverage < turned[0].coverage < 1.0
