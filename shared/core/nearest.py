"""The nearest of a submap's registration cells to each scan point, compiled.

Registration (:func:`fleetmap.shared.core.tracking.register`) matches every scan point to the
nearest cell of the submap's grid within the stage's radius, a dozen times a scan. A KD-tree
(``scipy.spatial.cKDTree``) answered it, with numpy round it to mark the cells that have no side;
it was the largest single cost of tracking a real log (mit-csail: 4.5 of 33 s). The cells here
are filed by buckets of :data:`BUCKET_CELLS` cells (a sort and a count), and one compiled
loop (Numba) searches each point's bucket, then the ring of buckets round it, then the next, until
no bucket not searched can hold a nearer cell: the same cell the KD-tree found (the same squared
distance, strictly within the radius), found in a few buckets.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
query (:mod:`fleetmap.shared.core.compiled`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array

BUCKET_CELLS = 4
"""A bucket's side, in cells of the grid the points were averaged in: most scan points lie within
a cell or two of their wall, found in the first ring."""
MAX_BUCKETS = 1 << 22
"""Buckets at most: points spread wider get wider buckets."""


def _build() -> Callable[..., None]:
    import numba

    @numba.njit(cache=True, nogil=True)
    def nearest(px, py, order, starts, frame, valid, qx, qy, radius, index, distance):
        x0, y0, side, nx, ny = frame
        nx, ny = np.int64(nx), np.int64(ny)
        bound = radius * radius
        rings = np.int64(math.ceil(radius / side)) + 1
        for q in range(len(qx)):
            x, y = qx[q], qy[q]
            index[q] = -1
            distance[q] = np.inf
            if not (np.isfinite(x) and np.isfinite(y)):
                continue
            u, v = (x - x0) / side, (y - y0) / side
            if u < -rings or v < -rings or u > nx + rings or v > ny + rings:
                continue  # farther than the radius from every bucket
            i, j = np.int64(math.floor(u)), np.int64(math.floor(v))
            best, found = np.inf, np.int64(-1)
            for d in range(rings + 1):
                # what lies beyond ring d - 1 is at least (d - 1) sides away: stop once nearer
                if d > 0 and (best <= ((d - 1) * side) ** 2 or ((d - 1) * side) ** 2 >= bound):
                    break
                for a in range(i - d, i + d + 1):
                    if a < 0 or a >= nx:
                        continue
                    edge = a == i - d or a == i + d
                    step = 1 if edge else 2 * d
                    b = j - d
                    while b <= j + d:
                        if 0 <= b < ny:
                            k = a * ny + b
                            for r in range(starts[k], starts[k + 1]):
                                p = order[r]
                                dx, dy = px[p] - x, py[p] - y
                                d2 = dx * dx + dy * dy
                                if d2 < best or (d2 == best and p < found):
                                    best, found = d2, p
                        b += step
            if found >= 0 and best < bound:
                distance[q] = math.sqrt(best)
                index[q] = found if valid[found] else -1

    return nearest


_nearest = Compiled(_build)


class CellIndex:
    """Points filed for nearest-neighbour queries within a radius (:meth:`query`)."""

    def __init__(self, points: Array, valid: Array, cell: float) -> None:
        self._px = np.ascontiguousarray(points[:, 0], dtype=np.float64)
        self._py = np.ascontiguousarray(points[:, 1], dtype=np.float64)
        self._valid = np.ascontiguousarray(valid, dtype=np.bool_)
        finite = np.isfinite(self._px) & np.isfinite(self._py)
        side = BUCKET_CELLS * cell
        if finite.any():
            low = np.array([self._px[finite].min(), self._py[finite].min()])
            high = np.array([self._px[finite].max(), self._py[finite].max()])
        else:
            low = high = np.zeros(2)
        while math.prod(int((h - lo) // side) + 1 for h, lo in zip(high, low, strict=True)) > MAX_BUCKETS:
            side *= 2.0
        nx, ny = (int((h - lo) // side) + 1 for h, lo in zip(high, low, strict=True))
        keep = np.flatnonzero(finite)
        i = np.floor((self._px[keep] - low[0]) / side).astype(np.int64).clip(0, nx - 1)
        j = np.floor((self._py[keep] - low[1]) / side).astype(np.int64).clip(0, ny - 1)
        bucket = i * ny + j
        self._order = keep[np.argsort(bucket, kind="stable")].astype(np.int64)
        self._starts = np.zeros(nx * ny + 1, dtype=np.int64)
        np.cumsum(np.bincount(bucket, minlength=nx * ny), out=self._starts[1:])
        self._frame = (float(low[0]), float(low[1]), float(side), float(nx), float(ny))

    def query(self, points: Array, radius: float) -> tuple[Array, Array]:
        """For each point, the nearest filed point strictly within ``radius`` (its index; -1 where
        there is none, or where the nearest is not valid) and its distance (inf where none)."""
        q = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        index = np.full(len(q), -1, dtype=np.int64)
        distance = np.full(len(q), math.inf)
        if len(q) and len(self._order):
            _nearest(
                self._px,
                self._py,
                self._order,
                self._starts,
                self._frame,
                self._valid,
                np.ascontiguousarray(q[:, 0]),
                np.ascontiguousarray(q[:, 1]),
                float(radius),
                index,
                distance,
            )
        return index, distance
