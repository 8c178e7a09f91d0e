"""The map file of the contracts (JSON), with validation that names the input.

``{"segments": [[x1, y1, x2, y2], ...], "ordered": true}``; extra keys are kept in ``extras``.
fleetmap adds an optional ``"oriented"`` key: true when every segment keeps the free space it was
seen from on its left (scans and the maps fleetmap builds). It defaults to ``ordered``: a scan's
segments follow the counter-clockwise sweep, so they are oriented too.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from fleetmap.shared.core.segmap import SegmentMap, as_segments
from fleetmap.shared.errors import BadInput


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
