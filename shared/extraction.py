"""Segments from a range scan (paper III-D).

1. Drop no-return beams and beams beyond ``max_range``.
2. Cluster: consecutive points (counter-clockwise order) closer than tau are in the same cluster.
3. Split: approximate each cluster by a polyline, starting from the chord between its first and
   last points and adding the farthest point as a new vertex until every point is within kappa.
4. Merge and fit (fleetmap, ``line_fit``; off gives the paper's polylines): with real sensor
   noise (1 cm, or the 5 cm range quantisation of some logs) step 3 cuts a straight wall into
   many short pieces wherever one reading strays beyond kappa. Adjacent pieces are merged again
   while the points of both fit one line (total least squares) with an RMS residual within
   kappa / 2 and no point farther than 2 kappa; each piece then lies on its fitted line, and
   adjacent pieces meet where their lines cross. This is split-and-merge (Pavlidis & Horowitz
   1974), the usual companion of the split step the paper cites.

Segments keep the scan order (the map is ``ordered``) and run counter-clockwise, so the sensor
lies on the left of every segment (``oriented``).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from fleetmap.shared.config import ExtractionParams
from fleetmap.shared.geometry import Array, point_segment_distance
from fleetmap.shared.scans import RangeScan


def scan_points(scan: RangeScan, max_range: float) -> Array:
    """Cartesian points ``(m, 2)`` of the beams with a return within ``max_range``, in beam order."""
    return _returns(scan, max_range)[0]


def _returns(scan: RangeScan, max_range: float) -> tuple[Array, Array]:
    """The points of the beams with a return, and their beam indices."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    idx = np.arange(r.shape[0])
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > 0.0) & (r < scan.range_max) & (r <= max_range)
    a = scan.angle_min + idx[ok] * scan.angle_increment
    rr = r[ok]
    return np.column_stack([rr * np.cos(a), rr * np.sin(a)]), idx[ok]


def clusters(
    points: Array, tau: float, step: float = 0.0, breakpoint_angle: float = 0.0, beams: Array | None = None
) -> list[Array]:
    """Runs of consecutive points whose successive distances are below the threshold (III-D, step 1).

    The threshold is tau (the paper). With a ``breakpoint_angle`` lambda it grows with range as in
    the adaptive breakpoint detector (Borges & Aldon 2004): two beams ``step`` apart hitting a wall
    seen at incidence lambda land ``r sin(step) / sin(lambda - step)`` apart, so a corridor wall
    seen at a grazing angle stays one cluster instead of falling apart into lone points. It
    applies between neighbouring beams only (``beams`` gives each point's beam index): across
    beams that returned nothing, tau holds.
    """
    if len(points) == 0:
        return []
    gaps = np.hypot(*np.diff(points, axis=0).T)
    limit = np.full(len(gaps), tau)
    if breakpoint_angle > step > 0:
        r = np.hypot(points[:-1, 0], points[:-1, 1])
        adaptive = tau + r * math.sin(step) / math.sin(breakpoint_angle - step)
        if beams is not None:
            adaptive = np.where(np.diff(beams) == 1, adaptive, tau)
        limit = np.maximum(limit, adaptive)
    cuts = np.flatnonzero(gaps >= limit) + 1
    return np.split(points, cuts)


def split_polyline(points: Array, kappa: float) -> list[int]:
    """Indices of the polyline vertices approximating ``points`` within kappa (III-D, step 2)."""
    n = len(points)
    if n < 2:
        return []
    vertices = {0, n - 1}
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        inner = points[i + 1 : j]
        chord = np.concatenate([points[i], points[j]])
        d = point_segment_distance(inner, chord[None, :])
        k = int(np.argmax(d))
        if d[k] > kappa:
            m = i + 1 + k
            vertices.add(m)
            stack.append((i, m))
            stack.append((m, j))
    return sorted(vertices)


def vertex_runs(points: Array, vertices: list[int], tau: float) -> list[list[int]]:
    """The polyline cut at *bridges*: pieces joining two consecutive points further apart than tau.

    With the adaptive breakpoint a cluster may hold a jump between two objects; the split step
    turns it into a piece with no point inside, which is not a wall.
    """
    runs: list[list[int]] = [[vertices[0]]] if vertices else []
    for a, b in itertools.pairwise(vertices):
        if b - a == 1 and np.hypot(*(points[b] - points[a])) > tau:
            runs.append([b])
        else:
            runs[-1].append(b)
    return [r for r in runs if len(r) >= 2]


def _moments(points: Array) -> Array:
    """Sufficient statistics of a point set for a line fit: n, sum x, sum y, sum xx, sum xy, sum yy."""
    x = points[:, 0]
    y = points[:, 1]
    return np.array([len(points), x.sum(), y.sum(), (x * x).sum(), (x * y).sum(), (y * y).sum()])


def _line_from_moments(m: Array) -> tuple[Array, Array, float]:
    """Centroid, unit direction and mean squared residual of the total least squares line."""
    n = m[0]
    c = np.array([m[1] / n, m[2] / n])
    sxx = m[3] / n - c[0] * c[0]
    sxy = m[4] / n - c[0] * c[1]
    syy = m[5] / n - c[1] * c[1]
    evals, evecs = np.linalg.eigh(np.array([[sxx, sxy], [sxy, syy]]))
    return c, evecs[:, 1], max(float(evals[0]), 0.0)


def merge_pieces(points: Array, vertices: list[int], kappa: float) -> list[tuple[int, int]]:
    """Merge adjacent polyline pieces that fit one line (step 4); returns inclusive index ranges."""
    pieces = [(vertices[k], vertices[k + 1]) for k in range(len(vertices) - 1)]
    moments = [_moments(points[i : j + 1]) for i, j in pieces]
    rms_limit = (0.5 * kappa) ** 2
    while len(pieces) > 1:
        best, best_cost = -1, rms_limit
        for k in range(len(pieces) - 1):
            m = moments[k] + moments[k + 1] - _moments(points[pieces[k][1] : pieces[k][1] + 1])
            _, _, mse = _line_from_moments(m)
            if mse <= best_cost:
                c, u, _ = _line_from_moments(m)
                seg = points[pieces[k][0] : pieces[k + 1][1] + 1] - c
                if np.abs(seg[:, 0] * u[1] - seg[:, 1] * u[0]).max() <= 2.0 * kappa:
                    best, best_cost = k, mse
        if best < 0:
            break
        shared = points[pieces[best][1] : pieces[best][1] + 1]
        moments[best] = moments[best] + moments[best + 1] - _moments(shared)
        pieces[best] = (pieces[best][0], pieces[best + 1][1])
        del pieces[best + 1], moments[best + 1]
    return pieces


def fitted_polyline(points: Array, pieces: list[tuple[int, int]]) -> Array:
    """Segments on the fitted lines of ``pieces``; neighbours meet where their lines cross."""
    # A two-point piece between two walls is the cut across a corner that fell between two
    # beams: drop it, so the walls meet where their lines cross.
    pieces = [
        pc
        for k, pc in enumerate(pieces)
        if not (
            0 < k < len(pieces) - 1
            and pc[1] - pc[0] == 1
            and pieces[k - 1][1] - pieces[k - 1][0] > 1
            and pieces[k + 1][1] - pieces[k + 1][0] > 1
        )
    ]
    lines = [_line_from_moments(_moments(points[i : j + 1]))[:2] for i, j in pieces]

    def project(p: Array, line: tuple[Array, Array]) -> Array:
        c, u = line
        return c + u * float(np.dot(p - c, u))

    ends = []
    for k, (i, j) in enumerate(pieces):
        ends.append([project(points[i], lines[k]), project(points[j], lines[k])])
    for k in range(len(pieces) - 1):
        (c1, u1), (c2, u2) = lines[k], lines[k + 1]
        det = u1[0] * u2[1] - u1[1] * u2[0]
        vertex = 0.5 * (points[pieces[k][1]] + points[pieces[k + 1][0]])
        if abs(det) > 0.17:  # lines more than ~10 degrees apart: a corner, put it where they cross
            d = c2 - c1
            s = (d[0] * u2[1] - d[1] * u2[0]) / det
            cross = c1 + s * u1
            if np.hypot(*(cross - vertex)) < 0.1:
                ends[k][1] = cross
                ends[k + 1][0] = cross
                continue
        mid = 0.5 * (ends[k][1] + ends[k + 1][0])
        ends[k][1] = mid
        ends[k + 1][0] = mid
    return np.array([[a[0], a[1], b[0], b[1]] for a, b in ends])


def range_noise(points: Array, beams: Array) -> float:
    """A scan's noise (m): the median distance of each point from the chord of its two neighbours,
    over the triples of neighbouring beams that lie within NOISE_SPAN of each other (on one
    wall, mostly; a corner's few triples do not move the median). 0 for a scan with no such triple."""
    if len(points) < 3:
        return 0.0
    a, b, c = points[:-2], points[1:-1], points[2:]
    chord = c - a
    length = np.hypot(chord[:, 0], chord[:, 1])
    ok = (beams[2:] - beams[:-2] == 2) & (length > 1e-9) & (length <= NOISE_SPAN)
    if not ok.any():
        return 0.0
    d = b[ok] - a[ok]
    u = chord[ok] / length[ok, None]
    return float(np.median(np.abs(d[:, 0] * u[:, 1] - d[:, 1] * u[:, 0])))


NOISE_SPAN = 0.3
"""Neighbouring beams whose outer two points lie farther apart than this (m) do not measure noise."""


def kappa_for(noise: float, p: ExtractionParams) -> float:
    """The polyline tolerance for a scan of this ``noise``: ``kappa_noise_factor`` times it where
    that exceeds kappa by more than NOISY, kappa otherwise. Merging pieces needs an RMS residual
    within kappa / 2, so a laser of noise sigma (a noise reading of 0.83 sigma) needs about 2.5
    sigma / 0.83: 3 times its noise, and a little more than that still cuts some walls. A clean
    laser's scans read 0.6-1.0 cm (the simulator's 1 cm sigma): without NOISY, some would take
    3 cm instead of 2.5, and their maps come out a little less precise."""
    wide = p.kappa_noise_factor * noise
    return wide if wide > NOISY * p.kappa else p.kappa


NOISY = 1.25
"""A scan's noise sets its kappa only where that is this many times the configured kappa."""


def extract_segments(scan: RangeScan, params: ExtractionParams | None = None) -> Array:
    """The segments ``(n, 4)`` of one scan, in scan order, counter-clockwise."""
    p = params or ExtractionParams()
    out: list[Array] = []
    step = abs(scan.angle_increment)
    points, beams = _returns(scan, p.max_range)
    kappa = kappa_for(range_noise(points, beams), p) if p.kappa_noise_factor > 0 else p.kappa
    for cluster in clusters(points, p.tau, step, p.breakpoint_angle, beams):
        if len(cluster) < max(p.min_cluster_points, 2):
            continue
        for run in vertex_runs(cluster, split_polyline(cluster, kappa), p.tau):
            part = cluster[run[0] : run[-1] + 1]
            vertices = [v - run[0] for v in run]
            if p.line_fit:
                out.append(fitted_polyline(part, merge_pieces(part, vertices, kappa)))
            else:
                v = part[vertices]
                out.append(np.hstack([v[:-1], v[1:]]))
    if not out:
        return np.zeros((0, 4))
    seg = np.vstack(out)
    keep = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) > 1e-6
    return seg[keep]
