"""The correlative window's support: where a scan's walls fall on the reference's, over a window."""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core.correlative import window_support
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.tracking import ReferenceMap, sample_segments

# a corridor 20 m long and 2 m wide, closed at its far end, with a doorway's jambs at x = 7
ROOM = np.array(
    [
        [0.0, -1.0, 6.5, -1.0],
        [7.5, -1.0, 20.0, -1.0],
        [20.0, -1.0, 20.0, 1.0],
        [20.0, 1.0, 0.0, 1.0],
        [6.5, -1.0, 6.5, -2.0],
        [7.5, -2.0, 7.5, -1.0],
    ]
)


def _reference() -> ReferenceMap:
    reference = ReferenceMap(0.05)
    reference.insert(sample_segments(ROOM, 0.05))
    return reference


def test_the_best_supported_position_is_where_the_scan_was_taken_down_a_corridor() -> None:
    # the scan sees the corridor from x = 5: 2.5 m along it from the window's centre at x = 2.5,
    # beyond registration's reach, where only the doorway and the far wall say where it is
    truth = Transform2D(5.0, 0.0, 0.0)
    scan = sample_segments(truth.inverse().apply(ROOM), 0.05)
    positions, support = window_support(_reference(), scan, Transform2D(2.5, 0.0, 0.0), 3.0, 0.25, 0.25)
    best = positions[int(np.argmax(support))]
    # (a lookup cell is 0.25 m wide, and neighbours count: the best lies within two cells, well within
    # the 1 m registration reaches from it)
    assert math.hypot(best[0] - 5.0, best[1]) <= 0.5, f"best supported at {best}, support {support.max():.1f} m"
    assert support.max() > 0.9 * scan.length


def test_a_window_a_broken_clock_makes_endless_is_only_as_large_as_the_reference() -> None:
    # a stamp 4e9 s after the last makes constant velocity's window endless: it is searched where
    # the scan can overlap the reference, not allocated over the clock's guess
    scan = sample_segments(ROOM, 0.05)
    positions, support = window_support(_reference(), scan, Transform2D(0.0, 0.0, 0.0), math.inf, 0.25, 0.25)
    assert 0 < len(positions) < 100_000
    best = positions[int(np.argmax(support))]
    assert math.hypot(best[0], best[1]) <= 0.5, f"best supported at {best}"
