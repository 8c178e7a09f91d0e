"""The checks of one field of a bus message: its wire value in, the value normalised out.

Each check takes the message's schema name, the field's name and its value, either as a service
builds it (numbers, arrays, :class:`~fleetmap.shared.core.geometry.Transform2D`, parts) or as
msgpack decoded it (maps, lists, packed little-endian bytes), and returns the value as the
message keeps it: a read-only array, a Transform2D, a tuple. Anything else is a
:class:`BadMessage` naming the message, the field and the reason. The limits every message keeps
(``MAX_SEGMENTS``, ``MAX_STAMP``, ...) are here, beside the checks that hold them; the messages are
in :mod:`fleetmap.shared.io.messages`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, fields
from typing import Any

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D, lengths
from fleetmap.shared.core.segmap import MIN_SEGMENT_LENGTH
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import MAP_KEY_PATTERN, NAME_PATTERN

MAX_SEGMENTS = 200_000
"""The most segments one message carries (a global map: all its components together)."""
MAX_BEAMS = 100_000
"""The most range readings of one scan."""
MAX_MAPS = 100_000
"""The most local maps a global map names."""
MAX_TEXT = 256
"""The longest string field (characters)."""
MAX_INT = 2**63 - 1
MAX_STAMP = (2**63 - 1) / 1e9
"""The latest stamp (s since 1970, in 2262): what signed 64-bit nanoseconds hold, as MCAP's log and
publish times and ROS's time do. A clock in milliseconds (1.7e12) is past it: a recording could not
hold its messages, and a merger would keep that stamp for good."""
MAX_KEY_NUMBER = 10**18 - 1
"""The largest epoch or submap number: what a map key ``<robot>/<epoch>/<submap>`` holds
(:data:`fleetmap.shared.io.keys.MAP_KEY_PATTERN`, 18 digits)."""


class BadMessage(BadInput):
    """A payload that is not a valid fleetmap message; the text names the message and the field."""

    def __init__(self, schema: str, field: str | None, reason: str) -> None:
        self.schema = schema
        self.field = field
        super().__init__(schema if field is None else f"{schema} field {field!r}", reason)

    def __reduce__(self) -> tuple[type, tuple[str, str | None, str]]:  # type: ignore[override]
        return type(self), (self.schema, self.field, self.reason)


# --- checks: (schema, field, value) -> the value, normalised; BadMessage otherwise ---


def robot(schema: str, name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise BadMessage(schema, name, f"expected a robot id (string), got {type(value).__name__}")
    if NAME_PATTERN.fullmatch(value) is None:
        raise BadMessage(schema, name, f"{value[:64]!r} is not a robot id (^[a-z][a-z0-9_-]{{0,31}}$)")
    return value


def map_key(schema: str, name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise BadMessage(schema, name, f"expected a map key (string), got {type(value).__name__}")
    if MAP_KEY_PATTERN.fullmatch(value) is None:
        raise BadMessage(schema, name, f"{value[:64]!r} is not a map key <robot>/<epoch>")
    return value


def count(schema: str, name: str, value: Any, most: int = MAX_INT) -> int:
    """A non-negative integer (epoch, version, index, sequence number), at most ``most``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise BadMessage(schema, name, f"expected a non-negative integer, got {type(value).__name__}")
    if not 0 <= value <= most:
        raise BadMessage(schema, name, f"expected an integer from 0 to {most}, got {value}")
    return int(value)


def optional_count(schema: str, name: str, value: Any, most: int = MAX_INT) -> int | None:
    return None if value is None else count(schema, name, value, most)


def number(schema: str, name: str, value: Any, *, minimum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise BadMessage(schema, name, f"expected a number, got {type(value).__name__}")
    out = float(value)
    if not math.isfinite(out):
        raise BadMessage(schema, name, f"{out} is not finite")
    if minimum is not None and out < minimum:
        raise BadMessage(schema, name, f"{out} is below {minimum}")
    return out


def stamp(schema: str, name: str, value: Any) -> float:
    seconds = number(schema, name, value, minimum=0.0)
    if seconds > MAX_STAMP:
        raise BadMessage(schema, name, f"{seconds:g} s is after the year 2262 (a clock in milliseconds?)")
    return seconds


def flag(schema: str, name: str, value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise BadMessage(schema, name, f"expected true or false, got {type(value).__name__}")
    return bool(value)


def text(schema: str, name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise BadMessage(schema, name, f"expected a string, got {type(value).__name__}")
    if len(value) > MAX_TEXT:
        raise BadMessage(schema, name, f"{len(value)} characters is more than {MAX_TEXT}")
    return value


def transform(schema: str, name: str, value: Any) -> Transform2D:
    """A Transform2D, or its wire form ``{"x", "y", "theta"}``, with finite fields."""
    if isinstance(value, Transform2D):
        x, y, theta = value.x, value.y, value.theta
    elif isinstance(value, Mapping):
        missing = [k for k in ("x", "y", "theta") if k not in value]
        if missing:
            raise BadMessage(schema, name, f"a transform needs x, y and theta; missing {', '.join(missing)}")
        x, y, theta = value["x"], value["y"], value["theta"]
    else:
        raise BadMessage(schema, name, f"expected a transform {{x, y, theta}}, got {type(value).__name__}")
    return Transform2D(
        number(schema, f"{name}.x", x), number(schema, f"{name}.y", y), number(schema, f"{name}.theta", theta)
    )


def optional_transform(schema: str, name: str, value: Any) -> Transform2D | None:
    return None if value is None else transform(schema, name, value)


def readonly(array: Array) -> Array:
    view = array.view()
    view.flags.writeable = False
    return view


def float_rows(schema: str, name: str, value: Any, row: str, noun: str, limit: int) -> Array:
    """Rows of float64 (``row`` names the columns, e.g. "x1, y1, x2, y2"), from an array-like or
    the wire's packed little-endian bytes; at most ``limit`` rows, every value finite."""
    width = len(row.split(","))
    if isinstance(value, (bytes, bytearray, memoryview)):
        raw = bytes(value)
        if len(raw) % 8:
            raise BadMessage(schema, name, f"{len(raw)} bytes is not a whole number of float64")
        if len(raw) // 8 % width:
            raise BadMessage(schema, name, f"{len(raw) // 8} floats is not a multiple of {width}")
        if len(raw) // (8 * width) > limit:
            raise BadMessage(schema, name, f"{len(raw) // (8 * width)} {noun}s is more than {limit}")
        array = np.frombuffer(raw, dtype="<f8").reshape(-1, width)
    elif isinstance(value, (np.ndarray, list, tuple)):
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise BadMessage(schema, name, f"expected rows of {width} numbers [{row}]") from None
        if array.size == 0:
            array = array.reshape(0, width)
        if array.ndim != 2 or array.shape[1] != width:
            raise BadMessage(schema, name, f"expected shape (n, {width}), got {array.shape}")
        if array.shape[0] > limit:
            raise BadMessage(schema, name, f"{array.shape[0]} {noun}s is more than {limit}")
    else:
        raise BadMessage(schema, name, f"expected packed float64 {noun}s, got {type(value).__name__}")
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise BadMessage(schema, name, f"{noun} {i} has a NaN or infinite coordinate")
    return array


def segments(schema: str, name: str, value: Any, limit: int = MAX_SEGMENTS) -> Array:
    """Segments as an (n, 4) float64 array, from an array-like or the wire's packed float64 bytes."""
    array = float_rows(schema, name, value, "x1, y1, x2, y2", "segment", limit)
    short = lengths(array) < MIN_SEGMENT_LENGTH
    if short.any():
        i = int(np.flatnonzero(short)[0])
        raise BadMessage(schema, name, f"segment {i} has zero length")
    return readonly(array)


def viewpoints(schema: str, name: str, value: Any, limit: int = MAX_SEGMENTS) -> Array:
    """Viewpoints as a (v, 5) float64 array ``[x, y, theta, bearing_min, bearing_max]`` (the pose of
    each scan in a local map and the bearings its laser covers), from an array-like or packed bytes."""
    return readonly(float_rows(schema, name, value, "x, y, theta, bearing_min, bearing_max", "viewpoint", limit))


def ranges(schema: str, name: str, value: Any) -> Array:
    """Range readings as a 1-D float32 array; NaN and infinity are allowed (no return)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        raw = bytes(value)
        if len(raw) % 4:
            raise BadMessage(schema, name, f"{len(raw)} bytes is not a whole number of float32")
        array = np.frombuffer(raw, dtype="<f4")
    elif isinstance(value, (np.ndarray, list, tuple)):
        try:
            with np.errstate(over="ignore"):  # a reading beyond float32 (3.4e38 m) is no return: inf
                array = np.asarray(value, dtype=np.float32)
        except (TypeError, ValueError):
            raise BadMessage(schema, name, "expected a list of numbers") from None
        if array.ndim != 1:
            raise BadMessage(schema, name, f"expected one reading per beam, got shape {array.shape}")
    else:
        raise BadMessage(schema, name, f"expected packed float32 ranges, got {type(value).__name__}")
    if array.shape[0] > MAX_BEAMS:
        raise BadMessage(schema, name, f"{array.shape[0]} readings is more than {MAX_BEAMS}")
    return readonly(array)


def mapping(schema: str, name: str, value: Any) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise BadMessage(schema, name, f"expected a map, got {type(value).__name__}")
    return value


def sequence(schema: str, name: str, value: Any, limit: int) -> Sequence[Any]:
    if not isinstance(value, (list, tuple)):
        raise BadMessage(schema, name, f"expected a list, got {type(value).__name__}")
    if len(value) > limit:
        raise BadMessage(schema, name, f"{len(value)} items is more than {limit}")
    return value


def part(cls: type[Any], schema: str, name: str, value: Any) -> Any:
    """A nested part (``cls`` instance) from itself or from its wire map, errors under ``name``."""
    if isinstance(value, cls):
        return value
    data = mapping(schema, name, value)
    kwargs = {}
    for f in fields(cls):
        if f.name in data:
            kwargs[f.name] = data[f.name]
        elif f.default is MISSING and f.default_factory is MISSING:
            raise BadMessage(schema, f"{name}.{f.name}", "missing")
    try:
        return cls(**kwargs)
    except BadMessage as exc:
        raise BadMessage(schema, name if exc.field is None else f"{name}.{exc.field}", exc.reason) from None


def assign(obj: object, name: str, value: Any) -> None:
    """Set a field of a frozen message or part to its checked value (in its ``__post_init__``)."""
    object.__setattr__(obj, name, value)


def covariance(schema: str, name: str, value: Any) -> tuple[float, ...]:
    """A 3x3 covariance, row-major: 9 finite numbers, symmetric, positive definite."""
    raw = value.ravel().tolist() if isinstance(value, np.ndarray) else value
    items = sequence(schema, name, raw, 9)
    if len(items) != 9:
        raise BadMessage(schema, name, f"expected 9 numbers (a 3x3 matrix, row-major), got {len(items)}")
    numbers = tuple(number(schema, f"{name}[{i}]", v) for i, v in enumerate(items))
    m = np.array(numbers).reshape(3, 3)
    if not np.allclose(m, m.T, rtol=1e-6, atol=1e-12 * max(float(np.abs(m).max()), 1e-300)):
        raise BadMessage(schema, name, "is not symmetric")
    if np.linalg.eigvalsh(m).min() <= 0:
        raise BadMessage(schema, name, "is not positive definite")
    return numbers


def int_rows(schema: str, name: str, value: Any, limit: int) -> Array:
    """Non-negative integers (scan indices) as a 1-D int64 array, from a list or packed bytes."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        raw = bytes(value)
        if len(raw) % 8:
            raise BadMessage(schema, name, f"{len(raw)} bytes is not a whole number of int64")
        array = np.frombuffer(raw, dtype="<i8")
    elif isinstance(value, (np.ndarray, list, tuple)):
        try:
            array = np.asarray(value, dtype=np.int64)
        except (TypeError, ValueError, OverflowError):
            raise BadMessage(schema, name, "expected a list of integers") from None
        if array.size == 0:
            array = array.reshape(0)
        if array.ndim != 1:
            raise BadMessage(schema, name, f"expected one integer per scan, got shape {array.shape}")
    else:
        raise BadMessage(schema, name, f"expected packed int64 indices, got {type(value).__name__}")
    if len(array) > limit:
        raise BadMessage(schema, name, f"{len(array)} items is more than {limit}")
    if len(array) and array.min() < 0:
        raise BadMessage(schema, name, f"index {int(array.min())} is negative")
    return readonly(array)


def column(value: Any) -> Any:
    """A 1-D sequence of numbers as one column (the wire packs it as bytes either way)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return value
    array = np.asarray(value, dtype=np.float64) if not isinstance(value, np.ndarray) else value
    return array.reshape(-1, 1)
