"""Ballesta et al.'s uncertainty-weighted fusion of one wall seen by two maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.kalman_fusion import fuse, offset_information, segment_estimate
from fleetmap.shared.core.walls import WallMap

WALL = np.array([0.0, 0.0, 4.0, 0.0])
"""The true wall, in the global frame."""
ALONG = np.column_stack([np.linspace(0.0, 4.0, 9), np.zeros(9)])
POINT_SIGMA, SPACING = 0.01, 0.05
MAPS = [
    # Each map's true pose and its pose covariance: one placed firmly, one loosely and far off.
    (Transform2D(-1.0, 2.0, 0.3), np.diag([0.01**2, 0.01**2, 0.002**2])),
    (Transform2D(9.0, -5.0, 2.0), np.diag([0.06**2, 0.06**2, 0.008**2])),
]


def off_wall(segments: np.ndarray) -> float:
    """Mean distance (m) of the true wall's points from the line of each segment ``(n, 4)``, averaged."""
    out = []
    for s in segments.reshape(-1, 4):
        u = (s[2:4] - s[0:2]) / math.hypot(*(s[2:4] - s[0:2]))
        out.append(np.mean(np.abs((ALONG - s[0:2]) @ np.array([-u[1], u[0]]))))
    return float(np.mean(out))


@pytest.mark.slow  # one of the fast suite's slowest (about 1 s): CI runs it with the slow ones
def test_kalman_fusion_of_two_noisy_copies_lands_closer_to_the_wall_than_either_and_than_unweighted() -> None:
    rng = np.random.default_rng(5)
    errors: dict[str, list[float]] = {k: [] for k in ("first", "second", "kalman", "unweighted", "weighted walls")}
    for _ in range(300):
        estimates, placed, weights = [], [], []
        for truth, covariance in MAPS:
            # The map saw the wall where it is (its fit a little off), and is placed a little off.
            local = truth.inverse().apply(WALL[None])[0]
            local[[1, 3]] += rng.normal(0.0, POINT_SIGMA / math.sqrt(4.0 / SPACING), 2)
            e = rng.multivariate_normal(np.zeros(3), covariance)
            pose = Transform2D(truth.x + e[0], truth.y + e[1], truth.theta + e[2])
            estimates.append(segment_estimate(local, pose, covariance, POINT_SIGMA, SPACING, centre=(2.0, 0.0)))
            placed.append(pose.apply(local[None])[0])
            weights.append(offset_information(local[None], pose, covariance, POINT_SIGMA, SPACING)[0])
        fused = fuse(*estimates)
        errors["first"].append(off_wall(placed[0]))
        errors["second"].append(off_wall(placed[1]))
        errors["kalman"].append(float(np.mean([abs(fused.distance(p)) for p in ALONG])))
        for name, w in (("unweighted", None), ("weighted walls", np.array(weights))):
            walls = WallMap(tolerance=0.5, gap=0.5)
            for k, segment in enumerate(placed):  # map by map, as a global map is built
                walls.add(segment[None], None if w is None else w[k : k + 1])
            assert len(walls) == 1  # the two copies are one wall
            errors[name].append(off_wall(walls.segments))
    mean = {k: float(np.mean(v)) for k, v in errors.items()}
    assert mean["kalman"] < mean["first"] < mean["second"], mean
    assert mean["kalman"] < 0.8 * mean["unweighted"], mean
    assert mean["weighted walls"] < 0.8 * mean["unweighted"], mean
    assert abs(mean["weighted walls"] - mean["kalman"]) < 0.2 * mean["kalman"], mean


def test_the_fused_covariance_is_smaller_than_either() -> None:
    a = segment_estimate(WALL, Transform2D(), np.diag([1e-4, 1e-4, 1e-6]), POINT_SIGMA, SPACING)
    b = segment_estimate(WALL, Transform2D(), np.diag([4e-4, 4e-4, 4e-6]), POINT_SIGMA, SPACING)
    f = fuse(a, b)
    assert f.covariance[1, 1] < min(a.covariance[1, 1], b.covariance[1, 1])
    # Eq. 8 for equal copies halves the variance.
    g = fuse(a, a)
    assert np.allclose(g.covariance, a.covariance / 2)
