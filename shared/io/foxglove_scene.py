"""What a person sees of a session in Foxglove: the Foxglove-typed views of fleet messages.

Foxglove does not decode msgpack, so a recording (:mod:`fleetmap.shared.io.recording`) and the
live view (``fleetmap view``) write, beside each fleet message, its views: ``foxglove.SceneUpdate``
line lists on ``/foxglove/<key>`` for scans, local maps and global maps, ``foxglove.FrameTransform``
on ``/tf`` for where local maps and robots are, ``foxglove.Log`` for fleet events, and, for the
session so far, each robot's path and the largest component's occupancy grid.

Frames: a scan is drawn in its robot's frame (``r1``), a local map in its own frame (its map key,
``r1/0``), global map component k in ``global`` (k = 0) or ``global/<k>``; a global map places its
members' frames in its component frames, and a robot pose places the robot's frame.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.io.messages import FleetEvent, GlobalMap, LaserRanges, LocalMap, Scan
from fleetmap.shared.io.messages import Message as FleetMessage
from fleetmap.shared.io.occupancy import Beams, occupancy_grid, placed_scans
from foxglove import Schema
from foxglove.messages import (
    Color,
    FrameTransform,
    Grid,
    LaserScan,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    Pose,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    Timestamp,
    Vector2,
    Vector3,
)

FOXGLOVE_PREFIX = "/foxglove/"
TF_TOPIC = "/tf"

SCENE_UPDATE: Schema = SceneUpdate.get_schema()
FRAME_TRANSFORM: Schema = FrameTransform.get_schema()
LOG: Schema = Log.get_schema()
LASER_SCAN: Schema = LaserScan.get_schema()
POSES_IN_FRAME: Schema = PosesInFrame.get_schema()
GRID: Schema = Grid.get_schema()
ROOT_FRAME = "fleet"
"""The frame every other reaches: component 0's frame sits on it, the other components beside it."""
COMPONENT_GAP = 5.0
"""Metres between components laid side by side in the root frame (their relation is unknown)."""
PATH_POSES = 1000
"""The most poses a robot's drawn path holds (evenly thinned beyond)."""

PALETTE = (
    (0.12, 0.47, 0.71),
    (1.00, 0.50, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.40, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.09, 0.75, 0.81),
)
"""Robot colours (matplotlib's tab10, without its greys and olive)."""


@dataclass(frozen=True)
class FoxgloveView:
    """One Foxglove-typed message to write for a fleet message."""

    topic: str
    schema: Schema
    data: bytes


def robot_color(robot: str, alpha: float = 1.0) -> Color:
    r, g, b = PALETTE[zlib.crc32(robot.encode()) % len(PALETTE)]
    return Color(r=r, g=g, b=b, a=alpha)


def component_frame(index: int) -> str:
    """The Foxglove frame of global map component ``index``: ``global`` for the first one."""
    return "global" if index == 0 else f"global/{index}"


def _timestamp(stamp: float) -> Timestamp:
    sec = math.floor(stamp)
    return Timestamp(sec, min(round((stamp - sec) * 1e9), 999_999_999))


def _lines(segments: Array, color: Color, thickness: float) -> LinePrimitive:
    points = [Point3(x=x, y=y, z=0.0) for x, y in np.asarray(segments).reshape(-1, 2).tolist()]
    return LinePrimitive(
        type=LinePrimitiveLineType.LineList, thickness=thickness, scale_invariant=True, points=points, color=color
    )


def _entity(entity_id: str, frame: str, stamp: float, segments: Array, color: Color, thickness: float) -> SceneEntity:
    return SceneEntity(
        timestamp=_timestamp(stamp),
        frame_id=frame,
        id=entity_id,
        lines=[_lines(segments, color, thickness)] if len(segments) else [],
    )


def _frame_transform(parent: str, child: str, pose: Transform2D, stamp: float) -> bytes:
    return FrameTransform(
        timestamp=_timestamp(stamp),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=pose.x, y=pose.y, z=0.0),
        rotation=_yaw(pose.theta),
    ).encode()


def _yaw(theta: float) -> Quaternion:
    """The rotation by ``theta`` about the vertical."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2.0), w=math.cos(theta / 2.0))


def foxglove_views(message: FleetMessage, key: str, at: float | None = None) -> list[FoxgloveView]:
    """What a person sees of ``message`` (received on ``key``) in Foxglove; pure. ``at`` (s) stamps
    the views, by default the message's own stamp: a recorder stamps them with their log time, so
    that Foxglove finds every view and every frame on the one clock it plays the file by (a
    simulated robot's stamps start at 0, a real one's are its own clock)."""
    topic = FOXGLOVE_PREFIX + key
    stamp = message.stamp if at is None else at
    match message:
        case Scan():
            entity = _entity(
                f"scan/{message.robot}",
                message.robot,
                stamp,
                message.segments,
                robot_color(message.robot, 0.5),
                1.0,
            )
            views = [FoxgloveView(topic, SCENE_UPDATE, SceneUpdate(entities=[entity]).encode())]
            if message.ranges is not None:
                r = message.ranges
                n = len(r.ranges)
                with np.errstate(invalid="ignore"):
                    seen = np.where(np.isfinite(r.ranges) & (r.ranges > 0) & (r.ranges < r.range_max), r.ranges, np.nan)
                laser = LaserScan(
                    timestamp=_timestamp(stamp),
                    frame_id=message.robot,
                    pose=_pose3(Transform2D()),
                    start_angle=r.angle_min,
                    end_angle=r.angle_min + (n - 1) * r.angle_increment,
                    ranges=seen.tolist(),
                    intensities=[],
                )
                views.append(FoxgloveView(topic + "/laser", LASER_SCAN, laser.encode()))
            if message.submap is not None and message.pose is not None:
                # the robot's frame hangs on the submap that placed its scan (global -> submap -> robot)
                parent = f"{message.robot}/{message.epoch}/{message.submap}"
                views.append(
                    FoxgloveView(
                        TF_TOPIC, FRAME_TRANSFORM, _frame_transform(parent, message.robot, message.pose, stamp)
                    )
                )
            return views
        case LocalMap():
            frame = message.submap_key
            entity = _entity(frame, frame, stamp, message.segments, robot_color(message.robot), 2.0)
            return [FoxgloveView(topic, SCENE_UPDATE, SceneUpdate(entities=[entity]).encode())]
        case GlobalMap():
            white = Color(r=0.9, g=0.9, b=0.9, a=1.0)
            entities = [
                _entity(f"component/{i}", component_frame(i), stamp, c.segments, white, 2.0)
                for i, c in enumerate(message.components)
            ]
            # components merge and reorder: drop the previous global map's entities first
            drop = SceneEntityDeletion(timestamp=_timestamp(stamp), type=SceneEntityDeletionType.All)
            views = [FoxgloveView(topic, SCENE_UPDATE, SceneUpdate(deletions=[drop], entities=entities).encode())]
            for i, offset in enumerate(_side_by_side(message)):
                data = _frame_transform(ROOT_FRAME, component_frame(i), offset, stamp)
                views.append(FoxgloveView(TF_TOPIC, FRAME_TRANSFORM, data))
            for i, component in enumerate(message.components):
                for member, pose in component.poses.items():
                    data = _frame_transform(component_frame(i), member, pose, stamp)
                    views.append(FoxgloveView(TF_TOPIC, FRAME_TRANSFORM, data))
            return views
        case FleetEvent():
            text = f"{message.kind} {message.robot or ''} {message.detail}".strip()
            entry = Log(timestamp=_timestamp(stamp), level=LogLevel.Info, message=text, name="fleetmap")
            return [FoxgloveView(topic, LOG, entry.encode())]
    # a robot's pose is drawn by its scans (its frame on its submap's); merge edges have no view
    return []


def _pose3(pose: Transform2D) -> Pose:
    return Pose(position=Vector3(x=pose.x, y=pose.y, z=0.0), orientation=_yaw(pose.theta))


def _side_by_side(message: GlobalMap) -> list[Transform2D]:
    """Where each component's frame sits in the root frame: the first at its origin, each other to
    the right of the one before, ``COMPONENT_GAP`` apart (how they relate is not known: that is why
    they are separate)."""
    out: list[Transform2D] = []
    right = 0.0
    for i, c in enumerate(message.components):
        seg = np.asarray(c.segments).reshape(-1, 2)
        low, high = (float(seg[:, 0].min()), float(seg[:, 0].max())) if len(seg) else (0.0, 0.0)
        x = 0.0 if i == 0 else right + COMPONENT_GAP - low
        out.append(Transform2D(x, 0.0, 0.0))
        right = x + high
    return out


class FoxgloveScene:
    """The Foxglove views of a session's messages in bus order (:func:`foxglove_views`), and what
    takes the session so far: each robot's path in its component (``PosesInFrame`` on
    ``/foxglove/<fleet>/paths/<robot>``), drawn at every global map from the scans its submaps
    hold, at their submaps' poses there; and, when the recording is finished, the largest
    component's occupancy grid (``foxglove.Grid`` on ``/foxglove/<fleet>/grid``,
    :mod:`fleetmap.shared.io.occupancy`; :meth:`grid_views` for the grid so far)."""

    def __init__(self) -> None:
        self._tables: dict[str, tuple[Array, Array]] = {}
        self._ranges: dict[tuple[str, int], LaserRanges] = {}
        self._last: tuple[GlobalMap, str] | None = None

    def views(self, message: FleetMessage, key: str, at: float | None = None) -> list[FoxgloveView]:
        """:func:`foxglove_views`, and the paths at a global map (stamped ``at`` too)."""
        out = foxglove_views(message, key, at)
        if isinstance(message, LocalMap) and message.scan_indices is not None and message.scan_poses is not None:
            self._tables[message.submap_key] = (np.asarray(message.scan_indices), np.asarray(message.scan_poses))
        elif isinstance(message, Scan) and message.ranges is not None:
            self._ranges[(message.robot, message.index)] = message.ranges
        elif isinstance(message, GlobalMap):
            prefix = key.rsplit("/", 2)[0] if key.count("/") >= 2 else key
            self._last = (message, prefix)
            out += self._paths(message, prefix, message.stamp if at is None else at)
        return out

    def final_views(self, at: float | None = None) -> list[FoxgloveView]:
        """The views of the whole session (its occupancy grid), once it is over (stamped ``at``,
        by default the last global map's stamp)."""
        return self.grid_views(at)

    def grid_views(self, at: float | None = None) -> list[FoxgloveView]:
        """The largest component's occupancy grid as the session has it so far (stamped ``at``, by
        default the last global map's stamp); none before the first global map. A recording
        writes it once, at its end; a live view now and then."""
        if self._last is None or not self._last[0].components:
            return []
        message, prefix = self._last
        main = message.components[0]
        beams = [
            Beams(pose, r.angle_min, r.angle_increment, r.range_max, r.ranges)
            for scan, (_, pose) in sorted(placed_scans(main.poses, self._tables).items())
            if (r := self._ranges.get(scan)) is not None
        ]
        grid = occupancy_grid(beams, np.asarray(main.segments))
        cols = grid.cells.shape[1]
        drawn = Grid(
            timestamp=_timestamp(message.stamp if at is None else at),
            frame_id=component_frame(0),
            pose=_pose3(Transform2D(grid.origin[0], grid.origin[1], 0.0)),
            column_count=cols,
            cell_size=Vector2(x=grid.resolution, y=grid.resolution),
            row_stride=cols,
            cell_stride=1,
            fields=[PackedElementField(name="occupancy", offset=0, type=PackedElementFieldNumericType.Int8)],
            data=grid.cells.astype(np.int8).tobytes(),
        )
        return [FoxgloveView(f"{FOXGLOVE_PREFIX}{prefix}/grid", GRID, drawn.encode())]

    def _paths(self, message: GlobalMap, prefix: str, stamp: float) -> list[FoxgloveView]:
        out = []
        for i, component in enumerate(message.components):
            paths: dict[str, dict[int, Transform2D]] = {}
            for (robot, index), (_, pose) in placed_scans(component.poses, self._tables).items():
                paths.setdefault(robot, {})[index] = pose
            for robot, placed in sorted(paths.items()):
                order = sorted(placed)
                keep = order[:: max(1, -(-len(order) // PATH_POSES))]
                drawn = PosesInFrame(
                    timestamp=_timestamp(stamp),
                    frame_id=component_frame(i),
                    poses=[_pose3(placed[k]) for k in keep],
                )
                out.append(FoxgloveView(f"{FOXGLOVE_PREFIX}{prefix}/paths/{robot}", POSES_IN_FRAME, drawn.encode()))
        return out
