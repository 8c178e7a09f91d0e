"""The occupancy grid's beam march, compiled: the cells every beam passes through, counted.

:func:`fleetmap.shared.io.occupancy.occupancy_grid` casts every placed scan's beams across the
grid: a point every half cell along each beam, each cell counted once per beam. A long log's beams
make a few hundred million points; in numpy that was a dozen passes over chunks of four million
(gather, add, floor, compare), and the largest part of what ``fleetmap map`` did after its last
scan (mit-csail: 4.4 of 17 s). One compiled loop (Numba) walks each beam in turn with the same
arithmetic and adds its count where the numpy passes did; the counts are whole numbers, so the
grid is the same to the bit.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
call, so a process that never draws a grid never pays for it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array


def _build() -> Callable[..., None]:
    import numba

    @numba.njit(cache=True, nogil=True)
    def march(start_x, start_y, step_x, step_y, count, weight, rows, cols, passes):
        for b in range(len(count)):
            last = np.int64(-1)
            for k in range(count[b]):
                x = start_x[b] + np.float64(k) * step_x[b]
                y = start_y[b] + np.float64(k) * step_y[b]
                col = np.int64(np.floor(x))
                row = np.int64(np.floor(y))
                flat = row * cols + col
                # a straight beam's points in one cell follow each other: the first counts
                if 0 <= row < rows and 0 <= col < cols and (k == 0 or flat != last):
                    passes[flat] += weight[b]
                last = flat

    return march


_march = Compiled(_build)


def beam_passes(start: Array, step: Array, count: Array, weight: Array, shape: tuple[int, int]) -> Array:
    """For each cell of a grid of ``shape`` (flat, row-major), the ``weight`` of the beams that pass
    through it: beam ``b`` is the points ``start[b] + k * step[b]`` for ``k`` below ``count[b]``, in
    cell units (x the column, y the row), and counts once in each cell its points fall in."""
    passes = np.zeros(shape[0] * shape[1], dtype=np.float64)
    if len(count) == 0:
        return passes
    _march(
        np.ascontiguousarray(start[:, 0], dtype=np.float64),
        np.ascontiguousarray(start[:, 1], dtype=np.float64),
        np.ascontiguousarray(step[:, 0], dtype=np.float64),
        np.ascontiguousarray(step[:, 1], dtype=np.float64),
        np.ascontiguousarray(count, dtype=np.int64),
        np.ascontiguousarray(weight, dtype=np.float64),
        int(shape[0]),
        int(shape[1]),
        passes,
    )
    return passes
