"""Simulated buildings: floor plans made of line segments.

A world's walls are one ``(n, 4)`` float64 array of rows ``[x1, y1, x2, y2]`` in the world frame
(metres). Walls are plain segments: the laser sees either side, so their direction does not
matter. Besides its walls a world knows where a robot may be: inside its ``outline`` and outside
every closed obstacle (``solids``: desks, boxes, shelf rows, the block between two corridors).

Bundled worlds (``WORLDS``; :func:`get_world` looks one up by name):

- ``department``: the paper's Section V environment, a loop of about 40 m: a cluttered laboratory
  (desks, boxes, chairs, a robot: many short segments), a narrow hallway with long straight walls
  and a few door frames, and a large hall with long perpendicular walls and few features; a wider
  passage closes the loop back into the laboratory.
- ``office``: a corridor with rooms of different widths on both sides, doors at different places
  in each room, furniture, a kitchen and a meeting room.
- ``warehouse``: rows of pallet racks (repetitive: the hard case for wrong merges), irregular only
  in places: a loading dock with pallets on the floor at one end, offices at the other, a few bays
  with pallets sticking out and a shorter row.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from fleetmap.shared.core.geometry import Array, point_segment_distance, segments_intersect
from fleetmap.shared.errors import ConfigError


@dataclass(frozen=True, eq=False)
class World:
    """A floor plan: walls, and where a robot may be (inside ``outline``, outside ``solids``)."""

    name: str
    description: str
    walls: Array
    """``(n, 4)`` wall segments in the world frame (read-only)."""
    outline: Array
    """``(k, 2)`` polygon around the building's inside."""
    solids: tuple[Array, ...] = field(default=())
    """``(k, 2)`` polygons of closed obstacles no robot can enter."""

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the outline."""
        lo = self.outline.min(axis=0)
        hi = self.outline.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    @property
    def total_wall_length(self) -> float:
        w = self.walls
        return float(np.hypot(w[:, 2] - w[:, 0], w[:, 3] - w[:, 1]).sum())

    def inside(self, points: Array) -> Array:
        """Whether each point ``(..., 2)`` is inside the building and outside every obstacle."""
        p = np.asarray(points, dtype=np.float64)
        edges, starts = self._polygon_edges
        inside = _crossings(p, edges, starts) % 2 == 1  # (..., 1 + solids): the outline's, then each solid's
        return np.asarray(inside[..., 0] & ~inside[..., 1:].any(axis=-1))

    @functools.cached_property
    def _polygon_edges(self) -> tuple[Array, Array]:
        """The edges ``(e, 4)`` of the outline and of every solid, polygon after polygon, and where
        each polygon's begin: a warehouse's racks are tens of solids, and a point is checked against
        all of them at once."""
        polygons = (self.outline, *self.solids)
        edges = np.vstack([np.hstack([poly, np.roll(poly, -1, axis=0)]) for poly in polygons])
        starts = np.cumsum([0, *(len(poly) for poly in polygons[:-1])])
        return edges, starts

    def clearance(self, points: Array) -> Array:
        """Distance from each point ``(m, 2)`` to the nearest wall."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return point_segment_distance(p[:, None, :], self.walls[None, :, :]).min(axis=1)

    def crossing(self, a: tuple[float, float], b: tuple[float, float]) -> Array | None:
        """The first wall (a row of ``walls``) that the straight move from ``a`` to ``b`` crosses, if any."""
        move = np.array([a[0], a[1], b[0], b[1]], dtype=np.float64)
        hit = np.flatnonzero(segments_intersect(move[None, :], self.walls))
        return self.walls[hit[0]] if len(hit) else None


def _crossings(p: Array, edges: Array, starts: Array) -> Array:
    """For each point ``(..., 2)``: how many edges of each polygon (edges ``starts[j]`` up to the
    next start) a ray from it towards +x crosses (the even-odd rule: odd is inside that polygon)."""
    x, y = p[..., 0, None], p[..., 1, None]
    x1, y1, x2, y2 = edges[:, 0], edges[:, 1], edges[:, 2], edges[:, 3]
    straddles = (y1 > y) != (y2 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
    hits = (straddles & (x < x_cross)).astype(np.int64)
    return np.add.reduceat(hits, starts, axis=-1)


class FloorPlan:
    """Builds a :class:`World` from walls, polylines and boxes (the worlds' drawing board)."""

    def __init__(self) -> None:
        self._walls: list[tuple[float, float, float, float]] = []
        self._solids: list[Array] = []

    def polyline(self, *points: tuple[float, float]) -> None:
        """Walls joining consecutive points."""
        for (x1, y1), (x2, y2) in itertools.pairwise(points):
            self._walls.append((x1, y1, x2, y2))

    def box(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """A closed axis-aligned obstacle (a desk, a box, a shelf) with four walls."""
        self.polygon(((x0, y0), (x1, y0), (x1, y1), (x0, y1)))

    def rotated_box(self, cx: float, cy: float, width: float, depth: float, angle: float) -> None:
        """A closed obstacle of ``width`` x ``depth`` centred on ``(cx, cy)``, turned by ``angle`` (rad)."""
        c, s = math.cos(angle), math.sin(angle)
        corners = [(-width / 2, -depth / 2), (width / 2, -depth / 2), (width / 2, depth / 2), (-width / 2, depth / 2)]
        self.polygon(tuple((cx + c * u - s * v, cy + s * u + c * v) for u, v in corners))

    def polygon(self, points: tuple[tuple[float, float], ...]) -> None:
        """A closed obstacle with one wall per side."""
        self.polyline(*points, points[0])
        self.solid(points)

    def solid(self, points: tuple[tuple[float, float], ...]) -> None:
        """A region no robot can enter, whose walls are drawn elsewhere (the block between corridors)."""
        self._solids.append(np.array(points, dtype=np.float64))

    def build(self, name: str, description: str, outline: tuple[tuple[float, float], ...]) -> World:
        walls = np.array(self._walls, dtype=np.float64)
        walls.flags.writeable = False
        outline_arr = np.array(outline, dtype=np.float64)
        outline_arr.flags.writeable = False
        for s in self._solids:
            s.flags.writeable = False
        return World(name, description, walls, outline_arr, tuple(self._solids))


def _wall_with_recesses(
    plan: FloorPlan, y: float, x0: float, x1: float, recesses: list[tuple[float, float]], depth: float
) -> None:
    """A straight wall along y from x0 to x1 with door frames: recesses ``(start, end)`` ``depth`` deep."""
    points = [(x0, y)]
    for a, b in recesses:
        points += [(a, y), (a, y + depth), (b, y + depth), (b, y)]
    points.append((x1, y))
    plan.polyline(*points)


def department() -> World:
    """The paper's Section V loop (about 40 m): laboratory -> hallway -> hall -> back to the lab.

    Section V: "We started from a laboratory, a very scattered environment, then we crossed a
    narrow hallway with rectilinear walls to enter a department hall, a large open space with long
    perpendicular walls, and finally we closed the loop reentering the laboratory."

    Lab [0, 8] x [0, 7]; hallway [8, 16] x [5.2, 6.8] (1.6 m wide, door frames in both walls);
    hall [16, 26] x [-3, 9] (two pillars and a counter); passage [8, 16] x [0, 2.4] back to the
    lab; the block [8, 16] x [2.4, 5.2] between hallway and passage is solid.
    """
    p = FloorPlan()
    # Laboratory shell: a double door to the passage, the hallway opening to the north-east.
    p.polyline((8, 0.4), (8, 0), (0, 0), (0, 7), (8, 7), (8, 6.8))
    p.polyline((8, 2.0), (8, 2.4))
    # Hallway: long straight walls with door frames (recesses 0.15 m deep).
    _wall_with_recesses(p, 6.8, 8, 16, [(9.9, 10.8), (13.2, 14.1)], 0.15)
    _wall_with_recesses(p, 5.2, 8, 16, [(11.6, 12.5)], -0.15)
    # The block between hallway and passage (offices nobody enters).
    p.polyline((8, 5.2), (8, 2.4), (16, 2.4), (16, 5.2))
    p.solid(((8, 2.4), (16, 2.4), (16, 5.2), (8, 5.2)))
    # Passage back to the lab: a bench, a column, a cabinet.
    p.polyline((8, 0), (16, 0))
    p.box(10.5, 1.95, 12.0, 2.3)
    p.box(13.6, 0.05, 14.0, 0.35)
    p.box(9.0, 0.05, 9.5, 0.45)
    # Hall: a large open space with long perpendicular walls and few features.
    p.polyline((16, 0), (16, -3), (26, -3), (26, 9), (16, 9), (16, 6.8))
    p.box(23.25, 3.25, 23.75, 3.75)
    p.box(20.25, -1.25, 20.75, -0.75)
    p.box(23.8, 6.4, 25.6, 7.0)
    # Laboratory clutter: many short segments (paper Fig. 9: "chairs, tables, robots, and boxes").
    p.box(0.1, 2.2, 0.9, 3.8)  # desk along the west wall
    p.box(0.1, 4.4, 0.7, 5.2)  # cabinet
    p.box(3.7, 2.5, 5.5, 3.3)  # central desk island
    p.rotated_box(4.2, 3.75, 0.45, 0.45, 0.3)  # chairs at the island
    p.rotated_box(5.0, 3.8, 0.45, 0.45, -0.2)
    p.rotated_box(6.5, 4.2, 0.8, 0.6, 0.5)  # a robot
    p.rotated_box(6.9, 2.7, 0.5, 0.5, 0.3)  # boxes
    p.rotated_box(7.45, 3.35, 0.4, 0.4, 0.0)
    p.box(7.1, 4.9, 7.8, 5.15)
    p.box(1.0, 6.3, 1.6, 6.9)  # boxes stacked along the north wall
    p.box(1.7, 6.45, 2.2, 6.9)
    p.rotated_box(2.8, 6.55, 0.5, 0.4, 0.15)
    p.box(0.1, 0.1, 3.8, 0.5)  # a shelf along the south wall, with uprights
    for x in (0.9, 1.8, 2.7):
        p.box(x, 0.5, x + 0.08, 0.58)
    p.box(5.8, 0.1, 7.0, 0.7)  # a workbench
    for cx, cy in ((1.6, 4.6), (1.75, 5.25)):  # table legs
        p.box(cx, cy, cx + 0.06, cy + 0.06)
    outline = ((0, 0), (8, 0), (16, 0), (16, -3), (26, -3), (26, 9), (16, 9), (16, 6.95), (8, 6.95), (8, 7), (0, 7))
    return p.build("department", "the paper's Section V loop: cluttered lab, narrow hallway, large hall", outline)


def office() -> World:
    """An office floor [0, 30] x [0, 14]: a corridor y in [6, 8], rooms to the north and south."""
    p = FloorPlan()
    p.polyline((0, 6), (0, 0), (30, 0), (30, 14), (0, 14), (0, 8))
    p.polyline((0, 6), (0, 8))  # the corridor's west end: a window wall
    # Rooms: (x0, x1, door start) on each side; the door is 0.9 m wide.
    north = [(0, 4, 2.6), (4, 9, 4.5), (9, 13, 11.8), (13, 19, 15.0), (19, 24, 22.6), (24, 30, 24.6)]
    south = [(0, 6, 4.4), (6, 10, 6.4), (10, 15, 13.6), (15, 20, 17.8), (20, 24, 20.4), (24, 30, 27.4)]
    for rooms, y_wall, y_far in ((north, 8.0, 14.0), (south, 6.0, 0.0)):
        xs = [0.0]
        for _x0, x1, door in rooms:
            xs += [door, door + 0.9]
            if x1 < 30:
                p.polyline((x1, y_wall), (x1, y_far))
        xs.append(30.0)
        for a, b in zip(xs[0::2], xs[1::2], strict=True):
            p.polyline((a, y_wall), (b, y_wall))
    # Furniture, different in every room.
    p.box(0.3, 12.0, 2.0, 13.7)  # north room 1: desk in the corner
    p.box(3.3, 9.0, 3.9, 10.2)  # cabinet
    p.box(5.5, 11.5, 7.5, 12.3)  # north room 2: desk and chair
    p.rotated_box(6.4, 10.9, 0.45, 0.45, 0.4)
    p.box(8.4, 13.0, 8.9, 13.9)
    p.box(9.2, 12.6, 10.8, 13.8)  # north room 3
    p.box(14.5, 10.0, 17.5, 11.6)  # north room 4: meeting table
    for cx in (14.9, 15.9, 16.9):
        p.rotated_box(cx, 9.5, 0.45, 0.45, 0.1 * cx)
    p.box(19.2, 13.2, 21.0, 13.8)  # north room 5: kitchen counter
    p.box(23.2, 8.2, 23.8, 8.9)  # fridge
    p.box(27.0, 11.0, 28.6, 12.6)  # north room 6: desks
    p.box(25.0, 12.8, 26.5, 13.8)
    p.box(0.3, 0.3, 2.3, 1.1)  # south room 1
    p.rotated_box(3.6, 2.5, 0.5, 0.5, 0.6)
    p.box(8.2, 0.2, 9.8, 1.0)  # south room 2
    p.box(11.0, 2.0, 12.6, 3.6)  # south room 3: a round-ish table, drawn as a box
    p.box(14.2, 0.2, 14.8, 1.8)
    p.box(16.0, 0.2, 19.0, 1.0)  # south room 4: a row of desks
    p.box(22.8, 3.0, 23.8, 5.0)  # south room 5: printer and shelves
    p.box(26.0, 1.0, 29.5, 2.2)  # south room 6
    p.rotated_box(28.0, 4.0, 0.6, 0.6, 0.8)
    # Corridor furniture: a plant and a water cooler break its symmetry.
    p.box(8.3, 7.55, 8.7, 7.95)
    p.box(21.5, 6.05, 21.9, 6.4)
    outline = ((0, 0), (30, 0), (30, 14), (0, 14))
    return p.build("office", "an office floor: a corridor with rooms and doors on both sides", outline)


def warehouse() -> World:
    """A warehouse [0, 36] x [0, 24]: racks in rows, a loading dock to the south, offices to the west.

    Racks run north-south, 1.0 m deep, 2.5 m aisles (3.5 m pitch), split by a cross aisle; every
    bay is 2.7 m with an upright post. The racks repeat; what breaks the repetition: pallets
    sticking out of a few bays, a shorter row, pallets on the dock floor, the dock doors and the
    offices (a fixed seed picks the bays, so the world is always the same).
    """
    p = FloorPlan()
    rng = np.random.default_rng(2006)
    # Shell with dock doors (recesses) in the south wall.
    _wall_with_recesses(p, 0.0, 0, 36, [(9, 12), (15, 18), (21, 24), (27, 30)], -0.5)
    p.polyline((36, 0), (36, 24), (0, 24), (0, 0))
    # Offices at the west end: two rooms along the north wall with doors to the floor.
    p.polyline((0, 16), (2.0, 16))
    p.polyline((2.9, 16), (5, 16), (5, 17.5))
    p.polyline((5, 18.4), (5, 21.2))
    p.polyline((5, 22.1), (5, 24))
    p.polyline((0, 20), (5, 20))
    p.box(0.3, 22.5, 1.8, 23.7)
    p.box(3.6, 16.3, 4.7, 17.0)
    # Rack rows: x0 of each row; row 6 is shorter (a forklift parking at its north end).
    rows = [7.0, 10.5, 14.0, 17.5, 21.0, 24.5, 28.0, 31.5]
    sections = [(6.0, 13.9), (15.5, 21.9)]
    for k, x0 in enumerate(rows):
        for y0, y1 in sections:
            top = y1 - 2.7 if (k == 5 and y0 > 14) else y1
            p.box(x0, y0, x0 + 1.0, top)
            y = y0 + 2.7
            while y < top - 0.1:
                # Upright posts on both faces of the rack, every 2.7 m.
                p.box(x0 - 0.08, y - 0.04, x0, y + 0.04)
                p.box(x0 + 1.0, y - 0.04, x0 + 1.08, y + 0.04)
                y += 2.7
    # A few pallets sticking out of their bays (chosen once by the fixed seed).
    for _ in range(7):
        x0 = rows[int(rng.integers(len(rows)))]
        y0, y1 = sections[int(rng.integers(len(sections)))]
        yb = y0 + 0.3 + float(rng.integers(2)) * 2.7
        west = bool(rng.integers(2))
        depth = float(rng.uniform(0.15, 0.3))
        if west:
            p.box(x0 - 0.08 - depth, yb, x0 - 0.08, yb + 1.2)
        else:
            p.box(x0 + 1.08, yb, x0 + 1.08 + depth, yb + 1.2)
    # Forklift parked where row 6's last bay is missing; a column grid along the dock.
    p.rotated_box(25.0, 20.6, 1.2, 0.9, 0.3)
    for x in (8.5, 15.5, 22.5, 29.5):
        p.box(x - 0.2, 4.3, x + 0.2, 4.7)
    # Pallets waiting on the dock floor, irregular.
    for cx, cy, a in ((10.6, 1.6, 0.1), (13.3, 2.4, -0.25), (19.8, 1.4, 0.4), (26.0, 2.6, 0.0), (32.8, 1.8, 0.7)):
        p.rotated_box(cx, cy, 1.2, 1.0, a)
    outline = ((0, 0), (36, 0), (36, 24), (0, 24))
    return p.build("warehouse", "rack rows (repetitive), a loading dock and offices", outline)


WORLDS: dict[str, Callable[[], World]] = {"department": department, "office": office, "warehouse": warehouse}
"""Bundled worlds by name."""


@functools.cache
def get_world(name: str) -> World:
    """The bundled world called ``name`` (built once; its arrays are read-only)."""
    if name not in WORLDS:
        raise ConfigError(f"world {name!r}", f"unknown world (known: {', '.join(WORLDS)})")
    return WORLDS[name]()
