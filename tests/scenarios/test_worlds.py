"""The bundled worlds: the paper's Section V loop, an office floor, a repetitive warehouse."""

from __future__ import annotations

import numpy as np
import pytest
from fleetmap.scenarios.worlds import WORLDS, get_world
from fleetmap.shared.core.geometry import lengths
from fleetmap.shared.errors import ConfigError


def in_box(walls: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    mid = (walls[:, 0:2] + walls[:, 2:4]) / 2
    return (mid[:, 0] > x0) & (mid[:, 0] < x1) & (mid[:, 1] > y0) & (mid[:, 1] < y1)


@pytest.mark.parametrize("name", list(WORLDS))
def test_every_world_is_a_clean_read_only_segment_array(name: str) -> None:
    w = get_world(name)
    assert w.walls.dtype == np.float64 and w.walls.ndim == 2 and w.walls.shape[1] == 4 and len(w.walls) > 50
    assert np.isfinite(w.walls).all() and (lengths(w.walls) > 0.01).all()
    with pytest.raises(ValueError):
        w.walls[0, 0] = 1.0


def test_the_department_has_the_papers_three_environments() -> None:
    # Section V: a very scattered lab, a narrow hallway with rectilinear walls, a large hall.
    w = get_world("department").walls
    lab, hall = in_box(w, 0, 0, 8, 7), in_box(w, 15.9, -3.1, 26.1, 9.1)
    assert (lengths(w[lab]) < 1.0).sum() >= 40  # desks, boxes, chairs, a robot
    hallway = w[in_box(w, 8, 5.0, 16, 7.0) & (lengths(w) > 1.5)]
    assert lengths(hallway).max() >= 3.0 and np.allclose(hallway[:, 1], hallway[:, 3])  # straight, parallel
    assert hall.sum() <= 20 and lengths(w[hall]).sum() > 40  # few features, long walls


def test_the_warehouse_repeats_its_racks_but_is_not_symmetric() -> None:
    w = get_world("warehouse").walls
    long_walls = w[lengths(w) > 7.0]
    rack_faces = long_walls[np.isclose(long_walls[:, 0], long_walls[:, 2])]
    assert len(rack_faces) >= 16  # eight rows of racks, two faces each
    mirrored = w.copy()
    mirrored[:, [0, 2]] = 36.0 - w[:, [0, 2]]
    assert not np.allclose(np.sort(mirrored, axis=0), np.sort(w, axis=0))


def test_free_space_excludes_obstacles_and_the_outside() -> None:
    w = get_world("department")
    points = np.array([[4.0, 1.3], [12.0, 3.8], [4.6, 2.9], [30.0, 0.0], [12.0, 6.0]])
    assert w.inside(points).tolist() == [True, False, False, False, True]
    assert w.clearance(np.array([[12.0, 6.0]]))[0] == pytest.approx(0.8)
    assert w.crossing((12.0, 6.0), (12.0, 1.2)) is not None and w.crossing((8.5, 6.0), (15.0, 6.0)) is None


def test_an_unknown_world_is_refused_with_the_known_names() -> None:
    with pytest.raises(ConfigError, match=r"unknown world.*department, office, warehouse"):
        get_world("castle")
