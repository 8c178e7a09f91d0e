"""The messages of the bus: typed, versioned, validated msgpack maps.

Every payload is a msgpack map ``{"schema": "fleetmap.<Name>", "v": <version>, <fields>...}``.
Each message type is a frozen dataclass that validates every field when it is built, whether by a
service about to publish it or by :func:`decode` on receipt, so a bad message is refused where it
is made and where it arrives. A refusal is a :class:`BadMessage` whose text names the message, the
field and the reason::

    fleetmap.LocalMap field 'segments': 7 floats is not a multiple of 4

Conventions on the wire:

- segments travel as one ``bin`` of little-endian float64, ``n * 4`` values ``[x1, y1, x2, y2]``,
  and decode to a read-only ``(n, 4)`` array; NaN, infinite coordinates and zero-length segments
  are refused;
- transforms are maps ``{"x", "y", "theta"}`` (``docs/formats.md``);
- ``stamp`` is seconds (the scan's time: simulated or wall clock), finite and non-negative;
- a robot's local map of one epoch is named by its map key ``<robot>/<epoch>``, one submap of it
  by ``<robot>/<epoch>/<submap>`` (:mod:`fleetmap.shared.io.keys`);
- optional fields are ``nil`` or absent; unknown fields are ignored, so a newer sender may add
  optional fields without breaking older receivers; a ``v`` this code does not read is refused.
"""

from __future__ import annotations

import math
import sys
import types
import weakref
from collections.abc import Mapping, Sequence, Set
from dataclasses import MISSING, dataclass, fields, is_dataclass
from typing import Any, ClassVar, Self

import msgpack
import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D, lengths
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.segmap import MIN_SEGMENT_LENGTH
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import MAP_KEY_PATTERN, NAME_PATTERN

MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
"""Payloads larger than this are refused before they are unpacked: the largest message fleetmap
sends, a global map of ``MAX_SEGMENTS`` packed segments, is 6.4 MB, while a payload of small
integers unpacks into Python objects tens of times its size, in every subscriber
(docs/decisions/003-a-fleet-that-lets-in-only-its-own.md)."""
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

EVENT_KINDS = frozenset(
    {
        "join",  # a robot's liveliness token appeared
        "leave",  # ... and disappeared (clean exit, crash or lost link)
        "epoch",  # a robot started a new local map (robot: who; detail: why)
        "kidnap",  # a scenario carried a robot away (ground truth, for the report)
        "relocalized",  # the merger placed a robot's new epoch in the global map again
        "refused",  # the merger refuses a robot's epoch (detail: which, and why): a second agent under its id
        "merger_start",
        "merger_stop",
        "republish_request",  # a (re)started merger asks every robot for its latest local map
        "recorder_start",
        "recorder_stop",
        "scenario_start",
        "scenario_end",
    }
)
"""What a FleetEvent may say. Add a kind here before a service publishes it."""


class BadMessage(BadInput):
    """A payload that is not a valid fleetmap message; the text names the message and the field."""

    def __init__(self, schema: str, field: str | None, reason: str) -> None:
        self.schema = schema
        self.field = field
        super().__init__(schema if field is None else f"{schema} field {field!r}", reason)

    def __reduce__(self) -> tuple[type, tuple[str, str | None, str]]:  # type: ignore[override]
        return type(self), (self.schema, self.field, self.reason)


# --- field validators: (schema, field, value) -> the value, normalised; BadMessage otherwise ---


def _robot(schema: str, name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise BadMessage(schema, name, f"expected a robot id (string), got {type(value).__name__}")
    if NAME_PATTERN.fullmatch(value) is None:
        raise BadMessage(schema, name, f"{value[:64]!r} is not a robot id (^[a-z][a-z0-9_-]{{0,31}}$)")
    return value


def _map_key(schema: str, name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise BadMessage(schema, name, f"expected a map key (string), got {type(value).__name__}")
    if MAP_KEY_PATTERN.fullmatch(value) is None:
        raise BadMessage(schema, name, f"{value[:64]!r} is not a map key <robot>/<epoch>")
    return value


def _count(schema: str, name: str, value: Any, most: int = MAX_INT) -> int:
    """A non-negative integer (epoch, version, index, sequence number), at most ``most``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise BadMessage(schema, name, f"expected a non-negative integer, got {type(value).__name__}")
    if not 0 <= value <= most:
        raise BadMessage(schema, name, f"expected an integer from 0 to {most}, got {value}")
    return int(value)


def _optional_count(schema: str, name: str, value: Any, most: int = MAX_INT) -> int | None:
    return None if value is None else _count(schema, name, value, most)


def _number(schema: str, name: str, value: Any, *, minimum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise BadMessage(schema, name, f"expected a number, got {type(value).__name__}")
    number = float(value)
    if not math.isfinite(number):
        raise BadMessage(schema, name, f"{number} is not finite")
    if minimum is not None and number < minimum:
        raise BadMessage(schema, name, f"{number} is below {minimum}")
    return number


def _stamp(schema: str, name: str, value: Any) -> float:
    stamp = _number(schema, name, value, minimum=0.0)
    if stamp > MAX_STAMP:
        raise BadMessage(schema, name, f"{stamp:g} s is after the year 2262 (a clock in milliseconds?)")
    return stamp


def _flag(schema: str, name: str, value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise BadMessage(schema, name, f"expected true or false, got {type(value).__name__}")
    return bool(value)


def _text(schema: str, name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise BadMessage(schema, name, f"expected a string, got {type(value).__name__}")
    if len(value) > MAX_TEXT:
        raise BadMessage(schema, name, f"{len(value)} characters is more than {MAX_TEXT}")
    return value


def _transform(schema: str, name: str, value: Any) -> Transform2D:
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
        _number(schema, f"{name}.x", x), _number(schema, f"{name}.y", y), _number(schema, f"{name}.theta", theta)
    )


def _optional_transform(schema: str, name: str, value: Any) -> Transform2D | None:
    return None if value is None else _transform(schema, name, value)


def _readonly(array: Array) -> Array:
    view = array.view()
    view.flags.writeable = False
    return view


def _float_rows(schema: str, name: str, value: Any, row: str, noun: str, limit: int) -> Array:
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


def _segments(schema: str, name: str, value: Any, limit: int = MAX_SEGMENTS) -> Array:
    """Segments as an (n, 4) float64 array, from an array-like or the wire's packed float64 bytes."""
    array = _float_rows(schema, name, value, "x1, y1, x2, y2", "segment", limit)
    short = lengths(array) < MIN_SEGMENT_LENGTH
    if short.any():
        i = int(np.flatnonzero(short)[0])
        raise BadMessage(schema, name, f"segment {i} has zero length")
    return _readonly(array)


def _viewpoints(schema: str, name: str, value: Any, limit: int = MAX_SEGMENTS) -> Array:
    """Viewpoints as a (v, 5) float64 array ``[x, y, theta, bearing_min, bearing_max]`` (the pose of
    each scan in a local map and the bearings its laser covers), from an array-like or packed bytes."""
    return _readonly(_float_rows(schema, name, value, "x, y, theta, bearing_min, bearing_max", "viewpoint", limit))


def _ranges_array(schema: str, name: str, value: Any) -> Array:
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
    return _readonly(array)


def _mapping(schema: str, name: str, value: Any) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise BadMessage(schema, name, f"expected a map, got {type(value).__name__}")
    return value


def _sequence(schema: str, name: str, value: Any, limit: int) -> Sequence[Any]:
    if not isinstance(value, (list, tuple)):
        raise BadMessage(schema, name, f"expected a list, got {type(value).__name__}")
    if len(value) > limit:
        raise BadMessage(schema, name, f"{len(value)} items is more than {limit}")
    return value


def _part(cls: type[Any], schema: str, name: str, value: Any) -> Any:
    """A nested part (``cls`` instance) from itself or from its wire map, errors under ``name``."""
    if isinstance(value, cls):
        return value
    data = _mapping(schema, name, value)
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


def _set(obj: object, name: str, value: Any) -> None:
    object.__setattr__(obj, name, value)


# --- parts of messages ---


@dataclass(frozen=True, eq=False)
class LaserRanges:
    """A scan's raw laser readings, kept so replays and viewers can use them.

    Beam i points at ``angle_min + i * angle_increment``; a reading that is not finite, is <= 0
    or is >= ``range_max`` is no return (``docs/formats.md``, range scans). Readings travel
    as little-endian float32.
    """

    SCHEMA: ClassVar[str] = "fleetmap.LaserRanges"

    angle_min: float
    angle_increment: float
    range_max: float
    ranges: Array

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "angle_min", _number(s, "angle_min", self.angle_min))
        _set(self, "angle_increment", _number(s, "angle_increment", self.angle_increment))
        if self.angle_increment == 0.0:
            raise BadMessage(s, "angle_increment", "is zero")
        range_max = self.range_max
        if isinstance(range_max, bool) or not isinstance(range_max, (int, float, np.integer, np.floating)):
            raise BadMessage(s, "range_max", f"expected a number, got {type(range_max).__name__}")
        if not float(range_max) > 0.0:  # infinity is allowed: a log that does not say its range
            raise BadMessage(s, "range_max", f"{range_max} is not a positive number")
        _set(self, "range_max", float(range_max))
        _set(self, "ranges", _ranges_array(s, "ranges", self.ranges))

    @staticmethod
    def from_range_scan(scan: RangeScan) -> LaserRanges:
        return LaserRanges(scan.angle_min, scan.angle_increment, scan.range_max, scan.ranges)

    def to_range_scan(self, stamp: float) -> RangeScan:
        return RangeScan(stamp, self.angle_min, self.angle_increment, self.range_max, self.ranges.astype(np.float64))


@dataclass(frozen=True)
class EpochLink:
    """How a local map's epoch follows the robot's previous one.

    ``transform`` is the new epoch's frame in the previous epoch's frame when the robot knows it
    (a restart in place), and None when it does not (a kidnap: never a guess).
    """

    SCHEMA: ClassVar[str] = "fleetmap.EpochLink"

    epoch: int
    reason: str = ""
    transform: Transform2D | None = None

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "epoch", _count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        _set(self, "reason", _text(s, "reason", self.reason))
        _set(self, "transform", _optional_transform(s, "transform", self.transform))


@dataclass(frozen=True, eq=False)
class SubmapLink:
    """How a submap follows the previous one of its epoch, by the robot's own tracking.

    ``transform`` is the submap's frame in the previous submap's frame; ``covariance`` its
    uncertainty (row-major 3x3 over x, y, theta; m^2, m rad, rad^2), as the tracking measured it.
    """

    SCHEMA: ClassVar[str] = "fleetmap.SubmapLink"

    submap: int
    transform: Transform2D
    covariance: tuple[float, ...]

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "submap", _count(s, "submap", self.submap, MAX_KEY_NUMBER))
        _set(self, "transform", _transform(s, "transform", self.transform))
        _set(self, "covariance", _covariance(s, "covariance", self.covariance))

    @property
    def covariance_matrix(self) -> Array:
        return np.array(self.covariance, dtype=np.float64).reshape(3, 3)


def _covariance(schema: str, name: str, value: Any) -> tuple[float, ...]:
    """A 3x3 covariance, row-major: 9 finite numbers, symmetric, positive definite."""
    raw = value.ravel().tolist() if isinstance(value, np.ndarray) else value
    items = _sequence(schema, name, raw, 9)
    if len(items) != 9:
        raise BadMessage(schema, name, f"expected 9 numbers (a 3x3 matrix, row-major), got {len(items)}")
    numbers = tuple(_number(schema, f"{name}[{i}]", v) for i, v in enumerate(items))
    m = np.array(numbers).reshape(3, 3)
    if not np.allclose(m, m.T, rtol=1e-6, atol=1e-12 * max(float(np.abs(m).max()), 1e-300)):
        raise BadMessage(schema, name, "is not symmetric")
    if np.linalg.eigvalsh(m).min() <= 0:
        raise BadMessage(schema, name, "is not positive definite")
    return numbers


def _int_rows(schema: str, name: str, value: Any, limit: int) -> Array:
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
    return _readonly(array)


@dataclass(frozen=True, eq=False)
class Component:
    """One connected component of the pose graph: submaps (or map files) merged into one global map.

    ``poses[key]`` places local map ``key`` in the component's frame, which is the anchor's frame;
    ``segments`` is the merged map in that frame.
    """

    SCHEMA: ClassVar[str] = "fleetmap.Component"

    anchor: str
    members: tuple[str, ...]
    poses: Mapping[str, Transform2D]
    segments: Array

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "anchor", _map_key(s, "anchor", self.anchor))
        members = tuple(
            _map_key(s, f"members[{i}]", m) for i, m in enumerate(_sequence(s, "members", self.members, MAX_MAPS))
        )
        if len(set(members)) != len(members):
            raise BadMessage(s, "members", "a map is listed twice")
        if self.anchor not in members:
            raise BadMessage(s, "anchor", f"{self.anchor!r} is not one of the members")
        raw_poses = _mapping(s, "poses", self.poses)
        poses = {}
        for key, pose in raw_poses.items():
            poses[_map_key(s, "poses", key)] = _transform(s, f"poses[{key}]", pose)
        if set(poses) != set(members):
            unplaced = sorted(set(members) - set(poses))
            extra = sorted(set(poses) - set(members))
            what = f"members without a pose: {unplaced[:3]}" if unplaced else f"poses of non-members: {extra[:3]}"
            raise BadMessage(s, "poses", what)
        _set(self, "members", members)
        _set(self, "poses", types.MappingProxyType(poses))
        _set(self, "segments", _segments(s, "segments", self.segments))


# --- messages ---


class WireMessage:
    """What every message has: a schema name, a version and msgpack coding."""

    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int] = 1
    READS: ClassVar[tuple[int, ...]] = (1,)
    """Versions of this schema that :func:`decode` accepts."""

    stamp: float

    def to_msgpack(self) -> bytes:
        out: dict[str, Any] = {"schema": self.SCHEMA, "v": self.VERSION}
        for f in fields(self):  # type: ignore[arg-type]  # every subclass is a dataclass
            out[f.name] = _to_wire(getattr(self, f.name))
        packed: bytes = msgpack.packb(out, use_bin_type=True)
        return packed

    @classmethod
    def from_msgpack(cls, data: bytes) -> Self:
        message = decode(data)
        if not isinstance(message, cls):
            raise BadMessage(cls.SCHEMA, "schema", f"expected {cls.SCHEMA}, got {message.SCHEMA}")
        return message

    @classmethod
    def _from_wire(cls, data: Mapping[str, Any]) -> Self:
        kwargs = {}
        for f in fields(cls):  # type: ignore[arg-type]  # every subclass is a dataclass
            if f.name in data:
                kwargs[f.name] = data[f.name]
            elif f.default is MISSING and f.default_factory is MISSING:
                raise BadMessage(cls.SCHEMA, f.name, "missing")
        return cls(**kwargs)


_COMPONENT_WIRE: weakref.WeakKeyDictionary[Component, dict[str, Any]] = weakref.WeakKeyDictionary()
"""Each global-map component's wire form, made once: a merger publishes the components no step
changed again at every step."""


def _to_wire(value: Any) -> Any:
    if isinstance(value, Component):
        held = _COMPONENT_WIRE.get(value)
        if held is None:
            held = _COMPONENT_WIRE[value] = {f.name: _to_wire(getattr(value, f.name)) for f in fields(value)}
        return held
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "iu":
            return np.ascontiguousarray(value, dtype="<i8").tobytes()
        return np.ascontiguousarray(value, dtype="<f4" if value.dtype == np.float32 else "<f8").tobytes()
    if isinstance(value, Transform2D):
        return {"x": value.x, "y": value.y, "theta": value.theta}
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: _to_wire(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, Mapping):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    return value


@dataclass(frozen=True, eq=False)
class Scan(WireMessage):
    """One laser sweep of a robot: its segments (paper III-D) in the laser's frame."""

    SCHEMA: ClassVar[str] = "fleetmap.Scan"

    robot: str
    epoch: int
    index: int
    """The scan's number in the robot's stream (0, 1, ...)."""
    stamp: float
    segments: Array
    ranges: LaserRanges | None = None
    submap: int | None = None
    """The submap of the scan's epoch that placed it (None: not placed)."""
    pose: Transform2D | None = None
    """The laser's pose in that submap's frame, by the robot's tracking (None: not placed)."""
    odometry: Transform2D | None = None
    """The robot's odometry at the scan (its own frame: only differences between scans mean
    anything); None when the robot has none."""

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "robot", _robot(s, "robot", self.robot))
        _set(self, "epoch", _count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        _set(self, "index", _count(s, "index", self.index))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))
        _set(self, "segments", _segments(s, "segments", self.segments))
        if self.ranges is not None:
            _set(self, "ranges", _part(LaserRanges, s, "ranges", self.ranges))
        _set(self, "submap", _optional_count(s, "submap", self.submap, MAX_KEY_NUMBER))
        _set(self, "pose", _optional_transform(s, "pose", self.pose))
        _set(self, "odometry", _optional_transform(s, "odometry", self.odometry))
        if (self.submap is None) != (self.pose is None):
            raise BadMessage(s, "pose", "a placed scan names its submap and its pose in it, an unplaced one neither")


@dataclass(frozen=True, eq=False)
class LocalMap(WireMessage):
    """A robot's submap, version ``version``: the walls of a stretch of its path, in the frame of
    the submap's first scan, as its tracking placed them (``fleetmap.agents.tracker``).

    A robot's submaps of one epoch are numbered 0, 1, ... (submap 0's frame is the epoch's);
    consecutive ones overlap and are chained by ``link``. The active submap grows in versions;
    a finished one is published once more with ``final`` true and never changes again.

    Version 1 carries a whole epoch's local map, with no submap fields: it reads as submap 0, not
    final, without a link or scan table.
    """

    SCHEMA: ClassVar[str] = "fleetmap.LocalMap"
    VERSION: ClassVar[int] = 2
    READS: ClassVar[tuple[int, ...]] = (1, 2)

    robot: str
    epoch: int
    version: int
    stamp: float
    segments: Array
    scans: int
    """How many scans went into it."""
    pose: Transform2D | None = None
    """The robot's current pose in this submap's frame; None when the robot is lost."""
    previous_epoch_link: EpochLink | None = None
    """Set on the submaps of an epoch that follows another one of the same robot."""
    viewpoints: Array | None = None
    """Where each scan that went into it was taken, in the map's frame, and the bearings its laser
    covers: rows ``[x, y, theta, bearing_min, bearing_max]`` (fleetmap.shared.core.mapgrid). With them
    the merger knows the free space the robot saw and refuses a match that puts walls in it."""
    submap: int = 0
    """The submap's number in its epoch."""
    final: bool = False
    """The submap is finished: this version is its last."""
    link: SubmapLink | None = None
    """Submap ``submap - 1``'s frame to this one's, by the robot's tracking (None for submap 0)."""
    scan_indices: Array | None = None
    """The scans this submap places (each scan of an epoch is placed by one submap): their
    indices in the robot's stream, ..."""
    scan_stamps: Array | None = None
    """... their stamps (s), ..."""
    scan_poses: Array | None = None
    """... and their laser poses in this submap's frame, rows ``[x, y, theta]``."""
    frame_scan: int | None = None
    """The index of the scan whose laser pose is this submap's frame (its first inserted scan)."""

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "robot", _robot(s, "robot", self.robot))
        _set(self, "epoch", _count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        _set(self, "version", _count(s, "version", self.version))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))
        _set(self, "segments", _segments(s, "segments", self.segments))
        _set(self, "scans", _count(s, "scans", self.scans))
        _set(self, "pose", _optional_transform(s, "pose", self.pose))
        if self.viewpoints is not None:
            _set(self, "viewpoints", _viewpoints(s, "viewpoints", self.viewpoints))
        if self.previous_epoch_link is not None:
            link = _part(EpochLink, s, "previous_epoch_link", self.previous_epoch_link)
            if link.epoch >= self.epoch:
                raise BadMessage(s, "previous_epoch_link.epoch", f"{link.epoch} is not before epoch {self.epoch}")
            _set(self, "previous_epoch_link", link)
        _set(self, "submap", _count(s, "submap", self.submap, MAX_KEY_NUMBER))
        _set(self, "final", _flag(s, "final", self.final))
        _set(self, "frame_scan", _optional_count(s, "frame_scan", self.frame_scan))
        if self.link is not None:
            submap_link = _part(SubmapLink, s, "link", self.link)
            if submap_link.submap != self.submap - 1:
                raise BadMessage(s, "link.submap", f"{submap_link.submap} is not the submap before {self.submap}")
            _set(self, "link", submap_link)
        table = (self.scan_indices, self.scan_stamps, self.scan_poses)
        if any(part is not None for part in table):
            if any(part is None for part in table):
                raise BadMessage(s, "scan_indices", "scan_indices, scan_stamps and scan_poses go together")
            indices = _int_rows(s, "scan_indices", self.scan_indices, MAX_SEGMENTS)
            stamps = _float_rows(s, "scan_stamps", _column(self.scan_stamps), "stamp", "stamp", MAX_SEGMENTS)[:, 0]
            if len(stamps) and stamps.min() < 0:
                raise BadMessage(s, "scan_stamps", f"stamp {float(stamps.min())} is negative")
            if len(stamps) and stamps.max() > MAX_STAMP:
                raise BadMessage(s, "scan_stamps", f"stamp {float(stamps.max()):g} s is after the year 2262")
            poses = _float_rows(s, "scan_poses", self.scan_poses, "x, y, theta", "pose", MAX_SEGMENTS)
            if not len(indices) == len(stamps) == len(poses):
                raise BadMessage(
                    s, "scan_poses", f"{len(indices)} indices, {len(stamps)} stamps and {len(poses)} poses differ"
                )
            _set(self, "scan_indices", indices)
            _set(self, "scan_stamps", _readonly(stamps))
            _set(self, "scan_poses", _readonly(poses))

    @property
    def key(self) -> str:
        """The map key ``<robot>/<epoch>`` of the epoch this submap belongs to."""
        return f"{self.robot}/{self.epoch}"

    @property
    def submap_key(self) -> str:
        """The submap's own key ``<robot>/<epoch>/<submap>``."""
        return f"{self.robot}/{self.epoch}/{self.submap}"


def _column(value: Any) -> Any:
    """A 1-D sequence of numbers as one column (the wire packs it as bytes either way)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return value
    array = np.asarray(value, dtype=np.float64) if not isinstance(value, np.ndarray) else value
    return array.reshape(-1, 1)


@dataclass(frozen=True)
class MergeEdge(WireMessage):
    """An integration attempt between local maps a and b: ``(x, y, theta)`` maps b into a's frame."""

    SCHEMA: ClassVar[str] = "fleetmap.MergeEdge"

    a: str
    b: str
    x: float
    y: float
    theta: float
    value: float
    """The paper's transformation value (matched length, m)."""
    valid: bool
    stamp: float

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "a", _map_key(s, "a", self.a))
        _set(self, "b", _map_key(s, "b", self.b))
        if self.a == self.b:
            raise BadMessage(s, "b", f"an edge joins two different maps, got {self.a!r} twice")
        for name in ("x", "y", "theta"):
            _set(self, name, _number(s, name, getattr(self, name)))
        _set(self, "value", _number(s, "value", self.value, minimum=0.0))
        _set(self, "valid", _flag(s, "valid", self.valid))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))

    @property
    def transform(self) -> Transform2D:
        return Transform2D(self.x, self.y, self.theta)


@dataclass(frozen=True, eq=False)
class GlobalMap(WireMessage):
    """The merger's global maps: one per connected component of the pose graph."""

    SCHEMA: ClassVar[str] = "fleetmap.GlobalMap"

    seq: int
    """Increases with every global map the merger publishes."""
    stamp: float
    components: tuple[Component, ...]

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "seq", _count(s, "seq", self.seq))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))
        raw = _sequence(s, "components", self.components, MAX_MAPS)
        components = tuple(_part(Component, s, f"components[{i}]", c) for i, c in enumerate(raw))
        seen: set[str] = set()
        for i, component in enumerate(components):
            twice = seen.intersection(component.members)
            if twice:
                raise BadMessage(s, f"components[{i}].members", f"{sorted(twice)[0]!r} is in two components")
            seen.update(component.members)
        if len(seen) > MAX_MAPS:
            raise BadMessage(s, "components", f"{len(seen)} maps is more than {MAX_MAPS}")
        total = sum(len(c.segments) for c in components)
        if total > MAX_SEGMENTS:
            raise BadMessage(s, "components", f"{total} segments is more than {MAX_SEGMENTS}")
        _set(self, "components", components)

    def component_of(self, key: str) -> int | None:
        """The index of the component that holds map ``key``, or None."""
        for i, component in enumerate(self.components):
            if key in component.poses:
                return i
        return None


@dataclass(frozen=True)
class RobotPose(WireMessage):
    """A robot's pose in the frame of global map component ``component`` (of the latest GlobalMap).

    ``pose`` None means unknown (the robot is lost, or its epoch is not placed yet), never a guess;
    then ``component`` is None too.
    """

    SCHEMA: ClassVar[str] = "fleetmap.RobotPose"

    robot: str
    epoch: int
    stamp: float
    pose: Transform2D | None
    component: int | None

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "robot", _robot(s, "robot", self.robot))
        _set(self, "epoch", _count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))
        _set(self, "pose", _optional_transform(s, "pose", self.pose))
        _set(self, "component", _optional_count(s, "component", self.component))
        if (self.pose is None) != (self.component is None):
            raise BadMessage(s, "component", "a pose needs its component, and an unknown pose has none")


@dataclass(frozen=True)
class FleetEvent(WireMessage):
    """Something that happened to the fleet: a robot joined, left, started an epoch, ..."""

    SCHEMA: ClassVar[str] = "fleetmap.FleetEvent"

    kind: str
    """One of :data:`EVENT_KINDS`."""
    robot: str | None
    stamp: float
    detail: str = ""

    def __post_init__(self) -> None:
        s = self.SCHEMA
        if not isinstance(self.kind, str) or self.kind not in EVENT_KINDS:
            raise BadMessage(s, "kind", f"{str(self.kind)[:64]!r} is not one of {', '.join(sorted(EVENT_KINDS))}")
        if self.robot is not None:
            _set(self, "robot", _robot(s, "robot", self.robot))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))
        _set(self, "detail", _text(s, "detail", self.detail))


@dataclass(frozen=True, eq=False)
class MergerStep(WireMessage):
    """The local map versions the merger took into its graph in one step, in the order it took
    them, and how many pairs of maps it integrated.

    The merger is deterministic given its inputs in order; a replay feeds the recorded local
    maps in the order these steps give and integrates as many pairs per step, so it rebuilds
    exactly the live global map even where the recorder heard two robots in the other order, or
    the live merger's time budget cut a step short.
    """

    SCHEMA: ClassVar[str] = "fleetmap.MergerStep"

    seq: int
    stamp: float
    maps: tuple[str, ...]
    versions: tuple[int, ...]
    integrations: int | None = None
    """Pairs of maps the step took off its queue (a replay takes as many; None: all of them)."""
    queued: int | None = None
    """Pairs still waiting after the step (0: the merger has caught up)."""

    def __post_init__(self) -> None:
        s = self.SCHEMA
        _set(self, "integrations", _optional_count(s, "integrations", self.integrations))
        _set(self, "queued", _optional_count(s, "queued", self.queued))
        _set(self, "seq", _count(s, "seq", self.seq))
        _set(self, "stamp", _stamp(s, "stamp", self.stamp))
        maps = _sequence(s, "maps", self.maps, MAX_MAPS)
        versions = _sequence(s, "versions", self.versions, MAX_MAPS)
        if len(maps) != len(versions):
            raise BadMessage(s, "versions", f"{len(versions)} versions for {len(maps)} maps")
        _set(self, "maps", tuple(_map_key(s, f"maps[{i}]", m) for i, m in enumerate(maps)))
        _set(self, "versions", tuple(_count(s, f"versions[{i}]", v) for i, v in enumerate(versions)))


Message = Scan | LocalMap | MergeEdge | GlobalMap | RobotPose | FleetEvent | MergerStep
"""Any message of the bus."""

_CONTAINER_TYPES = ("Transform2D", "LaserRanges", "EpochLink", "SubmapLink", "tuple[")
"""What a field's annotation names when its wire value is a msgpack map or array; every other
field is one number, string or flag, or packed bytes (arrays travel as bins, and always have)."""
_CONTAINER_HEADERS = frozenset([*range(0x80, 0xA0), 0xDC, 0xDD, 0xDE, 0xDF])
"""The first byte of a msgpack map or array (fixmap, fixarray, array 16/32, map 16/32)."""


MESSAGE_TYPES: dict[str, type[Scan | LocalMap | MergeEdge | GlobalMap | RobotPose | FleetEvent | MergerStep]] = {
    cls.SCHEMA: cls for cls in (Scan, LocalMap, MergeEdge, GlobalMap, RobotPose, FleetEvent, MergerStep)
}
_FIELD_NAMES: dict[type[Message], frozenset[str]] = {
    cls: frozenset({"schema", "v", *(f.name for f in fields(cls))}) for cls in MESSAGE_TYPES.values()
}
"""Each message type's fields: the values of a payload worth decoding."""
_CONTAINER_FIELDS: dict[type[Message], frozenset[str]] = {
    cls: frozenset(f.name for f in fields(cls) if any(t in str(f.type) for t in _CONTAINER_TYPES))
    for cls in MESSAGE_TYPES.values()
}
"""... and those of them whose value is a msgpack map or array."""


_LIMITS: dict[str, Any] = {
    # each checked against its header before anything is allocated
    "max_array_len": 4 * MAX_SEGMENTS,
    "max_map_len": MAX_MAPS + 64,
    "max_str_len": 64 * 1024,
    "max_bin_len": MAX_PAYLOAD_BYTES,
    "max_ext_len": 0,
}
MAX_FIELDS = 64
"""The most fields one message's top-level map may have (fleetmap's messages have at most 16)."""
DECODED_BYTES_PER_BYTE = 16
"""The decoding budget: what a payload decodes into (its containers and their items, as Python
objects) may take this many bytes per payload byte, plus :data:`DECODED_SLACK`. Messages as
fleetmap sends them carry their bulk in bins, about one byte per byte; a transform, the densest
part, takes 11 (38 bytes on the wire, 410 as a dict); a payload of empty lists would take 64."""
DECODED_SLACK = 1024 * 1024
"""... plus this much, for small messages of many little fields."""
_MOST_PER_BYTE = 64
"""The most one payload byte can decode into (an empty list: 56 bytes, and its slot in its
container), so a payload of at most ``DECODED_SLACK / (_MOST_PER_BYTE - DECODED_BYTES_PER_BYTE)``
bytes is within its budget whatever it holds and is decoded without counting."""


class _OverBudget(Exception):
    pass


class _DecodeBudget:
    """Counts what msgpack decodes, container by container as each is built, and stops decoding
    past the payload's budget: memory grows with the payload's size, not with how many items it
    packs (a 16 MB payload of empty lists would otherwise take a gigabyte)."""

    def __init__(self, size: int) -> None:
        self.left = DECODED_BYTES_PER_BYTE * size + DECODED_SLACK

    def _charge(self, size: int) -> None:
        self.left -= size
        if self.left < 0:
            raise _OverBudget

    def on_list(self, items: list[Any]) -> list[Any]:
        self._charge(sys.getsizeof(items) + sum(map(sys.getsizeof, items)))
        return items

    def on_map(self, entries: dict[str, Any]) -> dict[str, Any]:
        keys = sum(map(sys.getsizeof, entries.keys()))
        self._charge(sys.getsizeof(entries) + keys + sum(map(sys.getsizeof, entries.values())))
        return entries

    def unpacker(self, data: bytes | bytearray | memoryview) -> msgpack.Unpacker:
        unpacker = msgpack.Unpacker(
            None,
            raw=False,
            strict_map_key=True,
            list_hook=self.on_list,
            object_hook=self.on_map,
            max_buffer_size=max(len(data), 1),
            **_LIMITS,
        )
        unpacker.feed(data)
        return unpacker


def _top_level(data: bytes | bytearray | memoryview, budget: _DecodeBudget) -> dict[str, Any]:
    """The payload's map of fields, in two passes: the first decodes ``schema`` and ``v`` only,
    the second its message's fields; any other field is skipped over without being decoded (a
    newer sender's field, or a decoding bomb under a name no message has), and a map or array
    where its message has a single value or packed bytes is refused from its first byte."""
    raw: dict[str, Any] = {}
    passes: tuple[Set[str] | None, ...] = (frozenset({"schema", "v"}), None)
    containers: Set[str] = frozenset()
    for names in passes:
        unpacker = budget.unpacker(data)
        try:
            entries = unpacker.read_map_header()
        except msgpack.OutOfData:
            raise BadMessage("message", None, "not msgpack: no data") from None
        except ValueError:  # not a map: decode it (within the budget) to say what it is
            whole = budget.unpacker(data).unpack()
            raise BadMessage("message", None, f"expected a msgpack map, got {type(whole).__name__}") from None
        if entries > MAX_FIELDS:
            raise BadMessage("message", None, f"{entries} fields is more than {MAX_FIELDS}")
        if names is None:
            cls = _schema(raw)
            names, containers = _FIELD_NAMES[cls], _CONTAINER_FIELDS[cls]
        for _ in range(entries):
            name = unpacker.unpack()
            if not isinstance(name, str):
                raise BadMessage("message", None, f"not msgpack of named fields: a name is a {type(name).__name__}")
            if name not in names:
                unpacker.skip()
                continue
            if name not in containers and name not in ("schema", "v") and data[unpacker.tell()] in _CONTAINER_HEADERS:
                raise BadMessage(raw["schema"], name, "expected one value or packed bytes, got a msgpack map or array")
            raw[name] = unpacker.unpack()
        try:
            unpacker.skip()
        except msgpack.OutOfData:
            continue
        raise BadMessage("message", None, "not msgpack: extra data after the message")
    return raw


def _schema(raw: Mapping[str, Any]) -> type[Message]:
    """The message type a payload's ``schema`` and ``v`` name, if this fleetmap reads it."""
    if "schema" not in raw:
        raise BadMessage("message", "schema", "missing")
    schema = raw["schema"]
    if not isinstance(schema, str) or schema not in MESSAGE_TYPES:
        raise BadMessage("message", "schema", f"{str(schema)[:64]!r} is not a fleetmap message schema")
    version = raw.get("v")
    cls = MESSAGE_TYPES[schema]
    if isinstance(version, bool) or version not in cls.READS:
        raise BadMessage(schema, "v", f"version {str(version)[:32]} is not one this fleetmap reads {cls.READS}")
    return cls


def unpack(data: bytes) -> dict[str, Any]:
    """The msgpack map of a payload, with its schema and version checked, not yet its fields.

    Decoding is bounded twice: every item's header is checked against the limits before it is
    allocated, and what is decoded is counted as it is built (:class:`_DecodeBudget`), so a payload
    costs at most a fixed multiple of its size whatever it packs. Fields its message does not have
    are skipped without being decoded."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise BadMessage("message", None, f"expected bytes, got {type(data).__name__}")
    if len(data) > MAX_PAYLOAD_BYTES:
        raise BadMessage("message", None, f"{len(data)} bytes is more than {MAX_PAYLOAD_BYTES}")
    try:
        if len(data) * (_MOST_PER_BYTE - DECODED_BYTES_PER_BYTE) <= DECODED_SLACK:
            raw = msgpack.unpackb(data, raw=False, strict_map_key=True, **_LIMITS)
            if not isinstance(raw, dict):
                raise BadMessage("message", None, f"expected a msgpack map, got {type(raw).__name__}")
        else:
            raw = _top_level(data, _DecodeBudget(len(data)))
    except _OverBudget:
        raise BadMessage(
            "message", None, f"{len(data)} bytes decode into more than {DECODED_BYTES_PER_BYTE} times their size"
        ) from None
    except (msgpack.UnpackException, ValueError) as exc:
        raise BadMessage("message", None, f"not msgpack: {exc}"[:200]) from None
    _schema(raw)
    return raw


def decode(data: bytes) -> Message:
    """The message of a payload, every field validated; BadMessage names what is wrong."""
    raw = unpack(data)
    try:
        return MESSAGE_TYPES[raw["schema"]]._from_wire(raw)
    except BadMessage:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError, IndexError, RecursionError) as exc:
        # a field of a shape no check foresaw: still a bad message, never a dead service
        raise BadMessage(raw["schema"], None, f"malformed: {type(exc).__name__}: {exc}"[:200]) from None
