"""Geometry of segments and transforms: hand-computed cases and properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleetmap.shared.core.geometry import (
    Transform2D,
    matching_value,
    point_segment_distance,
    segment_distance,
    segments_intersect,
    transform_segments_batch,
    wrap_angle,
    wrap_scalar,
)
from hypothesis import given, settings
from hypothesis import strategies as st

TOL = 0.015
coord = st.floats(-50, 50, allow_nan=False, allow_infinity=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False, allow_infinity=False, exclude_max=True)
transforms = st.builds(Transform2D, coord, coord, angle)


def mv(a: list[float], b: list[float]) -> float:
    return float(matching_value(np.array(a), np.array(b), TOL, 5.0, 0.95))


def test_distance_d_is_min_of_max_point_to_line_distances() -> None:
    # Fig. 2 with numbers: s2's ends are a = 0.10 and b = 0.30 from s1's line (max 0.30); s1's
    # ends are c and d from s2's line. s2 runs from (0, 0.1) to (4, 0.3), so its line is
    # y = 0.1 + 0.05 x: c = 0.1 / sqrt(1 + 0.05**2) for (0, 0), d = 0.2 / sqrt(...) for (2, 0).
    s1 = np.array([0.0, 0.0, 2.0, 0.0])
    s2 = np.array([0.0, 0.1, 4.0, 0.3])
    k = math.sqrt(1 + 0.05**2)
    expected = min(max(0.1, 0.3), max(0.1 / k, 0.2 / k))
    assert math.isclose(float(segment_distance(s1, s2)), expected, rel_tol=1e-9)
    assert math.isclose(expected, 0.2 / k)


def test_matching_value_of_identical_segments_is_their_length() -> None:
    assert math.isclose(mv([0, 0, 3, 0], [0, 0, 3, 0]), 3.0)


def test_matching_value_of_overlapping_collinear_segments_is_the_common_part() -> None:
    # Common part 1 m on both projections; they touch (intersect), so no penalisation.
    assert math.isclose(mv([0, 0, 2, 0], [1, 0, 3, 0]), 1.0)


def test_matching_value_is_penalised_by_distance_when_segments_do_not_intersect() -> None:
    # Parallel, 3 cm apart, 1 m common part: d = 0.03, penalisation 0.95 ** (0.03 / 0.015).
    assert math.isclose(mv([0, 0, 1, 0], [0, 0.03, 1, 0.03]), 0.95**2, rel_tol=1e-9)


def test_matching_value_is_zero_beyond_the_segment_distance_threshold() -> None:
    # 8 cm apart: d / POINTDISTANCETOLERANCE = 5.33 > 5.
    assert mv([0, 0, 1, 0], [0, 0.08, 1, 0.08]) == 0.0
    # 7 cm apart: 4.67 <= 5, still matched.
    assert mv([0, 0, 1, 0], [0, 0.07, 1, 0.07]) > 0.0


def test_matching_value_averages_the_two_projections() -> None:
    # s2 is 2 m long, rotated 0.02 rad, crossing s1 (1 m) in its middle: l1 = 1 (s2 covers s1),
    # l2 = the projection of s1 on s2's line, 1 m * cos(0.02); they cross, so no penalty.
    a = 0.02
    s2 = [0.5 - math.cos(a), -math.sin(a), 0.5 + math.cos(a), math.sin(a)]
    assert math.isclose(mv([0, 0, 1, 0], s2), (1.0 + math.cos(a)) / 2, rel_tol=1e-9)


def test_intersection_includes_touching_and_excludes_disjoint() -> None:
    assert segments_intersect(np.array([0, 0, 1, 0.0]), np.array([1, 0, 1, 1.0]))
    assert segments_intersect(np.array([0, 0, 2, 2.0]), np.array([0, 2, 2, 0.0]))
    assert not segments_intersect(np.array([0, 0, 1, 0.0]), np.array([2, 0, 3, 0.0]))
    assert not segments_intersect(np.array([0, 0, 1, 0.0]), np.array([0, 1, 1, 1.0]))


@given(transforms, transforms)
def test_compose_then_inverse_is_identity(a: Transform2D, b: Transform2D) -> None:
    c = a.compose(b).compose(b.inverse()).compose(a.inverse())
    assert abs(c.x) < 1e-6 and abs(c.y) < 1e-6 and abs(wrap_angle(c.theta)) < 1e-9


@given(transforms, st.lists(st.tuples(coord, coord, coord, coord), min_size=1, max_size=5))
@settings(max_examples=50)
def test_rigid_transforms_keep_distances_and_matching_values(t: Transform2D, rows: list) -> None:
    seg = np.array(rows, dtype=np.float64)
    moved = t.apply(seg)
    np.testing.assert_allclose(
        np.hypot(moved[:, 2] - moved[:, 0], moved[:, 3] - moved[:, 1]),
        np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]),
        atol=1e-9,
    )
    batch = transform_segments_batch(seg, t.as_array()[None, :])[0]
    np.testing.assert_allclose(batch, moved, atol=1e-9)


@given(transforms, st.floats(0.1, 5.0), st.floats(-0.05, 0.05), st.floats(-1.0, 1.0))
@settings(max_examples=100)
def test_matching_value_is_invariant_under_rigid_motion(
    t: Transform2D, length: float, offset: float, shift: float
) -> None:
    s1 = np.array([0.0, 0.0, length, 0.0])
    s2 = np.array([shift, offset, shift + length, offset])
    before = mv(s1.tolist(), s2.tolist())
    after = mv(t.apply(s1[None])[0].tolist(), t.apply(s2[None])[0].tolist())
    assert math.isclose(before, after, rel_tol=1e-6, abs_tol=1e-9)
    assert 0.0 <= before <= length + 1e-9


@given(st.floats(-10, 10), st.floats(-10, 10))
def test_point_segment_distance_is_zero_on_the_segment_and_positive_off_it(x: float, y: float) -> None:
    seg = np.array([0.0, 0.0, 1.0, 0.0])
    d = float(point_segment_distance(np.array([x, y]), seg))
    expected = math.hypot(x - min(max(x, 0.0), 1.0), y)
    assert math.isclose(d, expected, abs_tol=1e-9)


@pytest.mark.slow  # a fuzz test
@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True) | st.integers(-40, 40).map(lambda k: k * math.pi))
def test_the_scalar_wrap_is_the_array_wrap_bit_for_bit(a: float) -> None:
    with np.errstate(invalid="ignore"):
        expected = float(wrap_angle(a))
    got = wrap_scalar(a)
    assert (math.isnan(got) and math.isnan(expected)) or (
        got == expected and math.copysign(1, got) == math.copysign(1, expected)
    )
