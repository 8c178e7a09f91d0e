"""Segment maps and the map file of the contracts (JSON), with validation that names the input.

``{"segments": [[x1, y1, x2, y2], ...], "ordered": true}``; extra keys are kept in ``extras``.
fleetmap adds an optional ``"oriented"`` key: true when every segment keeps the free space it was
seen from on its left (scans and the maps fleetmap builds). It defaults to ``ordered``: a scan's
segments follow the counter-clockwise sweep, so they are oriented too.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from fleetmap.shared.errors import BadInput
from fleetmap.shared.geometry import Array, lengths

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

    @property
    def total_length(self) -> float:
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


def map_from_dict(data: Any, source: str, *, allow_empty: bool = False) -> SegmentMap:
    """A SegmentMap from a decoded map-file object; errors name ``source``."""
    if not isinstance(data, dict):
        raise BadInput(source, f"a map must be a JSON object, got {type(data).__name__}")
    if "segments" not in data:
        raise BadInput(source, "missing key 'segments'")
    segments = as_segments(data["segments"], source, allow_empty=allow_empty)
    ordered = data.get("ordered", False)
    if not isinstance(ordered, bool):
        raise BadInput(source, f"'ordered' must be true or false, got {ordered!r}")
    oriented = data.get("oriented", ordered)
    if not isinstance(oriented, bool):
        raise BadInput(source, f"'oriented' must be true or false, got {oriented!r}")
    extras = {k: v for k, v in data.items() if k not in ("segments", "ordered", "oriented")}
    return SegmentMap(segments, ordered=ordered, oriented=oriented, extras=extras)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not allowed")


def parse_json(text: str, source: str) -> Any:
    """Strict JSON (NaN and Infinity literals rejected), errors naming ``source``."""
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise BadInput(source, f"malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except ValueError as exc:
        raise BadInput(source, f"malformed JSON: {exc} (NaN or infinite coordinates)") from None


def read_text(path: str | Path) -> str:
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BadInput(str(path), "no such file") from None
    except IsADirectoryError:
        raise BadInput(str(path), "is a directory, not a map file") from None
    except UnicodeDecodeError:
        raise BadInput(str(path), "not a text file (not UTF-8)") from None
    except OSError as exc:
        raise BadInput(str(path), f"cannot read: {exc.strerror}") from None


def read_map(path: str | Path) -> SegmentMap:
    """Read and validate a map file."""
    return map_from_dict(parse_json(read_text(path), str(path)), str(path))


def write_map(path: str | Path, segment_map: SegmentMap) -> None:
    Path(path).write_text(json.dumps(segment_map.to_json_dict()) + "\n", encoding="utf-8")


def finite_or_none(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)
