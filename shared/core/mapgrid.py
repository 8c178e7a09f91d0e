"""Large partial maps: viewpoints, seen free space and a grid index (fleetmap, beyond the paper).

The paper integrates partial maps exactly as it integrates scans (IV: "all the methods are
applicable to the integration of two partial maps"), and notes that it gets slow and unreliable
as they grow (V-B, V-C). Two partial maps of a real building share only a part of their walls,
while their many long parallel walls (corridors, racks) let wrong transformations match tens of
metres: the transformation value alone does not separate right from wrong. What separates them
is what the robots *saw*: a map built from scans knows from where each scan was taken, and the
space between those viewpoints and the walls they saw is free. A wrong transformation puts one
map's walls in the other's free space; the right one does not.

- **Viewpoints.** A map may carry the poses of the scans it was built from, in its own frame:
  ``SegmentMap.extras["viewpoints"]``, rows ``[x, y, theta, bearing_min, bearing_max]`` (the
  bearings, in the scan's frame, that its segments span). The pivot method records them
  (:class:`fleetmap.shared.core.pivotmap.PivotMapBuilder`); they survive a map file (extra keys are
  kept). A scan (an ``ordered`` map) has one, at its origin.
- **Free grid.** The cells seen free from any viewpoint: from each viewpoint, the range profile of
  the map's own segments (:func:`fleetmap.shared.core.visibility.range_profile`: the nearest wall in
  each bearing, within the span the scan covered) minus a margin that grows with range (the map's
  own small rotation errors move far walls most). The map's walls include the scan's own, so
  this never claims more than the scan saw.
- **Map index.** For ranking many candidate transformations fast: a grid of the cells near the
  map's walls, one layer per wall direction (a likelihood field, Thrun, Burgard & Fox 2005, 6.4;
  Olson 2009's correlative matching), plus the free grid and points sampled along the walls. The
  *grid score* of a transformation of B on A is the wall length of each map that lands near a
  wall of the other facing the same way (averaged over the two directions) minus the wall length
  of each that lands in the other's free space. It ranks the candidates of the paper's heuristics;
  the best few are then valued exactly (Algorithm 4) and refined.
- **What refuses an alignment** (``solid``). Refusing an alignment for the wall it puts in seen
  free space counts only the walls that are evidence against it:
  - outside the ``clearance`` of the map's own walls (``map_free_space_clearance``): two local
    maps, each built from its own scans, disagree on a wall's place by a few tenths of a metre
    (their scan-to-scan errors add up differently), and a viewpoint that sees the wall at a
    grazing angle puts such an offset metres along its ray, beyond any range margin. Another
    map's wall that close to one of this map's is that wall, placed a little apart;
  - of long segments (at least ``min_length``, ``MAP_FREE_SPACE_MIN_LENGTH``): short ones are
    mostly clutter that moves between visits, or that one viewpoint sees and another sees past.
  Ranking and scoring alignments count every wall (the free grid, every wall), so the choice, the
  ambiguity and the refutation of rivals are the same either way: in racks, the 8 cm posts a bay
  off are what refute an alias.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from fleetmap.shared.core.freecells import mark_free
from fleetmap.shared.core.geometry import Array, Transform2D, lengths, orientations, segment_points
from fleetmap.shared.core.gridlookup import code_sums
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.visibility import range_profile
from fleetmap.shared.core.walllookup import wall_sums
from fleetmap.shared.errors import BadInput

GRID_RESOLUTION = 0.10
"""Large maps: cell size (m) of the grids that rank candidates by matched wall length and wall in
seen free space."""
MAP_FREE_SPACE_MARGIN = 0.20
"""Large maps: a wall point this much (m) closer to a viewpoint than the map's wall in that bearing
lies in the seen free space ..."""
MAP_FREE_SPACE_SLOPE = 0.02
"""... plus this much per metre of range (far walls move most under a small rotation error)."""

VIEWPOINTS = "viewpoints"
"""The key of a map's viewpoints in ``SegmentMap.extras``."""

CHANNELS = 8
"""Wall-direction layers of the hit grid (45 degrees each over a full turn)."""

PROFILE_BINS = 720
"""Bearing bins of a viewpoint's range profile (0.5 degree)."""
PROFILE_WIDEN = 2
"""A bin's free range is the smallest over this many bins on either side (1 degree)."""

VIEWPOINT_SPACING = 0.5
VIEWPOINT_TURN = 0.35
"""A viewpoint closer than this (m) to one already drawn, and turned less than this (rad), adds
nothing new to the free grid and is skipped."""

MAX_CELLS = 4_000_000
"""The grid's resolution is coarsened so that a map never needs more cells than this."""

COARSE_POINTS = 160
FINE_SPACING = 0.1
"""Points sampled along a map's walls for the grid score: about COARSE_POINTS for the first pass
over every candidate, one every FINE_SPACING metres for the second."""


def scan_viewpoint(segments: Array) -> Array:
    """The viewpoint of a scan ``(1, 5)``: its origin, and the bearings its segments span."""
    ends = np.asarray(segments, dtype=np.float64).reshape(-1, 2)
    if len(ends) == 0:
        return np.zeros((0, 5))
    bearing = np.arctan2(ends[:, 1], ends[:, 0])
    return np.array([[0.0, 0.0, 0.0, float(bearing.min()), float(bearing.max())]])


def viewpoints_of(m: SegmentMap) -> Array:
    """A map's viewpoints ``(v, 5)``: those it carries, a scan's own, or none."""
    raw = m.extras.get(VIEWPOINTS)
    if raw is None:
        return scan_viewpoint(m.segments) if m.ordered else np.zeros((0, 5))
    try:
        vp = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise BadInput(VIEWPOINTS, "must be a list of [x, y, theta, bearing_min, bearing_max]") from None
    if vp.size == 0:
        return np.zeros((0, 5))
    if vp.ndim != 2 or vp.shape[1] != 5:
        raise BadInput(
            VIEWPOINTS, f"must have rows of 5 numbers [x, y, theta, bearing_min, bearing_max], got {vp.shape}"
        )
    if not np.isfinite(vp).all():
        raise BadInput(VIEWPOINTS, "has a NaN or infinite number")
    return vp


def with_viewpoints(m: SegmentMap, viewpoints: Array) -> SegmentMap:
    """``m`` carrying ``viewpoints`` (rows ``[x, y, theta, bearing_min, bearing_max]``)."""
    rows = [[float(v) for v in row] for row in np.asarray(viewpoints, dtype=np.float64).reshape(-1, 5)]
    return SegmentMap(m.segments, ordered=m.ordered, oriented=m.oriented, extras={**m.extras, VIEWPOINTS: rows})


def moved_viewpoints(viewpoints: Array, t: Transform2D) -> Array:
    """Viewpoints moved by ``t`` (their bearings are in their own frame and do not change)."""
    vp = np.asarray(viewpoints, dtype=np.float64).reshape(-1, 5).copy()
    vp[:, 0:2] = t.apply_points(vp[:, 0:2])
    vp[:, 2] = np.mod(vp[:, 2] + t.theta + math.pi, 2 * math.pi) - math.pi
    return vp


def distinct_viewpoints(viewpoints: Array) -> Array:
    """The viewpoints that add to the free grid (greedy, in order; see VIEWPOINT_SPACING). Those
    kept are filed by their cell of ``VIEWPOINT_SPACING``: one closer than that lies in the same
    cell or one beside it, so each viewpoint is compared with its neighbours, not with every one
    kept (a long log's 20,000 viewpoints took seconds)."""
    kept: list[int] = []
    cells: dict[tuple[int, int], list[int]] = {}
    for k, (x, y, th, _, _) in enumerate(viewpoints):
        if not (math.isfinite(x) and math.isfinite(y)):
            kept.append(k)  # near nothing, and nothing is near it
            continue
        i, j = math.floor(x / VIEWPOINT_SPACING), math.floor(y / VIEWPOINT_SPACING)
        near = (n for di in (-1, 0, 1) for dj in (-1, 0, 1) for n in cells.get((i + di, j + dj), ()))
        if not any(
            math.hypot(x - viewpoints[n, 0], y - viewpoints[n, 1]) < VIEWPOINT_SPACING
            and abs(math.remainder(th - viewpoints[n, 2], 2 * math.pi)) < VIEWPOINT_TURN
            for n in near
        ):
            kept.append(k)
            cells.setdefault((i, j), []).append(k)
    return viewpoints[kept]


@dataclass(frozen=True)
class Frame:
    """A raster over a map: cell (i, j) covers ``origin + ([i, i+1), [j, j+1)) * resolution``."""

    origin: Array
    resolution: float
    shape: tuple[int, int]

    @staticmethod
    def around(points: Array, resolution: float, pad: float = 1.0) -> Frame:
        lo = points.min(axis=0) - pad
        hi = points.max(axis=0) + pad
        res = resolution
        while math.ceil((hi[0] - lo[0]) / res) * math.ceil((hi[1] - lo[1]) / res) > MAX_CELLS:
            res *= 1.5
        shape = (math.ceil((hi[0] - lo[0]) / res) + 1, math.ceil((hi[1] - lo[1]) / res) + 1)
        return Frame(lo, res, shape)

    def cells(self, x: Array, y: Array) -> tuple[Array, Array, Array]:
        """Cell indices of points and whether each falls on the grid (off-grid points get (0, 0))."""
        i = np.floor((x - self.origin[0]) / self.resolution).astype(np.int64)
        j = np.floor((y - self.origin[1]) / self.resolution).astype(np.int64)
        on = (i >= 0) & (j >= 0) & (i < self.shape[0]) & (j < self.shape[1])
        return np.where(on, i, 0), np.where(on, j, 0), on


def free_grid(segments: Array, viewpoints: Array, frame: Frame, margin: float, slope: float) -> Array:
    """Cells seen free from any viewpoint (see the module docstring); bool ``frame.shape``."""
    free = np.zeros(frame.shape, dtype=bool)
    if len(segments) == 0:
        return free
    width = 2 * math.pi / PROFILE_BINS
    centre = (np.arange(PROFILE_BINS) + 0.5) * width - math.pi
    step = 0.7 * frame.resolution
    seen = distinct_viewpoints(np.asarray(viewpoints, dtype=np.float64))
    profiles = np.empty((len(seen), PROFILE_BINS))
    for v, (x, y, th, b0, b1) in enumerate(seen):
        pose = Transform2D(float(x), float(y), float(th))
        profiles[v] = range_profile(pose.inverse().apply(segments), PROFILE_BINS, PROFILE_WIDEN)
        profiles[v, (centre < b0) | (centre > b1)] = 0.0
    # Along each bearing, free up to the wall less the margin (which grows with range).
    reach = (profiles - margin) / (1.0 + slope)
    count = np.where(reach > 0, np.floor(np.maximum(reach, 0) / step).astype(np.int64) + 1, 0)
    angle = centre[None, :] + seen[:, 2, None]
    mark_free(seen[:, 0], seen[:, 1], reach, count, angle, step, frame.origin, frame.resolution, free)
    return free


@dataclass(frozen=True)
class Samples:
    """Points along a map's walls: position, wall direction, and the wall length each stands for."""

    points: Array
    direction: Array
    weight: Array
    solid: Array
    """The wall length each stands for where it lies in seen free space: its weight if its segment
    is at least the index's ``min_length`` long, else 0 (clutter is no evidence against)."""

    @staticmethod
    def along(segments: Array, spacing: float, min_length: float = 0.0) -> Samples:
        """One point every ``spacing`` metres of wall, the walls taken end to end (a segment
        shorter than the spacing may get none), each standing for ``spacing`` metres."""
        if len(segments) == 0:
            return Samples(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0))
        ln = lengths(segments)
        cum = np.cumsum(ln)
        at = np.arange(0.5 * spacing, float(cum[-1]), spacing)
        owner = np.minimum(np.searchsorted(cum, at, side="right"), len(segments) - 1)
        frac = np.clip((at - (cum[owner] - ln[owner])) / np.maximum(ln[owner], 1e-12), 0.0, 1.0)
        s = segments[owner]
        pts = s[:, 0:2] + (s[:, 2:4] - s[:, 0:2]) * frac[:, None]
        weight = np.full(len(at), spacing)
        return Samples(pts, orientations(segments)[owner], weight, np.where(ln[owner] >= min_length, weight, 0.0))


@dataclass(frozen=True)
class MapIndex:
    """A map prepared for the grid score (see the module docstring); build with :func:`map_index`."""

    frame: Frame
    hits: Array
    """``(CHANNELS, nx, ny)``: cells within reach of a wall of that direction (or a neighbouring one)."""
    free: Array
    """``(nx, ny)``: cells seen free from the map's viewpoints (all False without viewpoints)."""
    clear: Array
    """``(nx, ny)``: the free cells farther than the index's clearance from the map's walls (where
    another map's solid walls count against an alignment's validity)."""
    coarse: Samples
    fine: Samples
    period: float
    """2 pi for oriented maps (a wall's direction tells its seen side), pi otherwise."""
    has_free: bool
    code: Array
    """``(CHANNELS, nx + 2, ny + 2)`` int8, padded with a zero border: 1 on the hit cells, -2 on the
    free cells that are not, 0 elsewhere (twice the grid score's weights: the matched length is the
    mean over the two directions)."""


def map_index(
    m: SegmentMap,
    resolution: float,
    reach: float,
    margin: float,
    slope: float,
    min_length: float = 0.0,
    clearance: float = 0.0,
) -> MapIndex:
    """Index ``m`` for the grid score: hit grid within ``reach`` of its walls, free grid from its
    viewpoints less the cells within ``clearance`` of its walls; only its segments at least
    ``min_length`` long count in another map's free space."""
    seg = np.asarray(m.segments, dtype=np.float64)
    vp = viewpoints_of(m)
    corners = np.vstack([seg.reshape(-1, 2), vp[:, 0:2]]) if len(vp) else seg.reshape(-1, 2)
    frame = Frame.around(corners, resolution)
    period = 2 * math.pi if m.oriented else math.pi
    # Hit grid: cells around points every half cell along the walls, in the wall's direction layer
    # and its two neighbours (so a wall matches a wall within about 45 degrees).
    wall_points, owner = segment_points(seg, frame.resolution / 2)
    ch = _channel(orientations(seg)[owner], period)
    hits = np.zeros((CHANNELS, *frame.shape), dtype=bool)
    for i, j, on in _cells_within(frame, wall_points, max(reach, frame.resolution)):
        for dc in (-1, 0, 1):
            hits[(ch[on] + dc) % CHANNELS, i[on], j[on]] = True
    free = free_grid(seg, vp, frame, margin, slope) if len(vp) else np.zeros(frame.shape, dtype=bool)
    clear = free
    if clearance > 0 and len(vp) and not m.ordered:
        # Clear of the map's own walls: another map's wall that close is that wall, placed apart.
        # (Only between two partial maps does the validity rule read it: not for a scan.)
        clear = free.copy()
        for i, j, on in _cells_within(frame, wall_points, clearance):
            clear[i[on], j[on]] = False
    total = float(lengths(seg).sum())
    coarse = Samples.along(seg, max(FINE_SPACING, total / COARSE_POINTS), min_length)
    fine = Samples.along(seg, FINE_SPACING, min_length)
    code = np.zeros((CHANNELS, frame.shape[0] + 2, frame.shape[1] + 2), dtype=np.int8)
    code[:, 1:-1, 1:-1] = np.where(hits, np.int8(1), np.where(free[None], np.int8(-2), np.int8(0)))
    return MapIndex(frame, hits, free, clear, coarse, fine, period, bool(len(vp)), code)


def _cells_within(frame: Frame, points: Array, distance: float) -> Iterator[tuple[Array, Array, Array]]:
    """The cells (as :meth:`Frame.cells`) of ``points`` moved by each whole-cell offset within
    ``distance``: together, the cells within about that distance of the points."""
    r = math.ceil(distance / frame.resolution)
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            if di * di + dj * dj <= r * r:
                yield frame.cells(points[:, 0] + di * frame.resolution, points[:, 1] + dj * frame.resolution)


def _channel(direction: Array, period: float) -> Array:
    return (np.floor(np.mod(direction, period) / period * CHANNELS).astype(np.int64)) % CHANNELS


RANK_ROTATION_STEP = math.radians(0.25)
"""For ranking, candidates are grouped by rotation rounded to this (rad); each group's points are
turned once."""


def _ranking_lookups(index: MapIndex, s: Samples, t: Array) -> Array:
    """Grid score contributions of ``s`` moved by each transformation (rotations rounded, for ranking).

    All candidates at once, in one compiled pass (:func:`~fleetmap.shared.core.gridlookup.code_sums`):
    each rotation group's points are turned once, then every candidate of the group looks them up
    moved by its translation. The codes are summed as integers and scaled by the samples' spacing
    (each sample stands for the same wall length: :meth:`Samples.along`): the score is then exact,
    so equal scores tie exactly (the stable sort keeps the candidates' order).
    """
    if len(s.points) == 0 or len(t) == 0:
        return np.zeros(len(t))
    spacing = float(s.weight[0])
    if not np.all(s.weight == spacing):
        raise ValueError("the grid score's samples must each stand for the same wall length (Samples.along)")
    ox, oy = index.frame.origin
    frame = (float(ox), float(oy), index.frame.resolution, index.period, CHANNELS)
    counts = code_sums(index.code, s.points, s.direction, t, RANK_ROTATION_STEP, frame)
    return 0.5 * (counts * spacing)


def _lookups(index: MapIndex, s: Samples, t: Array, solid: bool = False) -> tuple[Array, Array]:
    """For each transformation: wall length of ``s`` (moved by it) near ``index``'s walls, and in its
    free space (if ``solid``: only the solid walls', clear of ``index``'s walls); one compiled loop
    (:mod:`~fleetmap.shared.core.walllookup`)."""
    ox, oy = index.frame.origin
    frame = (float(ox), float(oy), index.frame.resolution, index.period, CHANNELS, index.has_free)
    free, free_weight = (index.clear, s.solid) if solid else (index.free, s.weight)
    return wall_sums(index.hits, free, s.points, s.direction, s.weight, free_weight, t, frame)


def ranking_scores(a: MapIndex, b: MapIndex, t: Array, fine: bool = False) -> Array:
    """The grid score of transformations ``t`` of B on A (rotations rounded to RANK_ROTATION_STEP):
    matched wall length (mean of both directions) less wall length in the other's free space."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    sa, sb = (a.fine, b.fine) if fine else (a.coarse, b.coarse)
    ab, ba = _both_ways(
        lambda: _ranking_lookups(a, sb, t), lambda: _ranking_lookups(b, sa, inverse_transforms(t)), len(t)
    )
    return ab + ba


T = TypeVar("T")

_pool: tuple[int, ThreadPoolExecutor] | None = None

PARALLEL_FROM = 4096
"""Below this many transformations, the two directions of a grid score run one after the other
(a thread hand-off costs more than it saves)."""


def _both_ways(ab: Callable[[], T], ba: Callable[[], T], n: int) -> tuple[T, T]:
    """``ab()`` and ``ba()``, the first on a second thread where the machine has a second core.

    The lookups (the compiled loops of :mod:`~fleetmap.shared.core.walllookup` and
    :mod:`~fleetmap.shared.core.gridlookup`) release the GIL, so the two directions of a grid score
    run side by side, with the same arithmetic, so the same result to the bit. The pool
    belongs to the process that made it (a forked worker makes its own: threads do not survive
    a fork)."""
    global _pool
    if n < PARALLEL_FROM or (os.cpu_count() or 1) < 2:
        return ab(), ba()
    if _pool is None or _pool[0] != os.getpid():
        _pool = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="fleetmap-grid"))
    first = _pool[1].submit(ab)
    second = ba()
    return first.result(), second


def inverse_transforms(t: Array) -> Array:
    c, s = np.cos(t[:, 2]), np.sin(t[:, 2])
    return np.column_stack([-(c * t[:, 0] + s * t[:, 1]), s * t[:, 0] - c * t[:, 1], -t[:, 2]])


def grid_scores(a: MapIndex, b: MapIndex, t: Array, fine: bool = False, solid: bool = False) -> tuple[Array, Array]:
    """Grid score parts of transformations ``t`` of B on A: matched wall length (mean of both
    directions) and wall length in the other's free space (sum of both; if ``solid``, only the
    walls of segments at least the indexes' ``min_length`` long, and farther than the other's
    ``clearance`` from its walls: what the validity rule limits)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    sa, sb = (a.fine, b.fine) if fine else (a.coarse, b.coarse)
    (hit_ab, free_ab), (hit_ba, free_ba) = _both_ways(
        lambda: _lookups(a, sb, t, solid), lambda: _lookups(b, sa, inverse_transforms(t), solid), len(t)
    )
    return 0.5 * (hit_ab + hit_ba), free_ab + free_ba
