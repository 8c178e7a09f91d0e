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

This module is where a service takes its messages from: the messages, the parts they are built of
(:mod:`fleetmap.shared.io.message_parts`) and :class:`BadMessage` (:data:`__all__`). The checks of
one field are in :mod:`fleetmap.shared.io.wire_fields`, the wire form of values in
:mod:`fleetmap.shared.io.wire_form`, and the bounded msgpack decoding in
:mod:`fleetmap.shared.io.wire_decoding`.
"""

from __future__ import annotations

from collections.abc import Mapping, Set
from dataclasses import MISSING, dataclass, fields
from typing import Any, ClassVar, Self

import msgpack
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.io import wire_fields as field
from fleetmap.shared.io.message_parts import Component, EpochLink, LaserRanges, SubmapLink
from fleetmap.shared.io.wire_decoding import unpack_bounded
from fleetmap.shared.io.wire_fields import MAX_KEY_NUMBER, MAX_MAPS, MAX_SEGMENTS, MAX_STAMP, BadMessage
from fleetmap.shared.io.wire_form import to_wire

__all__ = [
    "EVENT_KINDS",
    "MESSAGE_TYPES",
    "BadMessage",
    "Component",
    "EpochLink",
    "FleetEvent",
    "GlobalMap",
    "LaserRanges",
    "LocalMap",
    "MergeEdge",
    "MergerStep",
    "Message",
    "RobotPose",
    "Scan",
    "SubmapLink",
    "WireMessage",
    "decode",
    "unpack",
]

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
            out[f.name] = to_wire(getattr(self, f.name))
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
        field.assign(self, "robot", field.robot(s, "robot", self.robot))
        field.assign(self, "epoch", field.count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        field.assign(self, "index", field.count(s, "index", self.index))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))
        field.assign(self, "segments", field.segments(s, "segments", self.segments))
        if self.ranges is not None:
            field.assign(self, "ranges", field.part(LaserRanges, s, "ranges", self.ranges))
        field.assign(self, "submap", field.optional_count(s, "submap", self.submap, MAX_KEY_NUMBER))
        field.assign(self, "pose", field.optional_transform(s, "pose", self.pose))
        field.assign(self, "odometry", field.optional_transform(s, "odometry", self.odometry))
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
        field.assign(self, "robot", field.robot(s, "robot", self.robot))
        field.assign(self, "epoch", field.count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        field.assign(self, "version", field.count(s, "version", self.version))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))
        field.assign(self, "segments", field.segments(s, "segments", self.segments))
        field.assign(self, "scans", field.count(s, "scans", self.scans))
        field.assign(self, "pose", field.optional_transform(s, "pose", self.pose))
        if self.viewpoints is not None:
            field.assign(self, "viewpoints", field.viewpoints(s, "viewpoints", self.viewpoints))
        if self.previous_epoch_link is not None:
            link = field.part(EpochLink, s, "previous_epoch_link", self.previous_epoch_link)
            if link.epoch >= self.epoch:
                raise BadMessage(s, "previous_epoch_link.epoch", f"{link.epoch} is not before epoch {self.epoch}")
            field.assign(self, "previous_epoch_link", link)
        field.assign(self, "submap", field.count(s, "submap", self.submap, MAX_KEY_NUMBER))
        field.assign(self, "final", field.flag(s, "final", self.final))
        field.assign(self, "frame_scan", field.optional_count(s, "frame_scan", self.frame_scan))
        if self.link is not None:
            submap_link = field.part(SubmapLink, s, "link", self.link)
            if submap_link.submap != self.submap - 1:
                raise BadMessage(s, "link.submap", f"{submap_link.submap} is not the submap before {self.submap}")
            field.assign(self, "link", submap_link)
        table = (self.scan_indices, self.scan_stamps, self.scan_poses)
        if any(part is not None for part in table):
            if any(part is None for part in table):
                raise BadMessage(s, "scan_indices", "scan_indices, scan_stamps and scan_poses go together")
            indices = field.int_rows(s, "scan_indices", self.scan_indices, MAX_SEGMENTS)
            stamps = field.float_rows(s, "scan_stamps", field.column(self.scan_stamps), "stamp", "stamp", MAX_SEGMENTS)[
                :, 0
            ]
            if len(stamps) and stamps.min() < 0:
                raise BadMessage(s, "scan_stamps", f"stamp {float(stamps.min())} is negative")
            if len(stamps) and stamps.max() > MAX_STAMP:
                raise BadMessage(s, "scan_stamps", f"stamp {float(stamps.max()):g} s is after the year 2262")
            poses = field.float_rows(s, "scan_poses", self.scan_poses, "x, y, theta", "pose", MAX_SEGMENTS)
            if not len(indices) == len(stamps) == len(poses):
                raise BadMessage(
                    s, "scan_poses", f"{len(indices)} indices, {len(stamps)} stamps and {len(poses)} poses differ"
                )
            field.assign(self, "scan_indices", indices)
            field.assign(self, "scan_stamps", field.readonly(stamps))
            field.assign(self, "scan_poses", field.readonly(poses))

    @property
    def key(self) -> str:
        """The map key ``<robot>/<epoch>`` of the epoch this submap belongs to."""
        return f"{self.robot}/{self.epoch}"

    @property
    def submap_key(self) -> str:
        """The submap's own key ``<robot>/<epoch>/<submap>``."""
        return f"{self.robot}/{self.epoch}/{self.submap}"


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
        field.assign(self, "a", field.map_key(s, "a", self.a))
        field.assign(self, "b", field.map_key(s, "b", self.b))
        if self.a == self.b:
            raise BadMessage(s, "b", f"an edge joins two different maps, got {self.a!r} twice")
        for name in ("x", "y", "theta"):
            field.assign(self, name, field.number(s, name, getattr(self, name)))
        field.assign(self, "value", field.number(s, "value", self.value, minimum=0.0))
        field.assign(self, "valid", field.flag(s, "valid", self.valid))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))

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
        field.assign(self, "seq", field.count(s, "seq", self.seq))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))
        raw = field.sequence(s, "components", self.components, MAX_MAPS)
        components = tuple(field.part(Component, s, f"components[{i}]", c) for i, c in enumerate(raw))
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
        field.assign(self, "components", components)

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
        field.assign(self, "robot", field.robot(s, "robot", self.robot))
        field.assign(self, "epoch", field.count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))
        field.assign(self, "pose", field.optional_transform(s, "pose", self.pose))
        field.assign(self, "component", field.optional_count(s, "component", self.component))
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
            field.assign(self, "robot", field.robot(s, "robot", self.robot))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))
        field.assign(self, "detail", field.text(s, "detail", self.detail))


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
        field.assign(self, "integrations", field.optional_count(s, "integrations", self.integrations))
        field.assign(self, "queued", field.optional_count(s, "queued", self.queued))
        field.assign(self, "seq", field.count(s, "seq", self.seq))
        field.assign(self, "stamp", field.stamp(s, "stamp", self.stamp))
        maps = field.sequence(s, "maps", self.maps, MAX_MAPS)
        versions = field.sequence(s, "versions", self.versions, MAX_MAPS)
        if len(maps) != len(versions):
            raise BadMessage(s, "versions", f"{len(versions)} versions for {len(maps)} maps")
        field.assign(self, "maps", tuple(field.map_key(s, f"maps[{i}]", m) for i, m in enumerate(maps)))
        field.assign(self, "versions", tuple(field.count(s, f"versions[{i}]", v) for i, v in enumerate(versions)))


Message = Scan | LocalMap | MergeEdge | GlobalMap | RobotPose | FleetEvent | MergerStep
"""Any message of the bus."""

_CONTAINER_TYPES = ("Transform2D", "LaserRanges", "EpochLink", "SubmapLink", "tuple[")
"""What a field's annotation names when its wire value is a msgpack map or array; every other
field is one number, string or flag, or packed bytes (arrays travel as bins, and always have)."""


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
    allocated, and what is decoded is counted as it is built (:mod:`~fleetmap.shared.io.wire_decoding`), so a payload
    costs at most a fixed multiple of its size whatever it packs. Fields its message does not have
    are skipped without being decoded."""
    raw = unpack_bounded(data, _fields_of)
    _schema(raw)
    return raw


def _fields_of(raw: Mapping[str, Any]) -> tuple[Set[str], Set[str]]:
    """The fields worth decoding of the message ``raw`` names, and which of them are containers."""
    cls = _schema(raw)
    return _FIELD_NAMES[cls], _CONTAINER_FIELDS[cls]


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
