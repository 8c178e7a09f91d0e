"""The grid score's wall lookups, compiled: one map's wall samples, moved, on another's grids.

:func:`fleetmap.shared.core.mapgrid.grid_scores` moves the samples along one map's walls by each
transformation and sums the wall length that lands on the other's walls (a hit cell of the wall's
direction layer) and in its seen free space. The merger asks it of one transformation at a time,
pair after pair of submaps, to judge a join (:meth:`fleetmap.merger.pairs.PairJudge._look`): a
live fleet of 16 robots asked it 30,436 times in 28 steps, and its numpy passes (move, cell,
layer, gather, sum, each over a few hundred points) were 54 % of the merger's time there
(decision record 073). One compiled loop (Numba) does the same arithmetic point by point, with
the cosines and sines from numpy; the lengths are summed in the points' order, where numpy's
matrix product summed them in its own, so a sum may differ in its last bit.

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
    def sums(hits, free, points, direction, weight, free_weight, t, cos, sin, frame, hit_out, free_out):
        ox, oy, res, period, channels, nx, ny, has_free = frame
        plane = np.int64(nx) * np.int64(ny)
        for k in range(t.shape[0]):
            c, sn, tx, ty, th = cos[k], sin[k], t[k, 0], t[k, 1], t[k, 2]
            hit = 0.0
            seen = 0.0
            for p in range(points.shape[0]):
                x, y = points[p, 0], points[p, 1]
                i = np.int64(np.floor((c * x - sn * y + tx - ox) / res))
                j = np.int64(np.floor((sn * x + c * y + ty - oy) / res))
                if i < 0 or j < 0 or i >= nx or j >= ny:
                    continue
                layer = np.int64(np.floor((direction[p] + th) % period / period * channels)) % channels
                cell = i * ny + j
                if hits[layer * plane + cell]:
                    hit += weight[p]
                elif has_free and free[cell]:
                    seen += free_weight[p]
            hit_out[k] = hit
            free_out[k] = seen

    return sums


_sums = Compiled(_build)


def wall_sums(
    hits: Array,
    free: Array,
    points: Array,
    direction: Array,
    weight: Array,
    free_weight: Array,
    t: Array,
    frame: tuple[float, float, float, float, int, bool],
) -> tuple[Array, Array]:
    """For each transformation of ``t`` (rows ``[x, y, theta]``): the ``weight`` of the ``points``
    so moved that fall on a hit cell of ``hits`` (``(CHANNELS, nx, ny)`` bool, the layer of the
    point's wall ``direction`` turned with it), and the ``free_weight`` of those that do not and
    fall on a cell of ``free`` (``(nx, ny)`` bool). ``frame``: the grids' ``(origin x, origin y,
    resolution, period of a direction, CHANNELS, whether free counts)``; points off the grids
    count in neither."""
    t = np.ascontiguousarray(t, dtype=np.float64).reshape(-1, 3)
    hit_out, free_out = np.zeros(len(t)), np.zeros(len(t))
    if len(t) == 0 or len(points) == 0:
        return hit_out, free_out
    ox, oy, res, period, channels, has_free = frame
    nx, ny = hits.shape[1:]
    _sums(
        np.ascontiguousarray(hits, dtype=np.bool_).reshape(-1),
        np.ascontiguousarray(free, dtype=np.bool_).reshape(-1),
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(direction, dtype=np.float64),
        np.ascontiguousarray(weight, dtype=np.float64),
        np.ascontiguousarray(free_weight, dtype=np.float64),
        t,
        np.cos(t[:, 2]),
        np.sin(t[:, 2]),
        (float(ox), float(oy), float(res), float(period), int(channels), int(nx), int(ny), bool(has_free)),
        hit_out,
        free_out,
    )
    return hit_out, free_out
