"""Session recordings in MCAP: the writer, the Foxglove views of fleet messages, and the reader.

A recording holds two kinds of channels:

- **raw** channels, one per key expression seen on the bus: topic = the key, message encoding
  ``msgpack``, no schema, the exact payload bytes; ``log_time`` is when the recorder received the
  message, ``publish_time`` the message's own stamp. Replays read these.
- **Foxglove** channels, so a person can open the session in Foxglove (which does not decode
  msgpack): ``foxglove.SceneUpdate`` line lists on ``/foxglove/<key>`` for scans, local maps and
  global maps, ``foxglove.FrameTransform`` on ``/tf`` for where local maps and robots are, and
  ``foxglove.Log`` on ``/foxglove/<fleet events key>`` for fleet events.

Frames: a scan is drawn in its robot's frame (``r1``), a local map in its own frame (its map key,
``r1/0``), global map component k in ``global`` (k = 0) or ``global/<k>``; a global map places its
members' frames in its component frames, and a robot pose places the robot's frame.

Files are chunked and ZSTD-compressed; the recorder flushes every second, so a file cut short by
a crash still holds everything up to its last complete chunk, and :class:`RecordingReader` reads
such a file up to there and reports how much it read.
"""

from __future__ import annotations

import fcntl
import logging
import math
import os
import struct
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from importlib.metadata import version as package_version
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Self

import numpy as np
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.errors import BadInput
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
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Message, Metadata
from mcap.records import Schema as McapSchema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from zstandard import ZstdError

log = logging.getLogger(__name__)

LIBRARY = f"fleetmap {package_version('fleetmap')}"
"""What a recording names as the library that wrote it (the installed package's version: this
layer imports nothing of fleetmap above ``shared``)."""

RAW_ENCODING = "msgpack"
"""The message encoding of the raw channels (registered in the MCAP well-known encodings)."""
FOXGLOVE_PREFIX = "/foxglove/"
TF_TOPIC = "/tf"
PROFILE = ""
"""MCAP profile: none of the registered ones (ros1, ros2) applies."""
CHUNK_SIZE = 1024 * 1024
MAGIC = b"\x89MCAP0\r\n"

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


def seconds_to_ns(stamp: float) -> int:
    return round(stamp * 1e9)


# --- writer ---


def _open_alone(path: Path) -> IO[bytes]:
    """``path`` opened for writing, emptied, and locked for as long as it is open: a second writer
    of the same file (two recorders started together, both finding it free) is refused, not left
    to interleave its records with the first's. The lock goes with the process, however it ends."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    except OSError as exc:
        raise BadInput(str(path), f"cannot write: {exc.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise BadInput(str(path), "another recorder is writing it; give this one another --out") from None
    os.ftruncate(fd, 0)
    return os.fdopen(fd, "wb")


class RecordingWriter:
    """An MCAP file of raw and Foxglove channels. Channels and schemas are registered on first use."""

    def __init__(
        self,
        output: str | Path | IO[bytes],
        *,
        chunk_size: int = CHUNK_SIZE,
        compression: CompressionType = CompressionType.ZSTD,
    ) -> None:
        self._owned: IO[bytes] | None = None
        if isinstance(output, (str, Path)):
            self._owned = _open_alone(Path(output))
            stream: IO[bytes] = self._owned
        else:
            stream = output
        self._writer = Writer(stream, chunk_size=chunk_size, compression=compression)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: Counter[int] = Counter()
        self._finished = False

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def _channel(self, topic: str, encoding: str, schema: Schema | None, metadata: Mapping[str, str]) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            schema_id = 0
            if schema is not None:
                schema_id = self._schemas.get(schema.name, 0)
                if schema_id == 0:
                    schema_id = self._writer.register_schema(schema.name, schema.encoding, schema.data)
                    self._schemas[schema.name] = schema_id
            channel_id = self._writer.register_channel(topic, encoding, schema_id, dict(metadata))
            self._channels[topic] = channel_id
        return channel_id

    def write_raw(self, topic: str, payload: bytes, log_time: int, publish_time: int, source: str = "zenoh") -> None:
        """One message of the bus, bytes as received (``source``: zenoh sample or liveliness change)."""
        channel_id = self._channel(topic, RAW_ENCODING, None, {"source": source})
        self._add(channel_id, payload, log_time, publish_time)

    def write_foxglove(self, topic: str, schema: Schema, data: bytes, log_time: int, publish_time: int) -> None:
        channel_id = self._channel(topic, schema.encoding, schema, {})
        self._add(channel_id, data, log_time, publish_time)

    def _add(self, channel_id: int, data: bytes, log_time: int, publish_time: int) -> None:
        self._sequence[channel_id] += 1
        self._writer.add_message(channel_id, log_time, data, publish_time, sequence=self._sequence[channel_id])

    def flush(self) -> None:
        """End the chunk in progress and push it to the file, so a crash cannot lose it."""
        self._writer.flush()

    def finish(self) -> None:
        """Write the indexes and the summary; closes the file if this writer opened it."""
        if self._finished:
            return
        self._finished = True
        self._writer.finish()
        if self._owned is not None:
            self._owned.close()


def config_metadata(config: FleetmapConfig) -> dict[str, str]:
    """A config as MCAP metadata: every ``section.field`` and the whole TOML."""
    out = {name: str(value) for name, value in config.flat().items()}
    out["toml"] = config.to_toml()
    return out


# --- Foxglove views ---


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


# --- reader ---


@dataclass(frozen=True)
class RecordedMessage:
    """One raw message of a recording: the key it was received on and its exact bytes."""

    topic: str
    payload: bytes
    log_time: int
    """When the recorder received it (ns since the Unix epoch)."""
    publish_time: int
    """The message's own stamp (ns), or log_time when it had none."""
    sequence: int


@dataclass(frozen=True)
class ReadReport:
    """How much of a recording was read."""

    source: str
    complete: bool
    """Whether the file was finished (has its summary); a crashed recorder leaves it incomplete."""
    messages: int
    bytes_read: int
    """For an incomplete file: up to the end of its last complete record."""
    file_bytes: int

    @property
    def warning(self) -> str | None:
        if self.complete:
            return None
        return (
            f"{self.source}: the recording ends abruptly (not finished by its recorder): read {self.messages} "
            f"messages from its complete chunks, {self.bytes_read} of {self.file_bytes} bytes"
        )


class _Truncated(Exception):
    """The stream ended inside a record."""


CORRUPT = (McapError, ValueError, struct.error, KeyError, IndexError, OverflowError, ZstdError, RuntimeError)
"""What the mcap library raises, besides its own errors, on a file whose bytes are damaged (a text
field that is no UTF-8, a length past the end, a chunk that does not decompress: zstd or lz4)."""


class _ExactReader:
    """A stream whose short reads raise _Truncated, so a cut-off file ends in one known way."""

    def __init__(self, stream: IO[bytes]) -> None:
        self._stream = stream
        self.position = 0

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        if size >= 0 and len(data) < size:
            raise _Truncated
        self.position += len(data)
        return data


@dataclass(frozen=True)
class RecoverReport:
    """What :meth:`RecordingReader.recover` rewrote."""

    source: str
    messages: int
    """Messages on every channel (raw and Foxglove views)."""
    channels: int
    bytes_read: int
    """Bytes of the source up to its last complete record ..."""
    size: int
    """... of its size."""


def _corrupt(source: str, exc: Exception) -> BadInput:
    """The one line that says a file's bytes are damaged, in plain words."""
    if isinstance(exc, UnicodeDecodeError):
        why = f"a name in it is not UTF-8 text (byte {exc.start})"
    else:
        why = str(exc) or type(exc).__name__
    return BadInput(source, f"corrupt MCAP file: {why}"[:300])


class RecordingReader:
    """The raw messages of a recording, from a finished file or one a crash cut short.

    ``messages()`` yields them in log-time order (the recorder gives every message a later log
    time than the one before, so file order is log-time order also where no index can be used);
    afterwards ``report`` says how much was read, and ``report.warning`` is set for a cut-off file.
    Foxglove channels are skipped: they are views, not data.
    """

    def __init__(self, source: str | Path | IO[bytes]) -> None:
        self._owned: IO[bytes] | None = None
        if isinstance(source, (str, Path)):
            self.source = str(source)
            try:
                self._owned = open(source, "rb")  # noqa: SIM115 - closed by close()
            except FileNotFoundError:
                raise BadInput(self.source, "no such file") from None
            except OSError as exc:
                raise BadInput(self.source, f"cannot read: {exc.strerror}") from None
            self._stream: IO[bytes] = self._owned
        else:
            self.source = getattr(source, "name", "<stream>")
            self._stream = source
        self._start = self._stream.tell()
        self._size = self._stream.seek(0, 2) - self._start
        if self._size < len(MAGIC) or self._read_at(0, len(MAGIC)) != MAGIC:
            raise BadInput(self.source, "not an MCAP file")
        self.complete = self._size >= 2 * len(MAGIC) and self._read_at(self._size - len(MAGIC), len(MAGIC)) == MAGIC
        self._messages = 0
        self._bytes_read = self._size if self.complete else 0

    def _read_at(self, offset: int, size: int) -> bytes:
        self._stream.seek(self._start + offset)
        return self._stream.read(size)

    @property
    def report(self) -> ReadReport:
        return ReadReport(self.source, self.complete, self._messages, self._bytes_read, self._size)

    def messages(
        self,
        *,
        topics: Iterable[str] | None = None,
        start_time: int | None = None,
        end_time: int | None = None,
        warn: bool = True,
    ) -> Iterator[RecordedMessage]:
        """Raw messages with ``start_time <= log_time < end_time`` (ns), on ``topics`` if given; a
        recording that ends abruptly is logged at WARNING once read (unless ``warn`` is False: the
        caller says it, ``report.warning``)."""
        self._messages = 0
        wanted = set(topics) if topics is not None else None
        records = self._indexed() if self.complete else self._streamed()
        for channel, message in records:
            if channel.message_encoding != RAW_ENCODING or (wanted is not None and channel.topic not in wanted):
                continue
            if (start_time is not None and message.log_time < start_time) or (
                end_time is not None and message.log_time >= end_time
            ):
                continue
            self._messages += 1
            yield RecordedMessage(channel.topic, message.data, message.log_time, message.publish_time, message.sequence)
        if not self.complete and warn:
            log.warning("%s", self.report.warning)

    def _indexed(self) -> Iterator[tuple[Channel, Message]]:
        self._stream.seek(self._start)
        try:
            for _, channel, message in make_reader(self._stream).iter_messages(log_time_order=True):
                yield channel, message
        except CORRUPT as exc:
            raise _corrupt(self.source, exc) from None

    def _records(self, emit_chunks: bool) -> Iterator[Any]:
        """Every complete record of a file with no summary; stops (quietly) at the cut."""
        self._stream.seek(self._start)
        exact = _ExactReader(self._stream)
        self._bytes_read = 0
        try:
            for record in StreamReader(exact, emit_chunks=emit_chunks).records:  # type: ignore[arg-type]
                self._bytes_read = exact.position
                yield record
        except _Truncated:
            return
        except CORRUPT as exc:
            raise _corrupt(self.source, exc) from None

    def _streamed(self) -> Iterator[tuple[Channel, Message]]:
        channels: dict[int, Channel] = {}
        last_log_time = -1
        for record in self._records(emit_chunks=False):
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                if record.log_time < last_log_time:
                    log.warning("%s: messages out of log-time order; replaying them in file order", self.source)
                last_log_time = max(last_log_time, record.log_time)
                yield channels[record.channel_id], record

    def recover(self, target: IO[bytes]) -> RecoverReport:
        """Rewrite every complete record of this file into ``target`` as a finished MCAP file, with
        indexes and a summary, so any reader opens it (as ``mcap recover`` and ``ros2 bag reindex``
        do): schemas, channels (Foxglove views included), messages with their times and sequence
        numbers, metadata and attachments. A finished file is copied the same way."""
        writer = Writer(target, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        writer.start(profile=PROFILE, library=f"{LIBRARY} (recovered)")
        schemas: dict[int, int] = {0: 0}
        channels: dict[int, int] = {}
        messages = 0
        for record in self._records(emit_chunks=False):
            if isinstance(record, McapSchema):
                schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.schema_id in schemas:
                channels[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schemas[record.schema_id], dict(record.metadata)
                )
            elif isinstance(record, Message) and record.channel_id in channels:
                writer.add_message(
                    channels[record.channel_id], record.log_time, record.data, record.publish_time, record.sequence
                )
                messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
        writer.finish()
        return RecoverReport(self.source, messages, len(channels), self._bytes_read, self._size)

    def metadata(self) -> dict[str, dict[str, str]]:
        """Every metadata record of the file, by name (the recorder's config and session)."""
        out: dict[str, dict[str, str]] = {}
        if self.complete:
            self._stream.seek(self._start)
            try:
                for record in make_reader(self._stream).iter_metadata():
                    out[record.name] = dict(record.metadata)
            except CORRUPT as exc:
                raise _corrupt(self.source, exc) from None
            return out
        for record in self._records(emit_chunks=True):
            if isinstance(record, Metadata):
                out[record.name] = dict(record.metadata)
        return out

    def topic_counts(self) -> dict[str, int]:
        """How many raw messages each topic holds (reads the whole file)."""
        return dict(Counter(m.topic for m in self.messages()))

    def close(self) -> None:
        if self._owned is not None:
            self._owned.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
