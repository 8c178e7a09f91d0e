"""Map simplification: one segment per stretch of wall, nothing else changed."""

from __future__ import annotations

import numpy as np
from fleetmap.shared.core.geometry import lengths, orientations
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.simplify import simplify


def _noisy_wall(rng: np.random.Generator, x0: float, x1: float, y: float, piece: float = 0.12) -> np.ndarray:
    """A wall along +x seen as short noisy pieces (1 cm noise), as a real scan cuts it."""
    xs = np.arange(x0, x1, piece)
    ends = np.column_stack([xs, np.minimum(xs + piece, x1)])
    noise = rng.normal(0.0, 0.01, size=(len(xs), 2))
    return np.column_stack([ends[:, 0], y + noise[:, 0], ends[:, 1], y + noise[:, 1]])


def test_a_wall_seen_many_times_in_pieces_becomes_one_segment() -> None:
    rng = np.random.default_rng(0)
    # Three passes over the same 6 m wall, each cut into 12 cm pieces, plus a long segment of it.
    copies = [_noisy_wall(rng, 0.0, 6.0, 2.0) for _ in range(3)] + [np.array([[0.5, 2.0, 4.0, 2.01]])]
    m = SegmentMap(np.vstack(copies), oriented=True)
    out = simplify(m)
    assert len(m) > 150 and len(out) == 1
    (x1, y1, x2, y2) = out.segments[0]
    assert abs(x1 - 0.0) < 0.05 and abs(x2 - 6.0) < 0.05 and abs(y1 - 2.0) < 0.02 and abs(y2 - 2.0) < 0.02
    # The wall keeps its direction (free space on the same side).
    assert abs(orientations(out.segments)[0]) < 0.01


def test_separate_walls_doors_and_facing_sides_are_kept_apart() -> None:
    seg = np.array(
        [
            [0.0, 0.0, 2.0, 0.0],  # a wall ...
            [3.0, 0.0, 5.0, 0.0],  # ... a 1 m door, the wall goes on
            [0.0, 0.25, 5.0, 0.25],  # a parallel wall 25 cm away
            [5.0, -0.01, 0.0, -0.01],  # the back of the first wall (seen from the other side)
            [2.0, 1.0, 2.0, 3.0],  # a perpendicular wall
        ]
    )
    out = simplify(SegmentMap(seg, oriented=True))
    assert len(out) == len(seg)
    assert np.isclose(lengths(out.segments).sum(), lengths(seg).sum(), atol=0.02)


def test_small_gaps_are_bridged_and_viewpoints_kept() -> None:
    seg = np.array([[0.0, 0.0, 1.0, 0.0], [1.2, 0.0, 2.0, 0.0]])
    m = SegmentMap(seg, oriented=True, extras={"viewpoints": [[0.0, 1.0, 0.0, -1.0, 1.0]]})
    out = simplify(m, gap=0.3)
    assert len(out) == 1 and np.isclose(lengths(out.segments)[0], 2.0, atol=0.01)
    assert out.extras == m.extras
    assert len(simplify(m, gap=0.1)) == 2
