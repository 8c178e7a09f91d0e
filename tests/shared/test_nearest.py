"""The registration grid's nearest cell (shared/core/nearest.py) against a search of every cell."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleetmap.shared.core.nearest import CellIndex


def _every_cell(cells: np.ndarray, valid: np.ndarray, queries: np.ndarray, radius: float) -> np.ndarray:
    d2 = ((queries[:, None, :] - cells[None, :, :]) ** 2).sum(axis=2)
    best = d2.argmin(axis=1)
    found = d2[np.arange(len(queries)), best] < radius * radius
    return np.where(found & valid[best], best, -1)


@pytest.mark.parametrize("radius", [0.25, 0.5, 1.0, 3.0])
def test_each_point_gets_the_nearest_valid_cell_within_the_radius_as_a_search_of_every_cell_finds(radius):
    rng = np.random.default_rng(7)
    # walls of a room, averaged in 5 cm cells, and clutter; a tenth of the cells have no side
    wall = np.column_stack([rng.uniform(0, 12, 900), rng.choice([0.0, 8.0], 900) + rng.normal(0, 0.01, 900)])
    clutter = rng.uniform([0, 0], [12, 8], (300, 2))
    cells = np.vstack([wall, clutter])
    valid = rng.uniform(size=len(cells)) > 0.1
    # scan points near the walls, in the room, and well outside it
    queries = np.vstack([wall[:200] + rng.normal(0, 0.1, (200, 2)), rng.uniform([-5, -5], [17, 13], (800, 2))])
    index, distance = CellIndex(cells, valid, 0.05).query(queries, radius)
    assert np.array_equal(index, _every_cell(cells, valid, queries, radius))
    found = np.isfinite(distance)
    nearest = np.sqrt(((queries[:, None, :] - cells[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
    assert np.allclose(distance[found], nearest[found]) and np.all(nearest[~found] >= radius)
    assert 100 < found.sum() < len(queries)  # both kinds were asked


def test_a_point_that_is_not_a_number_or_an_empty_index_finds_nothing():
    index, distance = CellIndex(np.array([[0.0, 0.0], [1.0, 0.0]]), np.ones(2, bool), 0.05).query(
        np.array([[math.nan, 0.0], [0.9, 0.0], [math.inf, 0.0]]), 0.5
    )
    assert index.tolist() == [-1, 1, -1] and distance[1] == pytest.approx(0.1)
    index, _ = CellIndex(np.zeros((0, 2)), np.zeros(0, bool), 0.05).query(np.array([[0.0, 0.0]]), 1.0)
    assert index.tolist() == [-1]
