"""The parts bus messages are built of: a scan's laser readings, the links between epochs and
between submaps, and a global map's components.

Each part is a frozen dataclass that checks its fields when it is built (with the checks of
:mod:`fleetmap.shared.io.wire_fields`), as the messages that carry them do; on the wire a part is a
msgpack map of its fields, nested in its message (:mod:`fleetmap.shared.io.messages`).
"""

from __future__ import annotations

import types
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.io import wire_fields as field
from fleetmap.shared.io.wire_fields import MAX_KEY_NUMBER, MAX_MAPS, BadMessage


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
        field.assign(self, "angle_min", field.number(s, "angle_min", self.angle_min))
        field.assign(self, "angle_increment", field.number(s, "angle_increment", self.angle_increment))
        if self.angle_increment == 0.0:
            raise BadMessage(s, "angle_increment", "is zero")
        range_max = self.range_max
        if isinstance(range_max, bool) or not isinstance(range_max, (int, float, np.integer, np.floating)):
            raise BadMessage(s, "range_max", f"expected a number, got {type(range_max).__name__}")
        if not float(range_max) > 0.0:  # infinity is allowed: a log that does not say its range
            raise BadMessage(s, "range_max", f"{range_max} is not a positive number")
        field.assign(self, "range_max", float(range_max))
        field.assign(self, "ranges", field.ranges(s, "ranges", self.ranges))

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
        field.assign(self, "epoch", field.count(s, "epoch", self.epoch, MAX_KEY_NUMBER))
        field.assign(self, "reason", field.text(s, "reason", self.reason))
        field.assign(self, "transform", field.optional_transform(s, "transform", self.transform))


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
        field.assign(self, "submap", field.count(s, "submap", self.submap, MAX_KEY_NUMBER))
        field.assign(self, "transform", field.transform(s, "transform", self.transform))
        field.assign(self, "covariance", field.covariance(s, "covariance", self.covariance))

    @property
    def covariance_matrix(self) -> Array:
        return np.array(self.covariance, dtype=np.float64).reshape(3, 3)


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
        field.assign(self, "anchor", field.map_key(s, "anchor", self.anchor))
        members = tuple(
            field.map_key(s, f"members[{i}]", m)
            for i, m in enumerate(field.sequence(s, "members", self.members, MAX_MAPS))
        )
        if len(set(members)) != len(members):
            raise BadMessage(s, "members", "a map is listed twice")
        if self.anchor not in members:
            raise BadMessage(s, "anchor", f"{self.anchor!r} is not one of the members")
        raw_poses = field.mapping(s, "poses", self.poses)
        poses = {}
        for key, pose in raw_poses.items():
            poses[field.map_key(s, "poses", key)] = field.transform(s, f"poses[{key}]", pose)
        if set(poses) != set(members):
            unplaced = sorted(set(members) - set(poses))
            extra = sorted(set(poses) - set(members))
            what = f"members without a pose: {unplaced[:3]}" if unplaced else f"poses of non-members: {extra[:3]}"
            raise BadMessage(s, "poses", what)
        field.assign(self, "members", members)
        field.assign(self, "poses", types.MappingProxyType(poses))
        field.assign(self, "segments", field.segments(s, "segments", self.segments))

    def __reduce__(self) -> tuple[object, ...]:
        """Pickled as its fields, ``poses`` as a dict (a mapping proxy does not pickle): a session's
        log goes to the process that writes its files (:class:`fleetmap.mapping._Files`)."""
        return (Component, (self.anchor, self.members, dict(self.poses), self.segments))
