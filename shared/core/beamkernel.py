"""The beam test's inner loop, compiled: wall points against the beams of one scan or many.

A submap's walls are judged by its own scans each time it is published
(:func:`fleetmap.shared.core.tracking.wall_evidence`): every wall sample against every scan's beam
at its bearing. In numpy that is twenty passes over the samples for each scan, about thirty scans
a submap, a dozen publications a submap; it was a sixth of the tracking time of a real log
(mit-csail: 6.0 of 37.9 s, 25,592 calls of the numpy test). One compiled loop (Numba) does the
same arithmetic in one pass per scan, all of a submap's scans in one call.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
call, so a process that never tests beams never pays for it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array

NONE, VISIBLE, THROUGH, HIT = 0, 1, 2, 3
"""What a scan's beam says of a wall point (:func:`beam_codes`): not visible to it; visible, the
return neither through it nor on it; its beam passes through it; its beam returns from it."""


def _build() -> Callable[..., None]:
    import numba

    @numba.njit(cache=True, nogil=True)
    def codes(px, py, nx, ny, wide_per_metre, support, ranges, starts, scans, margin, out):
        # scans: one row per scan (x, y, theta, angle_min, angle_increment, range_max, reach,
        # no_return_beyond); its beams are ranges[starts[s]:starts[s + 1]]; out: (scans, points)
        n = len(px)
        for s in range(scans.shape[0]):
            x, y, th = scans[s, 0], scans[s, 1], scans[s, 2]
            angle_min, increment, range_max = scans[s, 3], scans[s, 4], scans[s, 5]
            reach, no_return_beyond = scans[s, 6], scans[s, 7]
            first = starts[s]
            beams = starts[s + 1] - first
            c, sn = np.cos(-th), np.sin(-th)
            for p in range(n):
                dx, dy = px[p] - x, py[p] - y
                lx = dx * c - dy * sn
                ly = dx * sn + dy * c
                tx = nx[p] * c - ny[p] * sn
                ty = nx[p] * sn + ny[p] * c
                distance = np.hypot(lx, ly)
                beam = np.int64(np.rint((np.arctan2(ly, lx) - angle_min) / increment))
                cos_incidence = -(tx * lx + ty * ly) / max(distance, 1e-9)
                wide = support[p] >= wide_per_metre * distance * abs(increment)
                out[s, p] = NONE
                if not (cos_incidence > 0.0 and wide and beam >= 0 and beam < beams):
                    continue
                if not (distance < reach and distance > 0.05):
                    continue
                measured = ranges[first + beam]
                if not (np.isfinite(measured) and measured > 0 and measured < range_max):
                    continue
                if not measured <= no_return_beyond:
                    continue
                cos_i = min(max(cos_incidence, 1e-3), 1.0)
                tan_incidence = np.sqrt(1.0 - cos_i**2) / cos_i
                beyond = margin[0] + margin[1] * distance * max(tan_incidence, 1.0)
                if measured > distance + beyond:
                    out[s, p] = THROUGH
                elif abs(measured - distance) <= beyond:
                    out[s, p] = HIT
                else:
                    out[s, p] = VISIBLE

    return codes


_codes = Compiled(_build)


def beam_codes(
    points: Array,
    normals: Array,
    support: Array,
    wide_beams: float,
    scans: list[tuple[Array, float, float, float, float, float, float, float, float]],
    margin: tuple[float, float],
) -> Array:
    """``(len(scans), len(points))`` int8: for each scan, what its beams say of each wall point
    (:data:`NONE`, :data:`VISIBLE`, :data:`THROUGH`, :data:`HIT`), as
    :func:`fleetmap.shared.core.tracking.beam_test` decides it. Each scan is ``(ranges, x, y, theta,
    angle_min, angle_increment, range_max, reach, no_return_beyond)``: its pose, its beams, how far
    a wall can be to be visible (``reach``) and the reading beyond which a beam returned nothing.
    ``wide_beams``: the beams a wall must span at its range to be one a beam can see through."""
    out = np.zeros((len(scans), len(points)), np.int8)
    if not scans or len(points) == 0:
        return out
    lengths = np.array([len(s[0]) for s in scans], dtype=np.int64)
    starts = np.zeros(len(scans) + 1, dtype=np.int64)
    np.cumsum(lengths, out=starts[1:])
    ranges = np.concatenate([np.asarray(s[0], dtype=np.float64) for s in scans])
    rows = np.array([s[1:] for s in scans], dtype=np.float64).reshape(len(scans), 8)
    p = np.ascontiguousarray(points, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    _codes(
        p[:, 0].copy(),
        p[:, 1].copy(),
        n[:, 0].copy(),
        n[:, 1].copy(),
        float(wide_beams),
        np.ascontiguousarray(support, dtype=np.float64),
        ranges,
        starts,
        rows,
        (float(margin[0]), float(margin[1])),
        out,
    )
    return out
