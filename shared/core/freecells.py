"""The free grid's march, compiled: the cells along every bearing of every viewpoint up to its wall.

A map's index for the grid score (:func:`fleetmap.shared.core.mapgrid.free_grid`) marks the cells
each viewpoint saw free: along each of its bearings, a point every 0.7 cell up to the wall less a
margin. The merger indexes every new version of a submap; in numpy that was, for each viewpoint,
a dozen passes over a few thousand points (owner, position, reach, angle, cell), and building the
indexes was a fifth of a live 16-robot merger's time (decision record 073). One compiled loop
(Numba) walks the bearings of all viewpoints in turn with the same arithmetic, the cosines and
sines from numpy: the same cells.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
call (:mod:`fleetmap.shared.core.compiled`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array


def _build() -> Callable[..., None]:
    # one function, calling no other built here (:mod:`fleetmap.shared.core.compiled`)
    import numba

    @numba.njit(cache=True, nogil=True)
    def mark(x, y, reach, count, cos, sin, step, frame, free):
        ox, oy, res, nx, ny = frame
        for v in range(len(x)):
            for b in range(reach.shape[1]):
                far, c, s = reach[v, b], cos[v, b], sin[v, b]
                for k in range(count[v, b]):
                    r = min((np.float64(k) + 0.5) * step, far)
                    i = np.int64(np.floor((x[v] + r * c - ox) / res))
                    j = np.int64(np.floor((y[v] + r * s - oy) / res))
                    if 0 <= i < nx and 0 <= j < ny:
                        free[i * ny + j] = True

    return mark


_mark = Compiled(_build)


def mark_free(
    x: Array, y: Array, reach: Array, count: Array, angle: Array, step: float, origin: Array, resolution: float,
    free: Array,
) -> None:  # fmt: skip
    """Mark in ``free`` (bool, C-ordered ``(nx, ny)``) the cells of the points ``(k + 0.5) * step``
    (at most ``reach[v, b]``) for ``k`` below ``count[v, b]`` along bearing ``angle[v, b]`` from
    viewpoint ``(x[v], y[v])``; a cell ``(i, j)`` covers ``origin + ([i, i+1), [j, j+1)) * resolution``."""
    if len(x) == 0:
        return
    nx, ny = free.shape
    _mark(
        np.ascontiguousarray(x, dtype=np.float64),
        np.ascontiguousarray(y, dtype=np.float64),
        np.ascontiguousarray(reach, dtype=np.float64),
        np.ascontiguousarray(count, dtype=np.int64),
        np.cos(angle),
        np.sin(angle),
        float(step),
        (float(origin[0]), float(origin[1]), float(resolution), int(nx), int(ny)),
        free.reshape(-1),
    )
