"""A submap's walls kept as one segment per stretch of wall, as its scans come in (pure core).

:func:`fleetmap.shared.core.simplify.simplify` turns a finished partial map into one segment per
covered stretch of wall; a robot's submap needs the same while it grows, several times a second,
and simplifying all its scans' segments again each time costs tens of milliseconds. A
:class:`WallMap` does it incrementally: each new segment joins the wall it lies on (both ends
within ``tolerance`` of the wall's fitted line, directions within ``angle_tolerance`` (a short
segment, whose direction is noise, only within ``min_short_cos``), the same side facing the
sensor, and its extent within ``gap`` of the wall's along the line), the wall's line is fitted
again from its accumulated moments, and walls that the new segment chains together become one.
A segment that joins no wall starts one. The tests and the fit are :func:`simplify`'s.

A large map (a fleet's global map, hundreds of submaps) keeps its walls in a grid of ``cell``
metres: a segment is tested against the walls registered in the cells it touches, not all of them.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core.geometry import Array

_GROW = 64

GRID_FROM = 512
"""With more walls than this, a segment is tested only against the walls of the grid cells it touches."""

GRID_BATCH = 16
"""... taken this many segments at a time: the walls tested are those near any of them, so a
batch of segments spread over the whole map (a submap of thousands of walls) is not tested
against every wall at once (the cost and memory of segments times walls)."""


class WallMap:
    """Walls as fitted lines with extents; :meth:`add` segments, :attr:`segments` to read."""

    def __init__(
        self,
        tolerance: float = 0.05,
        angle_tolerance: float = 0.1,
        gap: float = 0.3,
        short_length: float = 0.5,
        min_short_cos: float = 0.3,
        oriented: bool = True,
        cell: float = 2.0,
    ) -> None:
        self.tolerance = tolerance
        self.cos_tolerance = math.cos(angle_tolerance)
        self.gap = gap
        self.short_length = short_length
        self.min_short_cos = min_short_cos
        self.oriented = oriented
        self._n = 0
        # per wall: moments (s0, s1x, s1y, s2xx, s2xy, s2yy), line (cx, cy, ux, uy), extent (lo, hi)
        self._moments = np.zeros((_GROW, 6))
        self._line = np.zeros((_GROW, 4))
        self._extent = np.zeros((_GROW, 2))
        self._alive = np.zeros(_GROW, dtype=bool)
        self.cell = cell
        self._grid: dict[tuple[int, int], set[int]] = {}
        self._cells: dict[int, list[tuple[int, int]]] = {}
        """The cells each wall is registered in."""

    def __len__(self) -> int:
        return int(self._alive[: self._n].sum())

    @property
    def segments(self) -> Array:
        """One segment per wall ``(w, 4)``, running along the wall's direction."""
        alive = np.flatnonzero(self._alive[: self._n])
        c = self._line[alive, 0:2]
        u = self._line[alive, 2:4]
        lo = self._extent[alive, 0:1]
        hi = self._extent[alive, 1:2]
        return np.hstack([c + lo * u, c + hi * u])

    def add(self, segments: Array, weights: Array | None = None) -> None:
        """Add segments ``(n, 4)`` in the map's frame, longest first (long walls set the lines).

        A wall's line is fitted to its segments by length; ``weights`` ``(n,)``, if given, multiply
        each segment's share (the information per metre on its offset,
        :func:`fleetmap.shared.core.kalman_fusion.offset_information`: the fit is then Ballesta et
        al.'s uncertainty-weighted fusion instead of the paper's unweighted Algorithm 5).

        Which walls each segment lies on is tested for all of them at once, against the walls as
        they were before; the segments of one scan do not overlap one another, so a wall one of
        them starts is not one another of them joins."""
        seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
        length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
        scale = np.ones(len(seg)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(len(seg))
        real = np.flatnonzero(length > 1e-9)
        if len(real) == 0:
            return
        seg, length, scale = seg[real], length[real], scale[real]
        hits = self._walls_for(seg, length)
        redirect: dict[int, int] = {}

        def current(k: int) -> int:
            while k in redirect:
                k = redirect[k]
            return k

        touched: dict[int, list[tuple[float, float]]] = {}
        for i in np.argsort(-length, kind="stable").tolist():
            ax, ay, bx, by = (float(v) for v in seg[i])
            joined: list[int] = []
            for k in hits[i].tolist():
                k = current(k)
                if k not in joined:
                    joined.append(k)
            if not joined:
                d = (seg[i, 2:4] - seg[i, 0:2]) / length[i]
                self._new_wall(seg[i, 0:2], seg[i, 2:4], d, float(length[i]), float(scale[i]))
                continue
            keep = joined[0]
            self._moments[keep] += _segment_moments(ax, ay, bx, by, float(length[i] * scale[i]))
            ends = touched.setdefault(keep, [])
            ends += [(ax, ay), (bx, by)]
            for other in joined[1:]:
                self._moments[keep] += self._moments[other]
                self._absorb_extent(keep, other)
                self._alive[other] = False
                self._register(other)  # out of the grid
                redirect[other] = keep
                ends += touched.pop(other, [])
        # each wall a segment joined is fitted again once, with the joined segments' ends
        for k, ends in touched.items():
            if self._alive[k]:
                self._refit(k, ends)

    # -- internals ---------------------------------------------------------------------------
    def _walls_for(self, seg: Array, length: Array) -> list[Array]:
        """For each segment, the walls it lies on, the longest first."""
        if self._n <= GRID_FROM:
            return self._walls_among(seg, length, np.flatnonzero(self._alive[: self._n]))
        out: list[Array] = []
        for b in range(0, len(seg), GRID_BATCH):
            part = seg[b : b + GRID_BATCH]
            near: set[int] = set()
            for cell in self._cells_of(part, self.tolerance):
                near |= self._grid.get(cell, set())
            out += self._walls_among(part, length[b : b + GRID_BATCH], np.array(sorted(near), dtype=np.int64))
        return out

    def _walls_among(self, seg: Array, length: Array, alive: Array) -> list[Array]:
        """For each segment, the walls among ``alive`` (ascending) it lies on, the longest first
        (ties in ``alive``'s order: the same for any ``alive`` that holds them)."""
        if len(alive) == 0:
            return [alive] * len(seg)
        cx, cy, ux, uy = (self._line[alive, j] for j in range(4))
        ax, ay, bx, by = (seg[:, j : j + 1] for j in range(4))
        dx = (bx - ax) / length[:, None]
        dy = (by - ay) / length[:, None]
        dot = dx * ux + dy * uy
        limit = np.where(length < self.short_length, self.min_short_cos, self.cos_tolerance)[:, None]
        aligned = (dot if self.oriented else np.abs(dot)) >= limit
        ax, ay, bx, by = ax - cx, ay - cy, bx - cx, by - cy
        near = (np.abs(ay * ux - ax * uy) <= self.tolerance) & (np.abs(by * ux - bx * uy) <= self.tolerance)
        ta = ax * ux + ay * uy
        tb = bx * ux + by * uy
        ext = self._extent[alive]
        chained = (np.minimum(ta, tb) <= ext[:, 1] + self.gap) & (np.maximum(ta, tb) >= ext[:, 0] - self.gap)
        hit = aligned & near & chained
        span = ext[:, 1] - ext[:, 0]
        order = np.argsort(-span, kind="stable")
        return [alive[order][row[order]] for row in hit]

    def _new_wall(self, a: Array, b: Array, d: Array, length: float, scale: float = 1.0) -> None:
        if self._n == len(self._alive):
            grow = len(self._alive)
            self._moments = np.vstack([self._moments, np.zeros((grow, 6))])
            self._line = np.vstack([self._line, np.zeros((grow, 4))])
            self._extent = np.vstack([self._extent, np.zeros((grow, 2))])
            self._alive = np.concatenate([self._alive, np.zeros(grow, dtype=bool)])
        k = self._n
        self._n += 1
        self._moments[k] = _segment_moments(float(a[0]), float(a[1]), float(b[0]), float(b[1]), length * scale)
        self._alive[k] = True
        self._line[k] = (a[0], a[1], d[0], d[1])
        self._extent[k] = (0.0, length)
        self._register(k)

    def _absorb_extent(self, keep: int, other: int) -> None:
        """Carry the other wall's ends into ``keep``'s extent (in ``keep``'s current line)."""
        c, u = self._line[keep, 0:2], self._line[keep, 2:4]
        oc, ou = self._line[other, 0:2], self._line[other, 2:4]
        for t in self._extent[other]:
            p = oc + t * ou
            self._stretch(keep, float((p - c) @ u))

    def _stretch(self, k: int, t: float) -> None:
        self._extent[k, 0] = min(self._extent[k, 0], t)
        self._extent[k, 1] = max(self._extent[k, 1], t)

    def _refit(self, k: int, extra: list[tuple[float, float]]) -> None:
        """Fit wall ``k``'s line again from its moments; its extent is its old ends and ``extra``
        points, projected on the new line."""
        ocx, ocy, oux, ouy = (float(v) for v in self._line[k])
        lo, hi = (float(v) for v in self._extent[k])
        ends = [(ocx + lo * oux, ocy + lo * ouy), (ocx + hi * oux, ocy + hi * ouy), *extra]
        s0, sx, sy, sxx, sxy, syy = (float(v) for v in self._moments[k])
        cx, cy = sx / s0, sy / s0
        vxx, vxy, vyy = sxx - s0 * cx * cx, sxy - s0 * cx * cy, syy - s0 * cy * cy
        half = 0.5 * (vxx - vyy)
        root = math.hypot(half, vxy)
        if vxx >= vyy:
            ux, uy = root + half, vxy
        else:
            ux, uy = vxy, root - half
        norm = math.hypot(ux, uy)
        if norm <= 1e-12:
            ux, uy = oux, ouy
        else:
            ux, uy = ux / norm, uy / norm
        if ux * oux + uy * ouy < 0:
            ux, uy = -ux, -uy  # keep the wall's direction (the side the sensor saw it from)
        t = [(px - cx) * ux + (py - cy) * uy for px, py in ends]
        self._line[k] = (cx, cy, ux, uy)
        self._extent[k] = (min(t), max(t))
        self._register(k)

    def _register(self, k: int) -> None:
        """(Re-)register wall ``k`` in the grid cells its extent, widened by the tests' reach, touches."""
        for cell in self._cells.pop(k, []):
            self._grid[cell].discard(k)
        if not self._alive[k]:
            return
        cx, cy, ux, uy = self._line[k].tolist()
        lo, hi = self._extent[k].tolist()
        cells = self._cells_of_one(cx + lo * ux, cy + lo * uy, cx + hi * ux, cy + hi * uy, self.gap + self.tolerance)
        for cell in cells:
            self._grid.setdefault(cell, set()).add(k)
        self._cells[k] = cells

    def _cells_of_one(self, ax: float, ay: float, bx: float, by: float, margin: float) -> list[tuple[int, int]]:
        """:meth:`_cells_of` of one segment, in plain floats (the same arithmetic, without numpy's
        cost per call: a wall is registered again every time a segment joins it)."""
        c = self.cell
        x0, x1 = math.floor((min(ax, bx) - margin) / c), math.floor((max(ax, bx) + margin) / c)
        y0, y1 = math.floor((min(ay, by) - margin) / c), math.floor((max(ay, by) + margin) / c)
        return [(i, j) for i in range(x0, x1 + 1) for j in range(y0, y1 + 1)]

    def _cells_of(self, seg: Array, margin: float) -> list[tuple[int, int]]:
        """The grid cells the segments' bounding boxes, widened by ``margin``, touch."""
        out: set[tuple[int, int]] = set()
        lo = np.floor((np.minimum(seg[:, 0:2], seg[:, 2:4]) - margin) / self.cell).astype(np.int64)
        hi = np.floor((np.maximum(seg[:, 0:2], seg[:, 2:4]) + margin) / self.cell).astype(np.int64)
        for (x0, y0), (x1, y1) in zip(lo.tolist(), hi.tolist(), strict=True):
            out.update((i, j) for i in range(x0, x1 + 1) for j in range(y0, y1 + 1))
        return sorted(out)


def _segment_moments(ax: float, ay: float, bx: float, by: float, weight: float) -> tuple[float, ...]:
    """A segment's share of a wall's line fit: its two ends weighted by ``weight`` (its length, times
    its information per metre where weighted), and its own spread along itself (weight / 12 times
    its direction's outer product), as in :func:`fleetmap.shared.core.simplify._fit`."""
    w = weight
    ex, ey = bx - ax, by - ay
    return (
        2.0 * w,
        w * (ax + bx),
        w * (ay + by),
        w * (ax * ax + bx * bx) + w / 12.0 * ex * ex,
        w * (ax * ay + bx * by) + w / 12.0 * ex * ey,
        w * (ay * ay + by * by) + w / 12.0 * ey * ey,
    )
