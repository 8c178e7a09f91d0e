"""WallMap (fleetmap.shared.core.walls): a batch of segments is tested against the walls near it."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from fleetmap.shared.core import walls
from fleetmap.shared.core.walls import WallMap


def _strewn(n: int, seed: int) -> np.ndarray:
    """``n`` segments 0.2-3 m long strewn over 40 m by 40 m."""
    rng = np.random.default_rng(seed)
    start, heading = rng.uniform(-20.0, 20.0, (n, 2)), rng.uniform(0.0, 2 * np.pi, n)
    end = start + rng.uniform(0.2, 3.0, n)[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    return np.column_stack([start, end])


def test_a_large_batch_over_many_walls_takes_memory_for_the_walls_near_it_and_fuses_as_against_all(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # (about half a second) 1,000 segments over 1,500 walls: tested against every wall at once, the
    # segment-by-wall arrays took about 0.1 GB; the fused walls are the same either way
    first, second = _strewn(1500, 1), _strewn(1000, 2)
    near = WallMap(0.05)
    near.add(first)
    tracemalloc.start()
    near.add(second)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50e6, f"{peak / 1e6:.0f} MB"
    monkeypatch.setattr(walls, "GRID_FROM", 10**9)  # every wall tested against every segment
    every = WallMap(0.05)
    every.add(first)
    every.add(second)
    assert np.array_equal(near.segments, every.segments)
