"""The global map as an occupancy grid, and the map_server files every ROS planner loads.

nav2's ``map_server`` (and ROS 1's) reads a map as an image and a YAML file beside it: ``map.pgm``
(one byte a cell, the top row the farthest north) and ``map.yaml`` (``image``, ``resolution``,
``origin`` of the lower-left pixel, ``negate``, ``occupied_thresh``, ``free_thresh``, ``mode``). A
pixel ``p`` is read as occupancy ``(255 - p) / 255``: above ``occupied_thresh`` occupied, below
``free_thresh`` free, unknown between (trinary). The values written are ``map_saver``'s own: 0
occupied, 254 free, 205 unknown, with thresholds 0.65 and 0.196, so a map saved here loads as one
``map_saver`` wrote.

The cells (:func:`occupancy_grid`) come from the beams, as occupancy mapping has them (Moravec &
Elfes 1985; the hit and pass counts of gmapping and slam_toolbox): each placed scan's raw ranges,
cast from the scan's pose in the global map, pass through cells on their way (free evidence) and
end in one (occupied evidence); a cell's log-odds is the sum of its evidence under OctoMap's sensor
model (Hornung et al. 2013: a hit 0.7, a pass 0.4), so it is occupied where more beams ended than
passed, free where more passed, unknown where none did. A beam with no return says nothing, as in
gmapping and slam_toolbox, and neither does one whose end is on no wall of the map: a passer-by, a
reflection, or a log's no-return reading not named as one. The global map's walls (its fused
segments: what the merge found, not the raw returns of clutter that moved) add occupied cells only
where no beam's evidence says free: a wall the robots saw through, or drove through, is not in the
grid (docs/decisions/011-occupancy-from-the-beams.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fleetmap.shared.core.beammarch import beam_passes
from fleetmap.shared.core.geometry import Array, Transform2D, lengths
from scipy.ndimage import binary_dilation

FREE, OCCUPIED, UNKNOWN = 0, 100, -1
"""Cell values, as nav_msgs/OccupancyGrid has them."""
PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN = 254, 0, 205
"""Pixel values, as map_saver writes them."""
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
"""map_saver's thresholds: 205 reads as 0.196, which is not below ``FREE_THRESH``: unknown."""
MARGIN_CELLS = 2
"""Unknown cells kept round what was seen."""
LOG_ODDS_HIT = math.log(0.7 / 0.3)
LOG_ODDS_PASS = math.log(0.4 / 0.6)
"""A cell's evidence from one beam that ended in it, and from one that passed through it: OctoMap's
sensor model (``prob_hit`` 0.7, ``prob_miss`` 0.4, Hornung et al. 2013), its defaults."""
HIT_TOLERANCE = 0.15
"""How far (m) a beam's end may lie from the map's walls and still be a hit on them: the walls are
fused from many scans at their optimized poses, each a few centimetres off the raw return."""


@dataclass(frozen=True)
class Beams:
    """One scan's raw readings and where it was taken in the map (beam i at ``angle_min + i *
    angle_increment`` in the laser's frame; a reading that is not finite, <= 0 or >= ``range_max``
    is no return)."""

    pose: Transform2D
    angle_min: float
    angle_increment: float
    range_max: float
    ranges: Array


@dataclass(frozen=True)
class OccupancyGrid:
    """Cells ``(rows, cols)`` of ``resolution`` m, row 0 the southernmost; ``origin`` is the
    south-west corner of cell (0, 0) in the map frame."""

    cells: Array
    origin: tuple[float, float]
    resolution: float

    def cell_of(self, points: Array) -> tuple[Array, Array, Array]:
        """(row, col, inside) of points ``(n, 2)``."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        col = np.floor((p[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        row = np.floor((p[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        inside = (row >= 0) & (row < self.cells.shape[0]) & (col >= 0) & (col < self.cells.shape[1])
        return row, col, inside


def occupancy_grid(scans: Iterable[Beams], walls: Array, resolution: float = 0.05) -> OccupancyGrid:
    """The grid of the module docstring: the log-odds of every cell from the beams that ended on a
    wall of ``walls`` ``(n, 4)``, occupied above 0 and free below; the walls' cells occupied where
    the beams say nothing or occupied; unknown elsewhere. It spans the walls."""
    if not resolution > 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    origins, ends = [], []
    for s in scans:
        r = np.asarray(s.ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            hit = np.isfinite(r) & (r > 0) & (r < s.range_max)
        if not hit.any():
            continue
        a = s.angle_min + s.angle_increment * np.flatnonzero(hit) + s.pose.theta
        ends.append(np.column_stack([s.pose.x + r[hit] * np.cos(a), s.pose.y + r[hit] * np.sin(a)]))
        origins.append(np.repeat([[s.pose.x, s.pose.y]], int(hit.sum()), axis=0))
    start = np.vstack(origins) if origins else np.zeros((0, 2))
    end = np.vstack(ends) if ends else np.zeros((0, 2))
    corners = np.vstack([start[:1], walls.reshape(-1, 2)])  # every beam that counts ends on a wall
    if len(corners) == 0:
        return OccupancyGrid(np.full((1, 1), UNKNOWN, dtype=np.int8), (0.0, 0.0), resolution)
    low = np.floor(corners.min(axis=0) / resolution) - MARGIN_CELLS
    high = np.floor(corners.max(axis=0) / resolution) + MARGIN_CELLS + 1
    shape = (int(high[1] - low[1]), int(high[0] - low[0]))
    grid = OccupancyGrid(
        np.full(shape, UNKNOWN, dtype=np.int8), (float(low[0] * resolution), float(low[1] * resolution)), resolution
    )
    on_walls = np.zeros(shape, dtype=bool)
    for points in _along_walls(walls, resolution):
        row, col, inside = grid.cell_of(points)
        on_walls[row[inside], col[inside]] = True
    # a beam counts only if it ended on a wall of the map: one that hit a passer-by, a reading of
    # the sensor's no-return value, or a reflection says nothing of the cells it crossed
    near = binary_dilation(on_walls, iterations=max(1, round(HIT_TOLERANCE / resolution)))
    row, col, inside = grid.cell_of(end)
    on_wall = np.zeros(len(end), dtype=bool)
    on_wall[inside] = near[row[inside], col[inside]]
    start, end = start[on_wall], end[on_wall]
    row, col, _ = grid.cell_of(end)
    hits = np.bincount(row * shape[1] + col, minlength=grid.cells.size)
    start, end, repeats = _distinct_beams(grid, start, end)
    # each distinct beam stands for beams that end anywhere in its last cell, up to half its
    # diagonal from the centre it is drawn to: none of them says anything of its last HIT_TOLERANCE
    short = HIT_TOLERANCE / resolution + math.sqrt(0.5)
    passes = _along_beams(grid, start, end, short, repeats)
    log_odds = (hits * LOG_ODDS_HIT + passes * LOG_ODDS_PASS).reshape(shape)
    grid.cells[log_odds < 0] = FREE
    grid.cells[(log_odds > 0) | (on_walls & (log_odds >= 0))] = OCCUPIED
    return grid


def _distinct_beams(grid: OccupancyGrid, start: Array, end: Array) -> tuple[Array, Array, Array]:
    """The beams as the grid tells them apart: one from the centre of each first cell to the centre
    of each last cell that some beam joins, and how many beams joined them. A robot standing or
    creeping casts the same beams scan after scan (a log at 40 scans a second repeats most of
    them): each is marched once, and counted as often as it was cast."""
    if len(start) == 0:
        return start, end, np.zeros(0)
    r0, c0, _ = grid.cell_of(start)
    r1, c1, _ = grid.cell_of(end)
    cells = np.column_stack([r0, c0, r1, c1])
    low = cells.min(axis=0)
    span = cells.max(axis=0) - low + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:
        # one integer per (first cell, last cell): a sort of numbers, not of rows
        key, repeats = np.unique(np.ravel_multi_index(tuple((cells - low).T), tuple(span)), return_counts=True)
        cells = np.column_stack(np.unravel_index(key, tuple(span))) + low
    else:
        cells, repeats = np.unique(cells, axis=0, return_counts=True)
    centres = (cells + 0.5) * grid.resolution
    origin = np.array(grid.origin)
    return centres[:, [1, 0]] + origin, centres[:, [3, 2]] + origin, repeats.astype(np.float64)


def _along_beams(grid: OccupancyGrid, start: Array, end: Array, short: float, repeats: Array) -> Array:
    """For each cell (flat, as ``grid.cells``), the beams that pass through it, each counted
    ``repeats`` times (:func:`_distinct_beams`): points every half cell along a beam up to ``short``
    cells short of its end (the inverse sensor model's half obstacle depth: an end within
    ``HIT_TOLERANCE`` of a wall is a hit on it, so the beam's last ``HIT_TOLERANCE`` may be that
    wall's, at whatever angle it meets it), each cell counted once per beam. Worked in cell units,
    each beam marched by one compiled loop (:func:`~fleetmap.shared.core.beammarch.beam_passes`):
    a long log's beams make a few hundred million points."""
    origin = np.asarray(grid.origin)
    cell_start = (start - origin) / grid.resolution
    delta = (end - origin) / grid.resolution - cell_start
    length = np.hypot(delta[:, 0], delta[:, 1])
    count = np.maximum(np.floor((length - short) / 0.5).astype(np.int64) + 1, 0)
    step = delta * (0.5 / np.maximum(length, 1e-12))[:, None]
    return beam_passes(cell_start, step, count, repeats, grid.cells.shape)


def _along_walls(walls: Array, resolution: float) -> Iterable[Array]:
    """Points every half cell along each wall, its ends included."""
    if len(walls) == 0:
        return
    count = np.ceil(lengths(walls) / (resolution / 2)).astype(np.int64) + 1
    owner = np.repeat(np.arange(len(walls)), count)
    first = np.cumsum(count) - count
    f = ((np.arange(len(owner)) - np.repeat(first, count)) / np.maximum(count[owner] - 1, 1))[:, None]
    yield walls[owner, 0:2] + f * (walls[owner, 2:4] - walls[owner, 0:2])


def write_map_server(grid: OccupancyGrid, folder: str | Path, name: str = "map") -> tuple[Path, Path]:
    """``name.pgm`` and ``name.yaml`` in ``folder`` as map_saver writes them (module docstring)."""
    folder = Path(folder)
    pixels = np.full(grid.cells.shape, PGM_UNKNOWN, dtype=np.uint8)
    pixels[grid.cells == FREE] = PGM_FREE
    pixels[grid.cells == OCCUPIED] = PGM_OCCUPIED
    image = np.ascontiguousarray(pixels[::-1])  # the image's first row is the grid's northernmost
    pgm, yaml = folder / f"{name}.pgm", folder / f"{name}.yaml"
    rows, cols = image.shape
    pgm.write_bytes(
        f"P5\n# fleetmap occupancy grid, {grid.resolution} m/pixel\n{cols} {rows}\n255\n".encode() + image.tobytes()
    )
    yaml.write_text(
        f"image: {pgm.name}\n"
        "mode: trinary\n"
        f"resolution: {grid.resolution}\n"
        f"origin: [{grid.origin[0]:.6f}, {grid.origin[1]:.6f}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n",
        encoding="utf-8",
    )
    return pgm, yaml


def placed_scans(
    submap_poses: Mapping[str, Transform2D], tables: Mapping[str, tuple[Array, Array]]
) -> dict[tuple[str, int], tuple[str, Transform2D]]:
    """Each scan of the placed submaps, by (robot, index): the submap it is taken from and its pose
    in the submaps' frame (the submap's pose composed with the scan's in the submap, ``tables``:
    submap key -> (scan indices, scan poses)); a scan in two overlapping submaps counts once, from
    the first in key order."""
    out: dict[tuple[str, int], tuple[str, Transform2D]] = {}
    for key in sorted(submap_poses):
        table = tables.get(key)
        if table is None:
            continue
        robot = key.split("/", 1)[0]
        frame = submap_poses[key]
        for index, pose in zip(np.asarray(table[0]).tolist(), np.asarray(table[1]), strict=True):
            out.setdefault((robot, int(index)), (key, frame.compose(Transform2D.from_array(pose))))
    return out
