"""Scan-to-submap registration: robust point-to-line ICP with a motion prior (pure core).

A robot's next scan is the easy case of mapping: its laser runs at 5-40 Hz, so the scan is a few
centimetres and degrees from where its odometry (or its recent velocity) predicts it. Production
2D SLAM tracks such scans locally against a small submap (Cartographer, slam_toolbox, Hector);
so do two of the project's source papers: Dugarjav & Lee build each robot's local map by ICP, and
Armesto et al. register a scan's points to the continuous curve of the other scan (eICP). Here:

- **The scan** is sampled along its extracted segments (paper III-D), every :data:`SAMPLE_SPACING`
  metres: points with the segment's normal and the wall length each stands for. Sampling the
  segments, not the raw returns, weighs a wall by its length rather than by how close it is, and
  the segment fit has already averaged the range noise.
- **The submap** is a :class:`ReferenceMap`: the samples of its scans' segments, placed by their
  tracked poses, averaged per cell of a :data:`VOXEL_SIZE` grid, each with the mean normal of its
  cell. A scan point is matched to the nearest such point whose normal faces the same way (a thin
  wall's two sides are two different walls), and its residual is the distance from that point's
  line (point-to-line: Censi's PLICP). Armesto et al.'s curve through the reference points is its
  second-order case; on cell means it gains nothing (docs/decisions/012-the-other-papers.md).
- **The fit** minimises the robust (Cauchy) sum of squared residuals plus the prior, by
  Gauss-Newton, with the correspondence radius and the loss's scale annealed from coarse to fine
  (:func:`correspondence_schedule`): a prediction a few tens of centimetres or ten degrees off still
  finds its walls, since nearby walls pull first.
- **The prior** is the prediction with its uncertainty (odometry's, or constant velocity's).
  Where the walls fix the pose (a room), it barely matters; where they leave a direction free (a
  corridor with no feature along it), it alone decides that direction: the prediction is kept
  along the corridor. Weighing the two by their information is the mechanism; there is no
  corridor threshold.
- **The check against physics** (:func:`see_through`): a laser cannot see through a wall. The
  share of the submap's wall, in front of the laser and within its reach, that the scan's beams
  pass through at the fitted pose says the scan was taken somewhere else (a kidnap, a wrong fit).

Everything here is numpy in, numpy out: no clock, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.beamkernel import HIT, NONE, THROUGH, beam_codes
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.nearest import CellIndex
from fleetmap.shared.core.rangescan import RangeScan

SAMPLE_SPACING = 0.10
"""Metres between the points sampled along a scan's segments for registration: two of the
registration grid's cells."""
VOXEL_SIZE = 0.05
"""Cell size (m) of a submap's registration grid (the mean point and normal of each cell)."""
RESIDUAL_SIGMA = 0.03
"""Standard deviation (m) of a matched point's distance from the submap's wall: weighs the walls
against the prior: the order of a laser's range noise (0.6-2.2 cm on the logs;
docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
MAX_CORRESPONDENCE = 1.0
"""Registration's first stage matches a scan point to submap walls up to this far (m), each later
stage half as far (a prediction a few tens of centimetres off still finds its walls) ..."""
MIN_CORRESPONDENCE = 0.25
"""... down to this (m)."""
LOSS_SCALE = 0.2
"""The robust (Cauchy) loss's scale, as a share of the stage's correspondence radius."""
ITERATIONS_PER_STAGE = 8
"""Gauss-Newton steps per registration stage, at most ..."""
MAX_ITERATIONS = 30
"""... and in all (a bound on a registration's cost)."""
CONVERGENCE_TRANSLATION = 0.001
"""A Gauss-Newton step shorter than this (m) ..."""
CONVERGENCE_ROTATION = 0.001
"""... and turned less than this (rad) has converged: a millimetre, well under the laser's noise."""
MAX_NORMAL_ANGLE = 1.0472
"""A scan point matches a submap wall only if their normals are within this (rad, 60 degrees): a
thin wall's two sides are two different walls."""
SEE_THROUGH_MARGIN = 0.3
"""A beam passes through a submap wall when its return lies this much (m) beyond it ..."""
SEE_THROUGH_SLOPE = 0.02
"""... plus the range change a heading error of this much (rad) makes on that wall ..."""
SEE_THROUGH = (SEE_THROUGH_MARGIN, SEE_THROUGH_SLOPE)
"""The beam test's margin, as :func:`beam_test` takes it."""
SEE_THROUGH_BEAMS = 5.0
"""... and only walls spanning this many beams at their range count (a chair leg that one beam hits
and the next misses is not a wall the next one saw through)."""
DRIFT_TRANSLATION = 0.02
"""A submap link's uncertainty grows with the way between the two frames: m per square root of the
metres driven (without it the pose graph held a 380 s loop of mit-csail 15 degrees off its closure;
docs/decisions/001-tracking-front-end.md) ..."""
DRIFT_ROTATION = 0.004
"""... and rad per square root of the metres driven."""

RESIDUAL = "point_to_line"
"""A scan point's residual: its distance from its matched cell's tangent line. Armesto et al.'s
curve through the cells (eICP) gained nothing on cell means and cost twice the CPU
(docs/decisions/012-the-other-papers.md); a config's ``[tracking] registration`` is read as this."""

_KEY_STRIDE = 1 << 32
"""Packs a voxel's two cell indices into one int64 key."""


@dataclass(frozen=True)
class ScanSamples:
    """Points along a scan's (or a map's) segments, in its own frame.

    ``normals`` are unit vectors to the left of each segment: for oriented segments (a scan's,
    counter-clockwise) that is towards the free space the laser saw the wall from.
    """

    points: Array
    """``(n, 2)``"""
    normals: Array
    """``(n, 2)``"""
    weights: Array
    """``(n,)``: the wall length (m) each point stands for."""
    support: Array | None = None
    """``(n,)``: the length (m) of the segment each point lies on (None: unknown)."""
    segment: Array | None = None
    """``(n,)``: the index of that segment among those sampled (None: unknown)."""

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def length(self) -> float:
        return float(self.weights.sum())

    def moved(self, pose: Transform2D) -> ScanSamples:
        """The samples in the frame where ``pose`` places their own."""
        c, s = math.cos(pose.theta), math.sin(pose.theta)
        rotation = np.array([[c, s], [-s, c]])
        return ScanSamples(
            self.points @ rotation + (pose.x, pose.y), self.normals @ rotation, self.weights, self.support, self.segment
        )


def sample_segments(segments: Array, spacing: float) -> ScanSamples:
    """Points every ``spacing`` metres along each segment (at least one, at the middle of equal
    stretches), with the segment's left normal, the length of its stretch, the segment's length and its
    index among ``segments`` (a segment of no length gives no point)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(seg) == 0:
        return ScanSamples(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    d = seg[:, 2:4] - seg[:, 0:2]
    length = np.hypot(d[:, 0], d[:, 1])
    keep = np.flatnonzero(length > 1e-9)
    seg, d, length = seg[keep], d[keep], length[keep]
    count = np.maximum(1, np.ceil(length / spacing)).astype(np.int64)
    owner = np.repeat(np.arange(len(seg)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    fraction = (np.arange(int(count.sum())) - first + 0.5) / count[owner]
    points = seg[owner, 0:2] + d[owner] * fraction[:, None]
    normals = np.column_stack([-d[owner, 1], d[owner, 0]]) / length[owner, None]
    return ScanSamples(points, normals, (length / count)[owner], length[owner], keep[owner])


class ReferenceMap:
    """A submap's walls for registration: scan samples averaged per cell of a square grid.

    Each occupied cell keeps the mean of the points that fell in it and the mean of their normals
    (normals that cancel, a thin wall's two sides in one cell, leave the cell without a usable
    normal; it is kept but matches nothing). Inserting is cheap; the cells' index
    (:class:`~fleetmap.shared.core.nearest.CellIndex`) is rebuilt on the next query after one.
    """

    def __init__(self, voxel_size: float) -> None:
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = voxel_size
        self._index: dict[int, int] = {}
        self._sum = np.zeros((0, 2))
        self._normal_sum = np.zeros((0, 2))
        self._weight = np.zeros(0)
        self._count = np.zeros(0)
        self._support = np.zeros(0)
        self._cells: CellIndex | None = None
        self._points = np.zeros((0, 2))
        self._normals = np.zeros((0, 2))
        self._valid = np.zeros(0, dtype=bool)

    def __len__(self) -> int:
        return len(self._weight)

    def insert(self, samples: ScanSamples) -> None:
        """Add samples given in the submap's frame."""
        if len(samples) == 0:
            return
        cells = np.floor(samples.points / self.voxel_size).astype(np.int64)
        keys = cells[:, 0] * _KEY_STRIDE + cells[:, 1]
        slots = np.empty(len(keys), dtype=np.int64)
        size = len(self._weight)
        fresh = size
        for i, key in enumerate(keys.tolist()):
            slot = self._index.get(key)
            if slot is None:
                slot = self._index[key] = fresh
                fresh += 1
            slots[i] = slot
        if fresh > size:
            grow = fresh - size
            self._sum = np.vstack([self._sum, np.zeros((grow, 2))])
            self._normal_sum = np.vstack([self._normal_sum, np.zeros((grow, 2))])
            self._weight = np.concatenate([self._weight, np.zeros(grow)])
            self._count = np.concatenate([self._count, np.zeros(grow)])
            self._support = np.concatenate([self._support, np.zeros(grow)])
        w = samples.weights
        np.add.at(self._sum, slots, samples.points * w[:, None])
        np.add.at(self._normal_sum, slots, samples.normals * w[:, None])
        np.add.at(self._weight, slots, w)
        np.add.at(self._count, slots, 1.0)
        if samples.support is not None:
            np.maximum.at(self._support, slots, samples.support)
        self._cells = None

    def _refresh(self) -> None:
        if self._cells is not None:
            return
        self._points = self._sum / self._weight[:, None]
        norm = np.hypot(self._normal_sum[:, 0], self._normal_sum[:, 1])
        # a cell whose normals mostly cancel (both sides of a thin wall) has no side
        self._valid = norm > 0.5 * self._weight
        self._normals = self._normal_sum / np.maximum(norm, 1e-12)[:, None]
        self._cells = CellIndex(self._points, self._valid, self.voxel_size)

    @property
    def points(self) -> Array:
        self._refresh()
        return self._points

    @property
    def normals(self) -> Array:
        self._refresh()
        return self._normals

    @property
    def support(self) -> Array:
        """For each cell, the longest segment that put a sample in it (m)."""
        return self._support

    @property
    def weights(self) -> Array:
        """The wall length each cell stands for: its samples' mean (a wall seen many times
        counts once)."""
        return self._weight / np.maximum(self._count, 1.0)

    def nearest(self, points: Array, radius: float) -> tuple[Array, Array]:
        """For each point, the nearest cell within ``radius`` (index; -1 where none) and its distance."""
        self._refresh()
        if len(self._weight) == 0 or len(points) == 0:
            return np.full(len(points), -1, dtype=np.int64), np.full(len(points), math.inf)
        cells = self._cells
        if cells is None:  # pragma: no cover - _refresh built it
            raise RuntimeError("the reference map has no index")
        return cells.query(points, radius)


@dataclass(frozen=True)
class Registration:
    """The outcome of registering a scan on a submap."""

    pose: Transform2D
    """The scan's pose in the submap's frame."""
    information: Array
    """``(3, 3)``: how firmly the fit fixes (x, y, theta), prior included (the inverse covariance)."""
    scan_information: Array
    """``(3, 3)``: the same from the walls alone, without the prior (small eigenvalues: directions
    the walls leave free, such as along a featureless corridor)."""
    matched_length: float
    """Wall length of the scan (m) within the final correspondence radius of a submap wall facing
    the same way."""
    matched_share: float
    """``matched_length`` over the scan's whole wall length."""
    rms: float
    """Root mean square of the matched residuals (m)."""
    iterations: int
    converged: bool
    score: float = 0.0
    """The robust fit's support: the matched wall length (m), each point weighted by the Cauchy
    loss's weight at its residual in the last stage. Between two fits of one scan on one submap
    (from two predictions), the higher is the better."""

    @property
    def covariance(self) -> Array:
        return np.linalg.inv(self.information)


def _rotation(theta: float) -> Array:
    """The matrix that rotates row vectors by ``theta`` (``v @ R``)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, s], [-s, c]])


def correspondence_schedule() -> list[tuple[float, float]]:
    """The registration's stages: (correspondence radius, Cauchy scale) in metres, coarse to fine."""
    stages = []
    radius = MAX_CORRESPONDENCE
    while radius > MIN_CORRESPONDENCE * 1.001:
        stages.append(radius)
        radius /= 2.0
    stages.append(MIN_CORRESPONDENCE)
    return [(r, r * LOSS_SCALE) for r in stages]


def _linearize(
    scan: ScanSamples,
    reference: ReferenceMap,
    x: Array,
    radius: float,
    scale: float,
    sigma2: float,
    cos_normals: float,
) -> tuple[Array, Array, Array, Array, Array]:
    """One Gauss-Newton linearisation of :func:`register`'s residuals at the pose ``x``: the scan's
    points matched within ``radius`` (their rows), their point-to-line residuals, their Cauchy
    weights at ``scale``, and the residuals' Jacobian, plain and weighted."""
    rot = _rotation(x[2])
    moved = scan.points @ rot + x[:2]
    index, _ = reference.nearest(moved, radius)
    found = index >= 0
    q = reference.points[index[found]]
    n = reference.normals[index[found]]
    facing = ((scan.normals[found] @ rot) * n).sum(axis=1) >= cos_normals
    rows = np.flatnonzero(found)[facing]
    q, n = q[facing], n[facing]
    p = moved[rows]
    residuals = ((p - q) * n).sum(axis=1)
    # Cauchy loss: weight 1 / (1 + (r / c)^2), times the wall length the point stands for
    w = scan.weights[rows] / (1.0 + (residuals / scale) ** 2)
    arm = p - x[:2]
    jac = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * arm[:, 0] - n[:, 0] * arm[:, 1]])
    jw = jac * (w / sigma2)[:, None]
    return rows, residuals, w, jac, jw


def register(
    scan: ScanSamples,
    reference: ReferenceMap,
    initial: Transform2D,
    prior: Transform2D,
    prior_information: Array,
    params: TrackingParams,
) -> Registration:
    """The scan's pose on the submap: robust point-to-line ICP from ``initial``, pulled towards
    ``prior`` with ``prior_information`` (3x3, on x, y, theta in the submap's frame).

    The coarse stages widen the basin a fit reaches from ``initial``; they can also carry it out of
    the right one, a metre's radius matching walls to their neighbours. A descent must not end
    worse than it started: when the answer's objective at the fine stage (its robust cost, a point
    with no wall within the radius costing as one at the radius, plus the prior's) is higher than
    ``initial``'s own, the fine stage alone is run from ``initial``, and the lower of the two is
    taken. The case: freiburg-101-corrected's scan 93, a 1 m, 24 degree step predicted right by
    odometry, settled 7 degrees and 0.13 m off, its fine-stage support down from 2.5 m of wall at
    the prediction to 2.1 m (docs/decisions/015-a-descent-that-ends-no-worse.md)."""
    schedule = correspondence_schedule()
    start, mu = initial.as_array(), prior.as_array()
    run = _gauss_newton(scan, reference, start, mu, prior_information, schedule)
    radius, scale = schedule[-1]
    ended = _objective(scan, reference, run.x, mu, prior_information, radius, scale)
    if len(schedule) > 1 and ended > _objective(scan, reference, start, mu, prior_information, radius, scale):
        fine = _gauss_newton(scan, reference, start, mu, prior_information, schedule[-1:])
        if _objective(scan, reference, fine.x, mu, prior_information, radius, scale) < ended:
            run = fine
    inliers = np.abs(run.residuals) <= run.radius
    total = scan.length
    matched_length = float(scan.weights[run.matched].sum()) if len(scan) else 0.0
    rms = float(np.sqrt(np.mean(run.residuals[inliers] ** 2))) if inliers.any() else math.inf
    return Registration(
        Transform2D.from_array(run.x),
        run.h_scan + prior_information,
        run.h_scan,
        matched_length,
        matched_length / total if total > 0 else 0.0,
        rms,
        run.iterations,
        run.converged,
        float(run.w.sum()) if len(run.residuals) else 0.0,
    )


@dataclass(frozen=True)
class _Run:
    """Where one Gauss-Newton run of :func:`register` ended, with its last linearisation."""

    x: Array
    h_scan: Array
    matched: Array
    residuals: Array
    w: Array
    radius: float
    iterations: int
    converged: bool


def _gauss_newton(
    scan: ScanSamples,
    reference: ReferenceMap,
    x: Array,
    mu: Array,
    prior_information: Array,
    schedule: list[tuple[float, float]],
) -> _Run:
    """Robust Gauss-Newton from ``x`` through the ``schedule``'s stages (:func:`register`)."""
    stage = 0
    radius, scale = schedule[0]
    since = 0
    sigma2 = RESIDUAL_SIGMA**2
    cos_normals = math.cos(MAX_NORMAL_ANGLE)
    h_scan = np.zeros((3, 3))
    matched = np.zeros(len(scan), dtype=bool)
    residuals = np.zeros(0)
    w = np.zeros(0)
    converged = False
    iterations = 0
    for iterations in range(1, MAX_ITERATIONS + 1):
        rows, residuals, w, jac, jw = _linearize(scan, reference, x, radius, scale, sigma2, cos_normals)
        h_scan = jw.T @ jac
        error = x - mu
        error[2] = float(wrap_angle(error[2]))
        g = jw.T @ residuals + prior_information @ error
        try:
            step = -np.linalg.solve(h_scan + prior_information, g)
        except np.linalg.LinAlgError:
            break
        x = x + step
        matched = np.zeros(len(scan), dtype=bool)
        matched[rows] = True
        small = math.hypot(step[0], step[1]) < CONVERGENCE_TRANSLATION and abs(step[2]) < (CONVERGENCE_ROTATION)
        if small and stage == len(schedule) - 1:
            converged = True
            break
        if small or iterations - since >= ITERATIONS_PER_STAGE:
            stage = min(stage + 1, len(schedule) - 1)
            radius, scale = schedule[stage]
            since = iterations
    return _Run(x, h_scan, matched, residuals, w, radius, iterations, converged)


def _objective(
    scan: ScanSamples, reference: ReferenceMap, x: Array, mu: Array, information: Array, radius: float, scale: float
) -> float:
    """What :func:`register`'s stage at ``radius`` and ``scale`` minimises, at ``x``: each point's
    Cauchy loss, weighted by its wall length, a point matching no wall as one at ``radius``, plus
    the prior's Mahalanobis term."""
    sigma2 = RESIDUAL_SIGMA**2
    rows, residuals, _w, _jac, _jw = _linearize(scan, reference, x, radius, scale, sigma2, math.cos(MAX_NORMAL_ANGLE))
    distance = np.full(len(scan), radius)
    distance[rows] = np.minimum(np.abs(residuals), radius)
    data = float((scan.weights * np.log1p((distance / scale) ** 2)).sum()) * scale**2 / (2.0 * sigma2)
    error = x - mu
    error[2] = float(wrap_angle(error[2]))
    return data + 0.5 * float(error @ information @ error)


def see_through(reference: ReferenceMap, scan: RangeScan, pose: Transform2D, max_range: float) -> tuple[float, float]:
    """Wall of the submap the scan's beams pass through, at ``pose`` (the scan's pose in the
    submap): ``(violating length, visible length)`` in metres.

    A submap wall point is *visible* when it lies within the laser's field of view and reach,
    faces the laser, its beam returned something, and it lies on a wall wide enough for that beam
    to hit: its segment spans :data:`SEE_THROUGH_BEAMS` beams at its range (a chair leg that one beam
    hits and the next misses is not a wall the next one saw through). It is *seen through* when its
    beam's return lies beyond it by more than the margin: :data:`SEE_THROUGH_MARGIN`, plus the range
    change that a heading error of :data:`SEE_THROUGH_SLOPE` radians makes on a wall at that range and
    incidence (``r * slope * tan(incidence)``: a wall seen at a grazing angle moves far along the
    beam when the heading moves a little). A beam that returned nothing says little (glass, a dark
    surface) and counts for neither.
    """
    if len(reference) == 0:
        return 0.0, 0.0
    visible, through = see_through_masks(reference, scan, pose, max_range)
    weights = reference.weights
    return float(weights[through].sum()), float(weights[visible].sum())


def beam_evidence(
    reference: ReferenceMap,
    scan: RangeScan,
    pose: Transform2D,
    max_range: float,
    margin: tuple[float, float] = SEE_THROUGH,
) -> tuple[float, float]:
    """What the scan's beams say of the submap's walls at ``pose``: ``(through, hit)``, the wall
    length (m) they pass through and the length they return from (:func:`beam_test`). A beam that
    returns short of a wall (something in between) or returns nothing says neither: the beam
    model's short and max readings (Thrun, Burgard & Fox 2005, 6.3). Nor does one beyond
    ``max_range``, as extraction reads it: a log's no-return reading (81.91 m) is written as a
    range, and read as one it passes through every wall. (A fit is still refused by
    :func:`see_through`, which counts those: refusing costs a scan, concluding a kidnap an epoch.)"""
    if len(reference) == 0:
        return 0.0, 0.0
    points, normals, support = reference.points, reference.normals, reference.support
    _, through, hit = beam_test(points, normals, support, scan, pose, max_range, max_range, margin)
    weights = reference.weights
    return float(weights[through].sum()), float(weights[hit].sum())


def see_through_masks(
    reference: ReferenceMap, scan: RangeScan, pose: Transform2D, max_range: float
) -> tuple[Array, Array]:
    """:func:`see_through`'s cells: which are visible, and which of those are seen through."""
    visible, through, _ = beam_test(reference.points, reference.normals, reference.support, scan, pose, max_range)
    return visible, through


def beam_test(
    points: Array,
    normals: Array,
    support: Array,
    scan: RangeScan,
    pose: Transform2D,
    max_range: float,
    no_return_beyond: float = math.inf,
    margin: tuple[float, float] = SEE_THROUGH,
) -> tuple[Array, Array, Array]:
    """The test of :func:`see_through` on wall points (their normals, and the length of the wall
    each lies on): which are visible to the scan at ``pose``, which of those its beams pass
    through, and which of those its beams return from (within the same margin: ``margin`` is its
    fixed part and its slope, :data:`SEE_THROUGH`). A reading beyond ``no_return_beyond`` counts as
    no return."""
    reach = min(scan.range_max, max_range)
    row = (scan.ranges, pose.x, pose.y, pose.theta, scan.angle_min, scan.angle_increment, scan.range_max, reach)
    codes = beam_codes(points, normals, support, SEE_THROUGH_BEAMS, [(*row, no_return_beyond)], margin)[0]
    visible, through, hit = codes != NONE, codes == THROUGH, codes == HIT
    return visible, through, hit


def wall_evidence(
    segments: Array,
    scans: list[tuple[RangeScan, Transform2D]],
    max_range: float,
    no_return_beyond: float = math.inf,
    margin: tuple[float, float] = SEE_THROUGH,
) -> tuple[Array, Array]:
    """For each wall of a submap, what its own scans (each with its pose in the submap) say of it:
    ``(seen, through)``, the wall length (m, summed over the scans) their beams returned from, and
    the length they passed through (:func:`beam_test`). A wall stands where the scans saw it; a
    person walking past, a door swinging, a cart pushed by, is seen in a few scans and seen
    through in the others that look at where it was (the hit and miss counts of an occupancy
    grid, Thrun, Burgard & Fox 2005, 9.2, kept per wall)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    seen, through = np.zeros(len(seg)), np.zeros(len(seg))
    if len(seg) == 0 or not scans:
        return seen, through
    samples = sample_segments(seg, SAMPLE_SPACING)
    owner, support = samples.segment, samples.support
    if owner is None or support is None:  # pragma: no cover - sample_segments gives both
        raise RuntimeError("the wall samples do not say which wall each lies on")
    rows = [
        (
            scan.ranges,
            pose.x,
            pose.y,
            pose.theta,
            scan.angle_min,
            scan.angle_increment,
            scan.range_max,
            reach,
            no_return_beyond,
        )
        for scan, pose in scans
        for reach in [min(scan.range_max, max_range)]
    ]
    codes = beam_codes(samples.points, samples.normals, support, SEE_THROUGH_BEAMS, rows, margin)
    for code in codes:  # scan by scan: a wall seen as often as seen through is kept, to the bit
        hit, passed = code == HIT, code == THROUGH
        seen += np.bincount(owner[hit], weights=samples.weights[hit], minlength=len(seg))
        through += np.bincount(owner[passed], weights=samples.weights[passed], minlength=len(seg))
    return seen, through


REACH_ROTATION = math.radians(5.0)
"""How far in heading a registration (:func:`register`) started from one pose settles into the same
minimum as one started from another; in translation, :data:`MAX_CORRESPONDENCE`. The
tracker's second starts, the merger's near search and its join check all read it."""


def drift_covariance(distance: float) -> Array:
    """What tracking adds up over ``distance`` metres driven (a random walk, :data:`DRIFT_TRANSLATION`,
    :data:`DRIFT_ROTATION`)."""
    d = max(distance, 0.0)
    t, r = DRIFT_TRANSLATION**2 * d, DRIFT_ROTATION**2 * d
    return np.diag([t, t, r])
