"""A scan's support over a window of positions, every position at once (pure core).

Registration (:func:`fleetmap.shared.core.tracking.register`) settles into the minimum nearest its
start; a prior wider than its reach holds many. A correlative matcher scores every pose of the
prior's window on a grid and takes the best (Olson, "Real-time correlative scan matching", ICRA
2009, Section III: the exhaustive search over a window, each pose scored by a lookup of the
scan's points in a rasterized map). :func:`window_support` scores translations at one heading, the
heading the walls gave the first fit: the scan's wall length whose points fall in a cell of a
grid ``match`` fine that lies within ``match`` of a reference wall.
"""

from __future__ import annotations

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.tracking import ReferenceMap, ScanSamples
from scipy.ndimage import binary_dilation

__all__ = ["window_support"]

CHUNK_LOOKUPS = 1 << 18
"""Lookups done at once (a window of thousands of positions times a scan's points at once would be
arrays of a gigabyte)."""


def window_support(
    reference: ReferenceMap,
    samples: ScanSamples,
    center: Transform2D,
    radius: float,
    spacing: float,
    match: float,
) -> tuple[Array, Array]:
    """The positions ``(c, 2)`` of a square grid ``spacing`` apart within ``radius`` of ``center``
    (the reference's frame) where the scan can overlap the reference and, for each, the wall
    length (m) of ``samples`` placed there at ``center``'s heading whose points lie within about
    ``match`` of a reference wall (the lookup table's cells are ``match`` wide)."""
    if len(samples) == 0 or len(reference) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    turned = samples.moved(Transform2D(0.0, 0.0, center.theta))
    # only where the scan can overlap the reference at all: a window as wide as a broken clock
    # makes it (stamps 4e9 s apart) is as large as the reference, not the clock's guess
    walls = reference.points
    lowest = walls.min(axis=0) - turned.points.max(axis=0) - match - np.array([center.x, center.y])
    highest = walls.max(axis=0) - turned.points.min(axis=0) + match - np.array([center.x, center.y])
    lo = np.ceil(np.maximum(lowest, -radius) / spacing).astype(np.int64)
    hi = np.floor(np.minimum(highest, radius) / spacing).astype(np.int64)
    if np.any(hi < lo):
        return np.zeros((0, 2)), np.zeros(0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1) * spacing, np.arange(lo[1], hi[1] + 1) * spacing, indexing="ij")
    inside = np.hypot(gx, gy) <= radius + 1e-9
    positions = np.column_stack([gx[inside] + center.x, gy[inside] + center.y])
    if len(positions) == 0:
        return positions, np.zeros(0)
    # the lookup table: the reference's walls over the window's reach, dilated by one cell
    low = positions.min(axis=0) + turned.points.min(axis=0) - 2 * match
    high = positions.max(axis=0) + turned.points.max(axis=0) + 2 * match
    shape = np.ceil((high - low) / match).astype(np.int64) + 1
    table = np.zeros(tuple(shape), dtype=bool)
    cells = np.floor((walls - low) / match).astype(np.int64)
    keep = np.all((cells >= 0) & (cells < shape), axis=1)
    table[cells[keep, 0], cells[keep, 1]] = True
    table = binary_dilation(table, structure=np.ones((3, 3), dtype=bool))
    base = (turned.points - low) / match  # (n, 2), in cells
    support = np.empty(len(positions))
    chunk = max(1, CHUNK_LOOKUPS // len(base))
    for k in range(0, len(positions), chunk):
        at = np.floor(base[None, :, :] + positions[k : k + chunk, None, :] / match).astype(np.int64)
        support[k : k + chunk] = table[at[..., 0], at[..., 1]] @ turned.weights
    return positions, support
