"""Where an agent's scans come from: a simulated robot, a CARMEN log, or a ROS 2 bag in MCAP.

Every source yields :class:`SourceScan` ``(index, stamp, scan)`` in order; ``stamp`` is in
seconds and paces a live agent. No pose ever leaves a source: the scenario's true poses and the
poses written in a CARMEN log stay here, so the algorithms see the ranges alone.

Problems with the input raise :class:`~fleetmap.shared.errors.BadInput` naming it: a missing or
unreadable file, a bag without the topic, a robot the scenario does not have, or a source that
yields no scan at all. Files are checked when the source is made, before an agent goes on the bus.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from fleetmap.scenarios.fleet import Scenario
from fleetmap.scenarios.loader import load_scenario
from fleetmap.scenarios.stream import robot_stream
from fleetmap.shared.errors import BadInput
from fleetmap.shared.scans import RangeScan, read_carmen
from mcap.exceptions import InvalidMagic, McapError
from mcap.reader import McapReader, make_reader
from mcap_ros2.decoder import DecoderFactory

LASER_SCAN_SCHEMAS = ("sensor_msgs/msg/LaserScan", "sensor_msgs/LaserScan")
"""How a ROS 2 bag names the sensor_msgs/LaserScan schema (the first is what ros2 bag writes)."""


@dataclass(frozen=True)
class SourceScan:
    """One scan of a source; unpacks as ``index, stamp, scan``."""

    index: int
    """The scan's number: in the robot's plan (scenario), among the log's laser lines (CARMEN),
    among the topic's messages (ROS 2 bag)."""
    stamp: float
    """Seconds: scenario time, or the time the log or bag gives."""
    scan: RangeScan

    def __iter__(self) -> Iterator[Any]:
        return iter((self.index, self.stamp, self.scan))


class ScanSource(Protocol):
    """Scans in order; ``name`` says where they come from (for logs and summaries)."""

    name: str

    def __iter__(self) -> Iterator[SourceScan]: ...


def _checked(source: str, index: int, stamp: float, scan: RangeScan) -> SourceScan:
    """The scan as an agent gets it: a valid stamp and beam geometry, and no pose."""
    where = f"{source}: scan {index}"
    if not math.isfinite(stamp) or stamp < 0:
        raise BadInput(where, f"stamp {stamp} is not a finite non-negative number of seconds")
    if not (math.isfinite(scan.angle_min) and math.isfinite(scan.angle_increment)) or scan.angle_increment == 0:
        raise BadInput(where, f"bad beam angles (angle_min {scan.angle_min}, increment {scan.angle_increment})")
    if not scan.range_max > 0:
        raise BadInput(where, f"range_max {scan.range_max} is not positive")
    return SourceScan(index, stamp, replace(scan, stamp=stamp, odom=None))


def _existing_file(path: str | Path, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise BadInput(str(path), "no such file")
    if not p.is_file():
        raise BadInput(str(path), f"is not a file ({what} expected)")
    return p


class ScenarioSource:
    """The scans of one robot of a scenario (bundled name, file, or a loaded Scenario)."""

    def __init__(self, scenario: str | Path | Scenario, robot: str) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        if robot not in self.scenario.robot_ids:
            raise BadInput(
                f"robot {robot!r}",
                f"not in scenario {self.scenario.name!r} (its robots: {', '.join(self.scenario.robot_ids)})",
            )
        self.robot = robot
        self.name = f"scenario {self.scenario.name}, robot {robot}"

    def __iter__(self) -> Iterator[SourceScan]:
        for simulated in robot_stream(self.scenario, self.robot):
            # simulated.pose is the ground truth: it stays here
            yield _checked(self.name, simulated.index, simulated.stamp, simulated.scan)


class CarmenSource:
    """Laser scans ``[start:stop:step]`` of a CARMEN log (FLASER, RLASER, ROBOTLASER1; plain or .gz).

    Several agents given parts of one log (``r1``: ``--stop 600``, ``r2``: ``--start 500``) map a
    real building as a fleet whose maps overlap. ``index`` is the scan's position among the log's
    laser lines, so two robots sharing a log name the same scan alike. The log's poses are dropped.
    ``range_max`` is the no-return reading of FLASER/RLASER lines (:func:`~fleetmap.shared.scans.read_carmen`).
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
            raise BadInput("--range-max", f"must be positive, got {range_max}")
        self.start, self.stop, self.step, self.range_max = start, stop, step, range_max
        self.name = f"{path} [{start}:{'' if stop is None else stop}:{step}]"

    def __iter__(self) -> Iterator[SourceScan]:
        total = 0
        yielded = 0
        for index, scan in enumerate(read_carmen(self.path, self.range_max)):
            total = index + 1
            if self.stop is not None and index >= self.stop:
                break
            if index >= self.start and (index - self.start) % self.step == 0:
                yielded += 1
                yield _checked(str(self.path), index, scan.stamp, scan)
        if not yielded:
            raise BadInput(str(self.path), f"no laser scan from index {self.start} on (the log has {total})")


class Ros2BagSource:
    """sensor_msgs/LaserScan messages of one topic of a ROS 2 bag in MCAP, in log time order.

    Read with mcap-ros2-support: no ROS install. The stamp is the message header's, or the log
    time where the header has none; readings below ``range_min`` are no return, as in ROS.
    """

    def __init__(self, path: str | Path, topic: str = "/scan") -> None:
        self.path = _existing_file(path, "an MCAP file")
        self.topic = topic
        self.name = f"{path} {topic}"
        with self.path.open("rb") as stream:
            summary = self._guard(lambda: make_reader(stream).get_summary())
        if summary is None:
            return  # a bag without a summary section: the topic shows when reading
        schemas = {c.topic: summary.schemas.get(c.schema_id) for c in summary.channels.values()}
        if topic not in schemas:
            listed = ", ".join(sorted(schemas)) or "none"
            raise BadInput(str(path), f"no topic {topic!r} in the bag (its topics: {listed})")
        schema = schemas[topic]
        if schema is None or schema.name not in LASER_SCAN_SCHEMAS:
            kind = "no schema" if schema is None else schema.name
            raise BadInput(str(path), f"topic {topic!r} carries {kind}, not sensor_msgs/LaserScan")

    def _guard(self, read: Any) -> Any:
        try:
            return read()
        except InvalidMagic:
            raise BadInput(str(self.path), "not an MCAP file") from None
        except (McapError, struct.error, ValueError, EOFError, NotImplementedError) as exc:
            raise BadInput(str(self.path), f"not a readable ROS 2 MCAP bag: {exc}"[:300]) from None

    def __iter__(self) -> Iterator[SourceScan]:
        yielded = 0
        with self.path.open("rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for index, (message, ros_msg) in enumerate(self._messages(reader)):
                yielded += 1
                yield self._scan(index, message.log_time, ros_msg)
        if not yielded:
            raise BadInput(str(self.path), f"no sensor_msgs/LaserScan message on topic {self.topic!r}")

    def _messages(self, reader: McapReader) -> Iterator[tuple[Any, Any]]:
        decoded = reader.iter_decoded_messages(topics=[self.topic], log_time_order=True)
        while True:
            item = self._guard(lambda: next(decoded, None))
            if item is None:
                return
            schema, _channel, message, ros_msg = item
            if schema is None or schema.name not in LASER_SCAN_SCHEMAS:
                raise BadInput(str(self.path), f"topic {self.topic!r} does not carry sensor_msgs/LaserScan")
            yield message, ros_msg

    def _scan(self, index: int, log_time_ns: int, msg: Any) -> SourceScan:
        header = msg.header.stamp
        stamp = header.sec + header.nanosec * 1e-9
        if stamp == 0:
            stamp = log_time_ns * 1e-9
        ranges = np.asarray(msg.ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            ranges[ranges < msg.range_min] = np.nan
        range_max = float(msg.range_max) if msg.range_max > 0 else math.inf
        scan = RangeScan(stamp, float(msg.angle_min), float(msg.angle_increment), range_max, ranges)
        return _checked(self.name, index, stamp, scan)
