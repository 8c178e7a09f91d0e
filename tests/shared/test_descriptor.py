"""The cheap descriptor that ranks far candidates (fleetmap.shared.core.descriptor)."""

from __future__ import annotations

import itertools
import math

import numpy as np
from fleetmap.shared.core.descriptor import pairwise_histogram, similarity
from fleetmap.shared.core.geometry import Array, Transform2D

STEP, REACH = 0.5, 12.0


def _walls(width: float, start: float = 0.0) -> Array:
    """A 12 m stretch of a corridor or hall ``width`` wide from x = ``start`` on: two long walls
    broken by doors, each door with its jambs, and the end wall."""
    walls = [[12.0, 0.0, 12.0, width]]
    for y, doors in ((0.0, (2.0, 7.0)), (width, (4.5, 9.5))):
        edge = start
        for door in doors:
            if door + 1.0 <= start:
                continue
            walls.append([edge, y, door, y])
            jamb = -0.3 if y == 0.0 else width + 0.3
            walls += [[door, y, door, jamb], [door + 1.0, y, door + 1.0, jamb]]
            edge = door + 1.0
        walls.append([edge, y, 12.0, y])
    return np.asarray(walls, dtype=np.float64)


def _seen_again(walls: Array, seed: int) -> Array:
    """The same walls as another robot's submap holds them: in another frame, each wall in pieces,
    its ends a centimetre or two off."""
    rng = np.random.default_rng(seed)
    pieces = []
    for x1, y1, x2, y2 in walls:
        cuts = np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0.1, 0.9, size=int(rng.integers(0, 3)))]))
        for u, v in itertools.pairwise(cuts):
            pieces.append([x1 + u * (x2 - x1), y1 + u * (y2 - y1), x1 + v * (x2 - x1), y1 + v * (y2 - y1)])
    out = np.asarray(pieces) + rng.normal(0.0, 0.015, size=(len(pieces), 4))
    frame = Transform2D(5.0, -3.0, 0.7)
    return np.hstack([frame.apply_points(out[:, :2]), frame.apply_points(out[:, 2:])])


def test_a_map_moved_and_turned_has_the_same_descriptor() -> None:
    walls = _walls(2.0)
    frame = Transform2D(-7.5, 3.2, 2.4)
    moved = np.hstack([frame.apply_points(walls[:, :2]), frame.apply_points(walls[:, 2:])])
    there, here = pairwise_histogram(moved, STEP, REACH), pairwise_histogram(walls, STEP, REACH)
    np.testing.assert_allclose(there, here, atol=1e-9)
    assert similarity(there, here) > 1 - 1e-9


def test_a_corridor_seen_twice_is_more_alike_than_a_hall_whose_walls_run_the_same_two_ways() -> None:
    # In a building whose walls all run two ways (aces), every submap has the same directions:
    # a histogram of directions ranked the submaps that overlap a robot's no better than chance.
    # How far apart the walls lie tells a 2 m corridor from a 6 m hall.
    corridor = pairwise_histogram(_walls(2.0), STEP, REACH)
    for seed in range(5):
        again = pairwise_histogram(_seen_again(_walls(2.0, start=3.0), seed), STEP, REACH)
        for width in (3.5, 6.0):
            hall = pairwise_histogram(_seen_again(_walls(width), seed + 10), STEP, REACH)
            assert similarity(corridor, again) > similarity(corridor, hall) + 0.05, (seed, width)


def test_fewer_than_two_walls_have_an_empty_descriptor_and_a_map_of_thousands_has_a_whole_one() -> None:
    assert not pairwise_histogram(np.zeros((0, 4)), STEP, REACH).any()
    assert not pairwise_histogram(np.array([[0.0, 0.0, 1.0, 0.0]]), STEP, REACH).any()
    rng = np.random.default_rng(1)
    many = np.hstack([rng.uniform(0, 80, (5000, 2)), rng.uniform(0, 80, (5000, 2))])
    h = pairwise_histogram(many, STEP, REACH)
    assert h.shape == (4 * math.ceil(REACH / STEP),) and math.isclose(float(np.linalg.norm(h)), 1.0)
