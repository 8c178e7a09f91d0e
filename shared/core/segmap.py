"""Segment maps: the walls a scan, a submap or a merged map holds, in the map's own frame.

A map file of the contracts (JSON) reads into one (:mod:`fleetmap.shared.io.mapfile`).
fleetmap adds ``oriented``: true when every segment keeps the free space it was seen from on its
left (scans and the maps fleetmap builds). It defaults to ``ordered``: a scan's segments follow the
counter-clockwise sweep, so they are oriented too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from fleetmap.shared.core.geometry import Array, lengths
from fleetmap.shared.errors import BadInput

MIN_SEGMENT_LENGTH = 1e-6
"""Segments shorter than this (m) are zero-length: a map file containing one is rejected."""
MAX_COORDINATE = 1e6
"""No coordinate of a map lies farther than this (m, a thousand kilometres) from its origin: a laser
map spans a building or a site; beyond, a number is a unit or encoding mistake (and its squares
overflow)."""


@dataclass(frozen=True)
class SegmentMap:
    """A set of segments in the map's own frame."""

    segments: Array
    ordered: bool = False
    oriented: bool = False
    extras: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.segments.shape[0])

    @cached_property
    def total_length(self) -> float:
        """The segments' length in all (m; found once: the map does not change)."""
        return float(lengths(self.segments).sum())

    def to_json_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.extras)
        out["segments"] = [[float(v) for v in row] for row in self.segments]
        out["ordered"] = bool(self.ordered)
        out["oriented"] = bool(self.oriented)
        return out


def as_segments(value: Any, source: str, *, allow_empty: bool = False) -> Array:
    """Validate a segment list: rows of 4 finite numbers, none of zero length."""
    if not isinstance(value, (list, tuple, np.ndarray)):
        raise BadInput(source, f"segments must be a list of [x1, y1, x2, y2], got {type(value).__name__}")
    if len(value) == 0:
        if allow_empty:
            return np.zeros((0, 4))
        raise BadInput(source, "the map is empty (no segments)")
    if not isinstance(value, np.ndarray):
        for i, row in enumerate(value):
            if not isinstance(row, (list, tuple)) or len(row) != 4:
                raise BadInput(source, f"segment {i} must be [x1, y1, x2, y2], got {row!r}"[:200])
            for v in row:
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise BadInput(source, f"segment {i} has a non-numeric coordinate {v!r}"[:200])
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise BadInput(source, f"segments must have shape (n, 4), got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise BadInput(source, f"segment {i} has a NaN or infinite coordinate: {arr[i].tolist()}")
    far = (np.abs(arr) > MAX_COORDINATE).any(axis=1)
    if far.any():
        i = int(np.flatnonzero(far)[0])
        raise BadInput(source, f"segment {i} lies beyond {MAX_COORDINATE:g} m of the origin: {arr[i].tolist()}")
    short = lengths(arr) < MIN_SEGMENT_LENGTH
    if short.any():
        i = int(np.flatnonzero(short)[0])
        raise BadInput(source, f"segment {i} has zero length: {arr[i].tolist()}")
    return arr
