"""The grid score's inner loop, compiled: every candidate's sample points looked up in a map's code grid.

Ranking the candidates of two large maps (:func:`fleetmap.shared.core.mapgrid.ranking_scores`)
looks up tens of millions of points: every candidate transformation of the paper's heuristics
times the samples along the other map's walls. In numpy that is a dozen passes over arrays of a
million points a chunk (move, clip, cell number, layer, gather, sum), and it was half the time of
a pose-free integration between submaps (mit-csail cut in 8: docs/decisions/030). One compiled
loop (Numba) does the same arithmetic, in the same precision and order, in one pass: the scores
are the same to the bit.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
call, so a process that never ranks maps never pays for it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array


def _build() -> Callable[..., None]:
    import numba

    @numba.njit(cache=True, nogil=True)
    def scores(code, x, y, direction, turns, cos, sin, starts, order, move_x, move_y, frame, out):
        ox, oy, res, period, channels, nx, ny = frame
        n = len(x)
        px = np.empty(n, np.float32)
        py = np.empty(n, np.float32)
        layer = np.empty(n, np.int64)
        last_i, last_j = np.float32(nx - 1), np.float32(ny - 1)
        plane = np.int64(nx) * np.int64(ny)
        for k in range(len(turns)):
            th = turns[k]
            c, sn = cos[k], sin[k]
            for p in range(n):
                px[p] = np.float32((c * x[p] - sn * y[p] - ox) / res + 1.0)
                py[p] = np.float32((sn * x[p] + c * y[p] - oy) / res + 1.0)
                layer[p] = (np.int64(np.floor((direction[p] + th) % period / period * channels)) % channels) * plane
            for r in range(starts[k], starts[k + 1]):
                i = order[r]
                mx, my = move_x[i], move_y[i]
                total = 0
                for p in range(n):
                    # clipped, then truncated: the floor of the clipped coordinate (never negative)
                    ci = min(max(px[p] + mx, np.float32(0.0)), last_i)
                    cj = min(max(py[p] + my, np.float32(0.0)), last_j)
                    total += code[layer[p] + np.int64(ci) * ny + np.int64(cj)]
                out[i] = total

    return scores


_scores = Compiled(_build)


def code_sums(
    code: Array, points: Array, direction: Array, t: Array, rotation_step: float, frame: tuple[float, ...]
) -> Array:
    """For each transformation of ``t`` (rows ``[x, y, theta]``, its rotation rounded to
    ``rotation_step``): the sum of the code grid ``code`` (``(CHANNELS, nx, ny)``, int8) at ``points``
    (their wall ``direction`` choosing the layer) so moved. ``frame``: the grid's ``(origin x,
    origin y, resolution, period of a direction, CHANNELS)``; cell coordinates are clipped into the
    grid (its border cells, one deep, are all zero). Integers: exact.

    The arithmetic is the numpy loop's it replaced, so the scores are that loop's to the bit: the
    layer as :func:`fleetmap.shared.core.mapgrid._channel` takes it, cosines and sines from numpy,
    cell coordinates in single precision (a ten-thousandth of a cell on a grid a thousand cells
    wide). The points of each rotation group are turned once."""
    out = np.zeros(len(t), np.int64)
    if len(t) == 0 or len(points) == 0:
        return out
    ox, oy, res, period, channels = frame
    q = np.round(t[:, 2] / rotation_step).astype(np.int64)
    groups, inverse = np.unique(q, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind="stable")
    starts = np.searchsorted(inverse.ravel()[order], np.arange(len(groups) + 1))
    nx, ny = code.shape[1:]
    turns = groups.astype(np.float64) * rotation_step
    _scores(
        code.reshape(-1),
        np.ascontiguousarray(points[:, 0], dtype=np.float64),
        np.ascontiguousarray(points[:, 1], dtype=np.float64),
        np.ascontiguousarray(direction, dtype=np.float64),
        turns,
        np.cos(turns),
        np.sin(turns),
        starts.astype(np.int64),
        order.astype(np.int64),
        (t[:, 0] / res).astype(np.float32),
        (t[:, 1] / res).astype(np.float32),
        (float(ox), float(oy), float(res), float(period), int(channels), int(nx), int(ny)),
        out,
    )
    return out
