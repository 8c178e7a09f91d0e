"""Segments from a range scan (paper III-D).

1. Drop no-return beams and beams beyond ``max_range``.
2. Cluster: consecutive points (counter-clockwise order) closer than tau are in the same cluster.
3. Split: approximate each cluster by a polyline, starting from the chord between its first and
   last points and adding the farthest point as a new vertex until every point is within kappa.
4. Merge and fit (fleetmap, :data:`LINE_FIT`; off gives the paper's polylines): with real sensor
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
from fleetmap.shared.core.geometry import Array
from fleetmap.shared.core.rangescan import RangeScan

LINE_FIT = True
"""Step 4 on: merge split pieces that fit one line (false gives the paper's polylines); with real
lasers' noise step 3 alone cuts straight walls into short pieces (docs/decisions/006)."""
NOISY_KAPPA_SHARE = 1.25
"""A scan's noise sets its polyline tolerance only where that is this many times kappa: keeps a clean
laser (0.6-1.0 cm of noise) at the paper's kappa (docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
NOISE_SPAN = 0.3
"""Neighbouring beams whose outer two points lie farther apart than this (m) do not measure noise
(they straddle a corner or a gap, not one wall)."""
BREAKPOINT_ANGLE = 0.1745
"""Adaptive clustering (Borges & Aldon 2004's lambda, 10 degrees): walls seen at incidence down
to this angle (rad) stay one cluster however far apart their points are."""
MIN_CLUSTER_POINTS = 3
"""Clusters with fewer points give no segment (a lone return is not a wall)."""


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
    return [points[a:b] for a, b in cluster_bounds(points, tau, step, breakpoint_angle, beams)]


def cluster_bounds(
    points: Array, tau: float, step: float = 0.0, breakpoint_angle: float = 0.0, beams: Array | None = None
) -> list[tuple[int, int]]:
    """:func:`clusters` as ``(start, stop)`` index ranges into ``points``."""
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
    cuts = [0, *(np.flatnonzero(gaps >= limit) + 1).tolist(), len(points)]
    return list(itertools.pairwise(cuts))


def split_polyline(points: Array, kappa: float) -> list[int]:
    """Indices of the polyline vertices approximating ``points`` within kappa (III-D, step 2)."""
    n = len(points)
    if n < 2:
        return []
    x = points[:, 0]
    y = points[:, 1]
    vertices = {0, n - 1}
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        # distance of the inner points from the chord (as point_segment_distance, inlined: this
        # loop runs for every vertex of every scan)
        ax, ay = x[i], y[i]
        dx, dy = x[j] - ax, y[j] - ay
        l2 = dx * dx + dy * dy
        px = x[i + 1 : j] - ax
        py = y[i + 1 : j] - ay
        t = np.clip((px * dx + py * dy) / (l2 if l2 > 0 else 1.0), 0.0, 1.0)
        d = np.hypot(px - t * dx, py - t * dy)
        k = int(np.argmax(d))
        if d[k] > kappa:
            m = i + 1 + k
            vertices.add(m)
            stack.append((i, m))
            stack.append((m, j))
    return sorted(vertices)


def split_polylines(points: Array, bounds: list[tuple[int, int]], kappa: float) -> list[list[int]]:
    """:func:`split_polyline` of every cluster ``points[a:b]`` at once, level by level: at each
    level the farthest inner point of every open interval from its chord, for all intervals in one
    pass; the vertices of each cluster are indices into the cluster."""
    x = points[:, 0]
    y = points[:, 1]
    vertices: list[set[int]] = [{a, b - 1} if b - a >= 2 else set() for a, b in bounds]
    owner_of = [k for k, (a, b) in enumerate(bounds) if b - a >= 3]
    open_i = np.array([bounds[k][0] for k in owner_of], dtype=np.int64)
    open_j = np.array([bounds[k][1] - 1 for k in owner_of], dtype=np.int64)
    owner = np.array(owner_of, dtype=np.int64)
    while len(open_i):
        inner = open_j - open_i - 1
        keep = inner > 0
        open_i, open_j, owner, inner = open_i[keep], open_j[keep], owner[keep], inner[keep]
        if not len(open_i):
            break
        interval = np.repeat(np.arange(len(open_i)), inner)
        first = np.repeat(np.cumsum(inner) - inner, inner)
        idx = open_i[interval] + 1 + (np.arange(int(inner.sum())) - first)
        ax, ay = x[open_i][interval], y[open_i][interval]
        dx, dy = x[open_j][interval] - ax, y[open_j][interval] - ay
        l2 = dx * dx + dy * dy
        px, py = x[idx] - ax, y[idx] - ay
        t = np.clip((px * dx + py * dy) / np.where(l2 > 0, l2, 1.0), 0.0, 1.0)
        d = np.hypot(px - t * dx, py - t * dy)
        best = np.maximum.reduceat(d, np.cumsum(inner) - inner)
        # each interval's first point at its maximum, as argmax picks it
        hit = np.flatnonzero(d == best[interval])
        first_hit = np.full(len(open_i), len(d), dtype=np.int64)
        np.minimum.at(first_hit, interval[hit], hit)
        split = best > kappa
        middle = idx[first_hit[split]]
        for o, v in zip(owner[split].tolist(), middle.tolist(), strict=True):
            vertices[o].add(v)
        open_i, open_j = np.concatenate([open_i[split], middle]), np.concatenate([middle, open_j[split]])
        owner = np.concatenate([owner[split], owner[split]])
    return [sorted(v - a for v in vs) for vs, (a, _) in zip(vertices, bounds, strict=True)]


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


def _cumulative_moments(points: Array) -> Array:
    """Prefix sums of the moments of each point: the moments of ``points[i : j + 1]`` are row
    ``j + 1`` less row ``i`` (every piece's fit in O(1))."""
    x = points[:, 0]
    y = points[:, 1]
    rows = np.column_stack([np.ones(len(points)), x, y, x * x, x * y, y * y])
    return np.vstack([np.zeros((1, 6)), np.cumsum(rows, axis=0)])


def _line_from_moments(m: Array) -> tuple[Array, Array, float]:
    """Centroid, unit direction and mean squared residual of the total least squares line."""
    c, (ux, uy), mse = _fit_line(*(float(v) for v in m))
    return np.array(c), np.array([ux, uy]), mse


def _fit_line(
    n: float, sx: float, sy: float, sxx: float, sxy: float, syy: float
) -> tuple[tuple[float, float], tuple[float, float], float]:
    """:func:`_line_from_moments` on plain floats: the 2x2 covariance's eigen pair in closed form."""
    cx, cy = sx / n, sy / n
    vxx = sxx / n - cx * cx
    vxy = sxy / n - cx * cy
    vyy = syy / n - cy * cy
    half = 0.5 * (vxx + vyy)
    root = math.hypot(0.5 * (vxx - vyy), vxy)
    small = half - root
    # the direction: the eigenvector of the larger eigenvalue half + root
    if vxx >= vyy:
        ux, uy = root + 0.5 * (vxx - vyy), vxy
    else:
        ux, uy = vxy, root - 0.5 * (vxx - vyy)
    norm = math.hypot(ux, uy)
    if norm > 0:
        ux, uy = ux / norm, uy / norm
    else:
        ux, uy = 1.0, 0.0
    return (cx, cy), (ux, uy), max(small, 0.0)


def merge_pieces(points: Array, vertices: list[int], kappa: float, cum: Array | None = None) -> list[tuple[int, int]]:
    """Merge adjacent polyline pieces that fit one line (step 4); returns inclusive index ranges.

    Greedy: the adjacent pair whose joint fit has the smallest mean squared residual is merged
    first, while that is within (kappa / 2)^2 and no point lies farther than 2 kappa from the
    joint line. A pair's cost is computed once and again only when one of its pieces changes.
    """
    pieces = [(vertices[k], vertices[k + 1]) for k in range(len(vertices) - 1)]
    if len(pieces) < 2:
        return pieces
    if cum is None:
        cum = _cumulative_moments(points)
    rms_limit = (0.5 * kappa) ** 2

    def cost(a: tuple[int, int], b: tuple[int, int]) -> float:
        """The joint fit's mse, or inf when it is out of bounds (the pieces share a point)."""
        m = (cum[b[1] + 1] - cum[a[0]]).tolist()
        (cx, cy), (ux, uy), mse = _fit_line(*m)
        if mse > rms_limit:
            return math.inf
        seg = points[a[0] : b[1] + 1]
        if np.abs((seg[:, 0] - cx) * uy - (seg[:, 1] - cy) * ux).max() > 2.0 * kappa:
            return math.inf
        return mse

    costs = [cost(pieces[k], pieces[k + 1]) for k in range(len(pieces) - 1)]
    while costs:
        best = min(range(len(costs)), key=lambda k: (costs[k], -k))
        if not math.isfinite(costs[best]):
            break
        pieces[best] = (pieces[best][0], pieces[best + 1][1])
        del pieces[best + 1], costs[best]
        if best > 0:
            costs[best - 1] = cost(pieces[best - 1], pieces[best])
        if best < len(costs):
            costs[best] = cost(pieces[best], pieces[best + 1])
    return pieces


def fitted_polyline(points: Array, pieces: list[tuple[int, int]], cum: Array | None = None) -> Array:
    """Segments on the fitted lines of ``pieces``; neighbours meet where their lines cross."""
    return _fitted_runs(points, [_without_corner_cuts(pieces)], cum)


def _without_corner_cuts(pieces: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """A two-point piece between two walls is the cut across a corner that fell between two
    beams: drop it, so the walls meet where their lines cross."""
    return [
        pc
        for k, pc in enumerate(pieces)
        if not (
            0 < k < len(pieces) - 1
            and pc[1] - pc[0] == 1
            and pieces[k - 1][1] - pieces[k - 1][0] > 1
            and pieces[k + 1][1] - pieces[k + 1][0] > 1
        )
    ]


def _fitted_runs(points: Array, runs: list[list[tuple[int, int]]], cum: Array | None = None) -> Array:
    """:func:`fitted_polyline` of several runs of pieces at once (neighbours meet within a run)."""
    if cum is None:
        cum = _cumulative_moments(points)
    flat = [pc for run in runs for pc in run]
    if not flat:
        return np.zeros((0, 4))
    first = np.array([i for i, _ in flat])
    last = np.array([j for _, j in flat])
    # a junction between consecutive pieces only inside a run: mark the last piece of each run
    joins = np.zeros(len(flat) - 1, dtype=bool)
    k = 0
    for run in runs:
        if run:
            joins[k : k + len(run) - 1] = True
            k += len(run)
    c, u = _lines(cum[last + 1] - cum[first])
    # each piece's ends: its first and last points projected on its line
    start = c + u * ((points[first] - c) * u).sum(axis=1)[:, None]
    end = c + u * ((points[last] - c) * u).sum(axis=1)[:, None]
    if len(flat) > 1:
        c1, u1, c2, u2 = c[:-1], u[:-1], c[1:], u[1:]
        det = u1[:, 0] * u2[:, 1] - u1[:, 1] * u2[:, 0]
        vertex = 0.5 * (points[last[:-1]] + points[first[1:]])
        d = c2 - c1
        with np.errstate(divide="ignore", invalid="ignore"):
            along = (d[:, 0] * u2[:, 1] - d[:, 1] * u2[:, 0]) / det
        cross = c1 + along[:, None] * u1
        # lines more than ~10 degrees apart: a corner, put it where they cross (if near the vertex)
        corner = (np.abs(det) > 0.17) & (np.hypot(*(cross - vertex).T) < 0.1)
        mid = 0.5 * (end[:-1] + start[1:])
        joint = np.where(corner[:, None], cross, mid)
        end[:-1] = np.where(joins[:, None], joint, end[:-1])
        start[1:] = np.where(joins[:, None], joint, start[1:])
    return np.hstack([start, end])


def _lines(m: Array) -> tuple[Array, Array]:
    """Centroids ``(k, 2)`` and unit directions ``(k, 2)`` of the total least squares lines of the
    moments' rows (:func:`_fit_line`, vectorised)."""
    n = m[:, 0]
    cx, cy = m[:, 1] / n, m[:, 2] / n
    vxx = m[:, 3] / n - cx * cx
    vxy = m[:, 4] / n - cx * cy
    vyy = m[:, 5] / n - cy * cy
    half = 0.5 * (vxx - vyy)
    root = np.hypot(half, vxy)
    ux = np.where(vxx >= vyy, root + half, vxy)
    uy = np.where(vxx >= vyy, vxy, root - half)
    norm = np.hypot(ux, uy)
    safe = norm > 0
    ux = np.where(safe, ux / np.where(safe, norm, 1.0), 1.0)
    uy = np.where(safe, uy / np.where(safe, norm, 1.0), 0.0)
    return np.column_stack([cx, cy]), np.column_stack([ux, uy])


def range_noise(points: Array, beams: Array, span: float = 0.3) -> float:
    """A scan's noise (m): the median distance of each point from the chord of its two neighbours,
    over the triples of neighbouring beams that lie within ``span`` (m) of each other (:data:`NOISE_SPAN`) (on one
    wall, mostly; a corner's few triples do not move the median). 0 for a scan with no such triple."""
    if len(points) < 3:
        return 0.0
    a, b, c = points[:-2], points[1:-1], points[2:]
    chord = c - a
    length = np.hypot(chord[:, 0], chord[:, 1])
    ok = (beams[2:] - beams[:-2] == 2) & (length > 1e-9) & (length <= span)
    if not ok.any():
        return 0.0
    d = b[ok] - a[ok]
    u = chord[ok] / length[ok, None]
    return float(np.median(np.abs(d[:, 0] * u[:, 1] - d[:, 1] * u[:, 0])))


def kappa_for(noise: float, p: ExtractionParams) -> float:
    """The polyline tolerance for a scan of this ``noise``: ``kappa_noise_factor`` times it where
    that exceeds kappa :data:`NOISY_KAPPA_SHARE` times, kappa otherwise. Merging pieces needs an RMS
    residual within kappa / 2, so a laser of noise sigma (a noise reading of 0.83 sigma) needs
    about 2.5 sigma / 0.83: 3 times its noise, and a little more than that still cuts some walls.
    :data:`NOISY_KAPPA_SHARE` keeps a clean laser (the simulator's 1 cm sigma) at kappa
    (docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
    wide = p.kappa_noise_factor * noise
    return wide if wide > NOISY_KAPPA_SHARE * p.kappa else p.kappa


def extract_segments(scan: RangeScan, params: ExtractionParams | None = None) -> Array:
    """The segments ``(n, 4)`` of one scan, in scan order, counter-clockwise."""
    p = params or ExtractionParams()
    out: list[Array] = []
    step = abs(scan.angle_increment)
    points, beams = _returns(scan, p.max_range)
    kappa = kappa_for(range_noise(points, beams, NOISE_SPAN), p) if p.kappa_noise_factor > 0 else p.kappa
    cum = _cumulative_moments(points) if LINE_FIT else None
    runs: list[list[tuple[int, int]]] = []
    bounds = [(a, b) for a, b in cluster_bounds(points, p.tau, step, BREAKPOINT_ANGLE, beams)]
    bounds = [(a, b) for a, b in bounds if b - a >= max(MIN_CLUSTER_POINTS, 2)]
    for (a, b), vertices in zip(bounds, split_polylines(points, bounds, kappa), strict=True):
        cluster = points[a:b]
        for run in vertex_runs(cluster, vertices, p.tau):
            if LINE_FIT:
                runs.append(_without_corner_cuts(merge_pieces(points, [a + v for v in run], kappa, cum)))
            else:
                v = cluster[run]
                out.append(np.hstack([v[:-1], v[1:]]))
    if runs:
        out.append(_fitted_runs(points, runs, cum))
    if not out:
        return np.zeros((0, 4))
    seg = np.vstack(out)
    keep = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) > 1e-6
    return seg[keep]
