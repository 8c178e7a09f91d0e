"""Where an agent's scans come from: a CARMEN log, a ROS bag or a ranges JSONL file (one home for
scan input; the simulator is a source of the same kind, :class:`fleetmap.scenarios.stream.ScenarioSource`,
that the command line plugs in). :func:`open_input` opens a file by what it is.

Every source yields :class:`SourceScan` ``(index, stamp, scan)`` in order, with the robot's
odometry at the scan where it has some; ``stamp`` is in seconds and paces a live agent. No true
pose ever leaves a source: a simulation's true poses and the corrected poses written in a CARMEN
log stay in it, so the algorithms see the ranges and the robot's own odometry alone (which tracks
the robot's own scans, never relates two robots' maps).

Odometry, per source (``has_odometry`` says whether there is any):

- **CARMEN**: the ODOM lines, interpolated at the scan's stamp (by file order where the stamps do
  not increase: logs whose times are rounded or missing); without ODOM lines, the odometry pose
  written on the laser line (FLASER/RLASER odom_x, odom_y, odom_theta; ROBOTLASER1's laser pose).
- **ROS bag** (rosbag2 directory, .mcap, .db3; ROS 1 .bag): nav_msgs/Odometry on a topic (found
  by type, or named), else the tf transform
  from the odometry frame to the robot's base (on /tf), interpolated at the scan's stamp; the
  laser's mounting (base to laser, on /tf_static) is applied when the bag has it.
- **ranges JSONL** (the format of ``docs/formats.md``): none.
- **Scenario**: the simulator's wheel odometry (:mod:`fleetmap.scenarios.odometry`): it drifts,
  and it does not see a robot being carried.

Problems with the input raise :class:`~fleetmap.shared.errors.BadInput` naming it: a missing or
unreadable file, a bag without the topic, or a source that yields no scan at all. Files are
checked when the source is made, before an agent goes on the bus.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.logs import (
    OdometryReading,
    read_carmen,
    read_carmen_lines,
    read_carmen_odometry,
    read_ranges_jsonl,
)
from fleetmap.shared.io.wire_fields import MAX_STAMP
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

log = logging.getLogger(__name__)

LASER_SCAN_SCHEMAS = ("sensor_msgs/msg/LaserScan", "sensor_msgs/LaserScan")
"""How a ROS 2 bag names the sensor_msgs/LaserScan schema (the first is what ros2 bag writes)."""
ODOMETRY_SCHEMAS = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
TF_SCHEMAS = ("tf2_msgs/msg/TFMessage", "tf2_msgs/TFMessage")
ODOMETRY_FRAMES = ("odom",)
"""The odometry frame a tf odometry is read from (REP 105)."""
BASE_FRAMES = ("base_link", "base_footprint")
"""The robot's base frames, in order of preference, when its odometry comes from tf (REP 105)."""


@dataclass(frozen=True)
class SourceScan:
    """One scan of a source; unpacks as ``index, stamp, scan``."""

    index: int
    """The scan's number: in the robot's plan (scenario), among the log's laser lines (CARMEN),
    among the topic's messages (ROS 2 bag)."""
    stamp: float
    """Seconds: scenario time, or the time the log or bag gives."""
    scan: RangeScan
    odometry: Transform2D | None = None
    """The robot's odometry pose at the scan (the laser's, in the odometry's own frame: only its
    change from scan to scan means anything); None where the source has none."""
    given: float | None = None
    """The stamp as the input gives it, where it cannot be a time (:class:`BusStamps`); None where
    ``stamp`` is the input's own."""

    def __iter__(self) -> Iterator[Any]:
        return iter((self.index, self.stamp, self.scan))


class ScanSource(Protocol):
    """Scans in order; ``name`` says where they come from (for logs and summaries)."""

    name: str

    @property
    def has_odometry(self) -> bool: ...

    def __iter__(self) -> Iterator[SourceScan]: ...


class BusStamps:
    """A source's stamps as the bus carries them. A stamp that cannot be a time (negative, or not
    finite: a log whose converter counted from its own start, or lost the clock) is read as the last
    usable one repeated, said once: the tracker goes by the scans' sequence where stamps repeat
    (docs/decisions/009-clocks-evidence-over-stamps.md), and ``fleetmap map`` still writes the
    input's own stamp (:attr:`SourceScan.given`). One log seen: infinite-corridor-corrected, stamped
    -0.45 to -1.82 s, then 4.29e9 s throughout."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.last = 0.0
        self.unusable = 0
        self.seen = 0

    def __call__(self, index: int, stamp: float) -> float:
        self.seen += 1
        if math.isfinite(stamp) and stamp >= 0:
            self.last = stamp
            return stamp
        self.unusable += 1
        if self.unusable == 1:
            log.warning(
                "%s: scan %d: stamp %s cannot be a time (it is %s): read as the last usable stamp "
                "(%g s), as is any other such; the scans are tracked by their sequence where stamps repeat",
                self.source,
                index,
                stamp,
                "negative" if stamp < 0 else "not finite",
                self.last,
            )
        return self.last

    def summary(self) -> None:
        """Said at the source's end: how many stamps were read as repeats."""
        if self.unusable > 1:
            log.warning(
                "%s: %d of its %d scans' stamps could not be times (read as the last usable stamp)",
                self.source,
                self.unusable,
                self.seen,
            )


def checked_scan(
    source: str,
    index: int,
    stamp: float,
    scan: RangeScan,
    odometry: Transform2D | None = None,
    stamps: BusStamps | None = None,
) -> SourceScan:
    """The scan as an agent gets it: a valid stamp (``stamps`` reads one that cannot be a time; without
    it, such a stamp is refused) and beam geometry, no pose but the odometry."""
    where = f"{source}: scan {index}"
    given = stamp
    if stamps is not None:
        stamp = stamps(index, stamp)
    if not math.isfinite(stamp) or stamp < 0:
        raise BadInput(where, f"stamp {stamp} is not a finite non-negative number of seconds")
    if stamp > MAX_STAMP:
        raise BadInput(where, f"stamp {stamp:g} s is after the year 2262 (a clock in milliseconds?)")
    if not (math.isfinite(scan.angle_min) and math.isfinite(scan.angle_increment)) or scan.angle_increment == 0:
        raise BadInput(where, f"bad beam angles (angle_min {scan.angle_min}, increment {scan.angle_increment})")
    if not scan.range_max > 0:
        raise BadInput(where, f"range_max {scan.range_max} is not positive")
    bus = replace(scan, stamp=stamp, odom=None, odometry=None)
    return SourceScan(index, stamp, bus, odometry, None if given == stamp else given)


def _existing_file(path: str | Path, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise BadInput(str(path), "no such file")
    if not p.is_file():
        raise BadInput(str(path), f"is not a file ({what} expected)")
    return p


class CarmenSource:
    """Laser scans ``[start:stop:step]`` of a CARMEN log (FLASER, RLASER, ROBOTLASER1; plain or .gz).

    Several agents given parts of one log (``r1``: ``--stop 600``, ``r2``: ``--start 500``) map a
    real building as a fleet whose maps overlap. ``index`` is the scan's position among the log's
    laser lines, so two robots sharing a log name the same scan alike. The log's poses are dropped.
    ``range_max`` is the no-return reading of FLASER/RLASER lines (:func:`~fleetmap.shared.io.logs.read_carmen`).
    """

    def __init__(
        self, path: str | Path, start: int = 0, stop: int | None = None, step: int = 1, range_max: float = math.inf
    ) -> None:
        self.path = _existing_file(path, "a CARMEN log")
        if start < 0:
            raise BadInput("--start", f"must not be negative, got {start}")
        if stop is not None and stop <= start:
            raise BadInput("--stop", f"must be after --start {start}, got {stop}")
        if step < 1:
            raise BadInput("--step", f"must be at least 1, got {step}")
        if not range_max > 0:
            raise BadInput("--no-return-reading", f"must be positive, got {range_max}")
        self.start, self.stop, self.step, self.range_max = start, stop, step, range_max
        self.name = f"{path} [{start}:{'' if stop is None else stop}:{step}]"

    def __iter__(self) -> Iterator[SourceScan]:
        total = 0
        yielded = 0
        track = OdometryTrack(read_carmen_odometry(self.path))
        stamps = BusStamps(str(self.path))
        for index, (line, scan) in enumerate(read_carmen_lines(self.path, self.range_max)):
            total = index + 1
            if self.stop is not None and index >= self.stop:
                break
            if index >= self.start and (index - self.start) % self.step == 0:
                yielded += 1
                odometry = track.at(line, scan.stamp) if track else _pose(scan.odometry)
                yield checked_scan(str(self.path), index, scan.stamp, scan, odometry, stamps)
        stamps.summary()
        if not yielded:
            raise BadInput(str(self.path), f"no laser scan from index {self.start} on (the log has {total})")

    @property
    def has_odometry(self) -> bool:
        """Whether the log has ODOM lines, or odometry on its laser lines (the first one's, read)."""
        if read_carmen_odometry(self.path):
            return True
        first = next(iter(read_carmen(self.path, self.range_max)), None)
        return first is not None and first.odometry is not None


def _pose(value: tuple[float, float, float] | None) -> Transform2D | None:
    return None if value is None else Transform2D(float(value[0]), float(value[1]), float(value[2]))


class OdometryTrack:
    """A robot's odometry readings, to read at a scan: interpolated at its stamp where the readings'
    stamps increase and enclose it; otherwise the last reading before the scan's line in the file
    (logs whose times are rounded or missing)."""

    def __init__(self, readings: list[OdometryReading]) -> None:
        self.readings = readings
        self.mounting: Transform2D | None = None
        """The laser's pose on the robot's base, where the odometry is the base's (ROS tf)."""
        self.stamps = np.array([r.stamp for r in readings])
        self.lines = np.array([r.line for r in readings])
        self.by_time = (
            len(readings) >= 2 and bool(np.all(np.diff(self.stamps) >= 0)) and self.stamps[-1] > self.stamps[0]
        )

    def __bool__(self) -> bool:
        return bool(self.readings)

    def at(self, line: int, stamp: float) -> Transform2D | None:
        """The odometry at a scan; None where the wheels' motion from the reading before it is not
        known (:attr:`~fleetmap.shared.io.logs.OdometryReading.moved`)."""
        r = self.readings
        if self.by_time and self.stamps[0] <= stamp <= self.stamps[-1]:
            j = int(np.searchsorted(self.stamps, stamp, side="right"))
            if j >= len(r):
                return Transform2D(*r[-1].pose) if r[-1].moved else None
            a, b = r[j - 1], r[j]
            if not a.moved:
                return None
            span = b.stamp - a.stamp
            f = (stamp - a.stamp) / span if span > 0 else 0.0
            turn = math.remainder(b.pose[2] - a.pose[2], 2 * math.pi)
            return Transform2D(
                a.pose[0] + f * (b.pose[0] - a.pose[0]),
                a.pose[1] + f * (b.pose[1] - a.pose[1]),
                math.remainder(a.pose[2] + f * turn, 2 * math.pi),
            )
        j = max(int(np.searchsorted(self.lines, line, side="left")) - 1, 0)
        return Transform2D(*r[j].pose) if r[j].moved else None


class Ros2BagSource:
    """sensor_msgs/LaserScan messages of one topic of a ROS bag, in log time order: a rosbag2
    directory (``metadata.yaml`` and its .mcap or .db3 files), one .mcap or .db3 file of one, or a
    ROS 1 .bag. Read with the ``rosbags`` library: no ROS install.

    ``topic`` names the LaserScan topic; without it, the bag's one LaserScan topic (``/scan`` where
    there are several). The stamp is the message header's, or the log time where the header has
    none; readings below ``range_min`` are no return, as in ROS.
    """

    def __init__(self, path: str | Path, topic: str | None = None, odometry_topic: str | None = None) -> None:
        self.path = _existing_bag(path)
        self._types: dict[str, str] = self._guard(self._topic_types)
        topics = ", ".join(f"{t} ({ty})" for t, ty in sorted(self._types.items())) or "none"
        lasers = [t for t, ty in sorted(self._types.items()) if ty in LASER_SCAN_SCHEMAS]
        if topic is None:
            if not lasers:
                raise BadInput(str(path), f"no sensor_msgs/LaserScan topic in the bag (its topics: {topics})")
            if len(lasers) > 1 and "/scan" not in lasers:
                listed = ", ".join(lasers)
                raise BadInput(str(path), f"has {len(lasers)} LaserScan topics ({listed}): name one (--topic)")
            topic = "/scan" if "/scan" in lasers else lasers[0]
        elif topic not in self._types:
            raise BadInput(str(path), f"no topic {topic!r} in the bag (its topics: {topics})")
        elif self._types[topic] not in LASER_SCAN_SCHEMAS:
            raise BadInput(str(path), f"topic {topic!r} carries {self._types[topic]}, not sensor_msgs/LaserScan")
        self.topic = topic
        self.odometry_topic = odometry_topic
        self.name = f"{path} {topic}"
        if odometry_topic is not None and self._types.get(odometry_topic) not in ODOMETRY_SCHEMAS:
            found = [t for t, name in sorted(self._types.items()) if name in ODOMETRY_SCHEMAS]
            raise BadInput(
                str(path),
                f"topic {odometry_topic!r} is not nav_msgs/Odometry (odometry topics: {', '.join(found) or 'none'})",
            )

    def _reader(self) -> AnyReader:
        # the message definitions a bag carries decode it; a .db3 bag written before ROS 2 Iron
        # carries none, and Humble's standard messages do
        return AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))

    def _topic_types(self) -> dict[str, str]:
        with self._reader() as reader:
            return {c.topic: c.msgtype for c in reader.connections}

    @property
    def has_odometry(self) -> bool:
        """Whether the bag has nav_msgs/Odometry (the named topic, or any) or a tf topic."""
        return any(name in ODOMETRY_SCHEMAS + TF_SCHEMAS for name in self._types.values())

    @property
    def topic_types(self) -> dict[str, str]:
        """The bag's topics and their message types."""
        return dict(self._types)

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time in ns, decoded message) of ``topics``, in log time order (undecodable
        ones skipped with a warning); a bag that cannot be read is :class:`BadInput`."""
        return self._decoded(topics)

    def _decoded(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time in ns, message) of ``topics``, in log time order; a bag that cannot be
        read is :class:`BadInput` naming it, wherever it fails."""
        reader = self._guard(self._reader)
        self._guard(reader.open)
        try:
            connections = [c for c in reader.connections if c.topic in topics]
            messages = reader.messages(connections=connections)
            count = 0
            while True:
                item = self._guard(lambda: next(messages, None))
                if item is None:
                    return
                connection, log_time, raw = item
                count += 1
                try:
                    message = reader.deserialize(raw, connection.msgtype)
                except UNDECODABLE as exc:
                    # one message cut or garbled: skipped, said once, as a CARMEN log's bad line
                    log.warning(
                        "%s: message %d on %s (log time %.3f s) cannot be decoded (%s): skipped",
                        self.path,
                        count,
                        connection.topic,
                        log_time * 1e-9,
                        str(exc)[:120],
                    )
                    continue
                yield connection.topic, log_time, message
        finally:
            reader.close()

    def _odometry(self) -> OdometryTrack | None:
        """The robot's odometry over the bag: the named nav_msgs/Odometry topic, else the first one,
        else tf's odom -> base transforms; with the laser's mounting from /tf_static when there."""
        odom_topics = [t for t, name in sorted(self._types.items()) if name in ODOMETRY_SCHEMAS]
        topic = self.odometry_topic or (odom_topics[0] if odom_topics else None)
        tf_topics = [t for t, name in sorted(self._types.items()) if name in TF_SCHEMAS]
        if topic is None and not tf_topics:
            return None
        readings: list[OdometryReading] = []
        mounting: dict[str, Transform2D] = {}
        base: str | None = None
        for name, log_time, ros in self._decoded([t for t in [topic, *tf_topics] if t is not None]):
            if name == topic:
                stamp = _stamp_of(ros.header.stamp, log_time)
                pose = ros.pose.pose
                readings.append(OdometryReading(len(readings), stamp, planar_pose(pose.position, pose.orientation)))
                base = base or ros.child_frame_id
            elif topic is None or name.endswith("tf_static"):
                for t in ros.transforms:
                    planar = planar_pose(t.transform.translation, t.transform.rotation)
                    parent, child = t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/")
                    if name.endswith("tf_static"):
                        mounting[f"{parent}>{child}"] = Transform2D(*planar)
                    elif (
                        topic is None
                        and parent in ODOMETRY_FRAMES
                        and child in BASE_FRAMES
                        and (base is None or child == base)
                    ):
                        base = child
                        stamp = _stamp_of(t.header.stamp, log_time)
                        readings.append(OdometryReading(len(readings), stamp, planar))
        if len(readings) < 2:
            return None
        track = OdometryTrack(readings)
        track.mounting = mounting.get(f"{base}>{self._laser_frame()}") if base else None
        return track

    def _laser_frame(self) -> str:
        for _, _, msg in self._decoded([self.topic]):
            return str(msg.header.frame_id).lstrip("/")
        return ""

    def _guard(self, read: Any) -> Any:
        try:
            return read()
        except BadInput:
            raise
        except (*UNDECODABLE, Rosbag2ReaderError, Rosbag1ReaderError, EOFError, OSError, NotImplementedError) as exc:
            raise BadInput(str(self.path), f"not a readable ROS bag: {exc}"[:300]) from None

    def __iter__(self) -> Iterator[SourceScan]:
        yielded = 0
        track = self._odometry()
        skipped = 0
        for index, (_, log_time, msg) in enumerate(self._decoded([self.topic])):
            try:
                scan = self._scan(index, log_time, msg, track)
            except BadInput as exc:
                skipped += 1
                log.warning("%s: skipped", exc)
                continue
            yielded += 1
            yield scan
        if not yielded and skipped:
            raise BadInput(str(self.path), f"none of its {skipped} LaserScan messages on {self.topic!r} can be used")
        if not yielded:
            raise BadInput(str(self.path), f"no sensor_msgs/LaserScan message on topic {self.topic!r}")

    def _scan(self, index: int, log_time_ns: int, msg: Any, track: OdometryTrack | None = None) -> SourceScan:
        stamp = _stamp_of(msg.header.stamp, log_time_ns)
        return checked_scan(self.name, index, stamp, laser_scan(msg, stamp), laser_odometry(track, stamp))


class RangesSource:
    """The scans of a ranges JSONL file (``docs/formats.md``); no odometry."""

    has_odometry = False

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.name = str(path)

    def __iter__(self) -> Iterator[SourceScan]:
        stamps = BusStamps(self.name)
        for index, scan in enumerate(read_ranges_jsonl(self.path)):
            yield checked_scan(self.name, index, scan.stamp, scan, stamps=stamps)
        stamps.summary()


def open_input(
    path: str | Path, topic: str | None = None, odometry_topic: str | None = None, range_max: float = math.inf
) -> ScanSource:
    """The source of one input, by what it is: a ROS bag (a rosbag2 directory, an .mcap, .db3 or
    ROS 1 .bag file, or a directory holding one such file), a ranges JSONL file (.jsonl), else a
    CARMEN log (plain or .gz)."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return Ros2BagSource(p, topic, odometry_topic)
        bags = sorted(f for f in p.iterdir() if f.suffix in BAG_SUFFIXES)
        if not bags:
            raise BadInput(str(path), "is a directory with no ROS bag (no metadata.yaml, .mcap, .db3 or .bag file)")
        if len(bags) > 1:
            raise BadInput(str(path), f"holds {len(bags)} bag files and no metadata.yaml; name one of them")
        return Ros2BagSource(bags[0], topic, odometry_topic)
    if not p.exists():
        raise BadInput(str(path), "no such file")
    if p.suffix in BAG_SUFFIXES:
        return Ros2BagSource(p, topic, odometry_topic)
    if p.name.endswith((".jsonl", ".jsonl.gz")):
        return RangesSource(p)
    return CarmenSource(p, range_max=range_max)


def laser_scan(msg: Any, stamp: float) -> RangeScan:
    """A sensor_msgs/LaserScan as a RangeScan: readings below ``range_min`` are no return, as in ROS."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        ranges[ranges < msg.range_min] = np.nan
    range_max = float(msg.range_max) if msg.range_max > 0 else math.inf
    return RangeScan(stamp, float(msg.angle_min), float(msg.angle_increment), range_max, ranges)


def laser_odometry(track: OdometryTrack | None, stamp: float) -> Transform2D | None:
    """The laser's odometry pose at ``stamp``: the track's, within its span, on the laser's mounting."""
    if track is None or not track or not track.stamps[0] <= stamp <= track.stamps[-1]:
        return None
    odometry = track.at(0, stamp)
    if track.mounting is not None and odometry is not None:
        odometry = odometry.compose(track.mounting)  # the laser's pose, not the base's
    return odometry


UNDECODABLE = (AnyReaderError, SerdeError, TypesysError, struct.error, ValueError, KeyError, IndexError)
"""What rosbags raises for a message it cannot decode."""
BAG_SUFFIXES = (".mcap", ".db3", ".bag")
"""The files a ROS bag is: rosbag2's two storages, and ROS 1's bag."""


def _existing_bag(path: str | Path) -> Path:
    """A bag's path: a file with a bag's suffix, or a rosbag2 directory (with ``metadata.yaml``)."""
    p = Path(path)
    if not p.exists():
        raise BadInput(str(path), "no such file or directory")
    if p.is_dir():
        if not (p / "metadata.yaml").is_file():
            raise BadInput(str(path), "is a directory without metadata.yaml, not a rosbag2 bag")
        return p
    if p.suffix not in BAG_SUFFIXES:
        raise BadInput(str(path), f"is not a ROS bag (a rosbag2 directory, or a {', '.join(BAG_SUFFIXES)} file)")
    return p


def _stamp_of(header_stamp: Any, log_time_ns: int) -> float:
    """A ROS 2 header stamp in seconds, or the log time where the header has none."""
    stamp = float(header_stamp.sec) + float(header_stamp.nanosec) * 1e-9
    return stamp if stamp != 0 else log_time_ns * 1e-9


def planar_pose(position: Any, orientation: Any) -> tuple[float, float, float]:
    """(x, y, yaw) of a ROS 3D pose: the heading of its quaternion about the vertical."""
    qx, qy, qz, qw = (float(orientation.x), float(orientation.y), float(orientation.z), float(orientation.w))
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return float(position.x), float(position.y), yaw
