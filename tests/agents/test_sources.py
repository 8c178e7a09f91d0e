"""Scan sources: a simulated robot, a CARMEN log split among robots, a ROS 2 bag; and bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from fleetmap.agents.sources import CarmenSource, Ros2BagSource, ScenarioSource
from fleetmap.shared.errors import BadInput
from mcap_ros2.writer import Writer

LASER_SCAN_MSGDEF = """\
std_msgs/Header header
float32 angle_min
float32 angle_max
float32 angle_increment
float32 time_increment
float32 scan_time
float32 range_min
float32 range_max
float32[] ranges
float32[] intensities
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
"""sensor_msgs/msg/LaserScan as ros2 bag stores its definition."""


def flaser_line(ranges: list[float], stamp: float, pose: tuple[float, float, float] = (1.0, 2.0, 0.5)) -> str:
    x, y, theta = pose
    values = " ".join(f"{r:.3f}" for r in ranges)
    return f"FLASER {len(ranges)} {values} {x} {y} {theta} {x} {y} {theta} {stamp:.6f} host {stamp:.6f}\n"


@pytest.fixture
def carmen_log(tmp_path: Path) -> Path:
    """Ten FLASER scans at stamps 100.0, 100.1, ... with odometry lines between them; scan i
    reads 1 + i/10 m on every beam but the last, which reads the no-return 81.91."""
    lines = []
    for i in range(10):
        lines.append(f"ODOM {i} 0 0 0 0 0 {100 + i / 10:.6f} host {100 + i / 10:.6f}\n")
        lines.append(flaser_line([1.0 + i / 10] * 180 + [81.91], 100.0 + i / 10, pose=(i, 0.0, 0.0)))
    path = tmp_path / "robot.log"
    path.write_text("# a CARMEN log\n" + "".join(lines))
    return path


def test_a_scenario_source_gives_the_robots_scans_without_their_poses():
    scans = list(ScenarioSource("department", "r3"))
    assert [s.index for s in scans] == list(range(len(scans))) and len(scans) > 30
    assert [s.stamp for s in scans] == [0.5 * i for i in range(len(scans))]
    assert all(s.scan.odom is None and s.scan.stamp == s.stamp for s in scans)
    index, stamp, scan = scans[3]
    assert (index, stamp, scan) == (3, 1.5, scans[3].scan)


def test_a_carmen_log_split_between_two_robots_keeps_the_logs_indices_and_stamps(carmen_log):
    first = list(CarmenSource(carmen_log, stop=6))
    second = list(CarmenSource(carmen_log, start=4))
    assert [s.index for s in first] == [0, 1, 2, 3, 4, 5]
    assert [s.index for s in second] == [4, 5, 6, 7, 8, 9]
    assert [s.stamp for s in second] == pytest.approx([100.4, 100.5, 100.6, 100.7, 100.8, 100.9])
    # the overlap is the same scans for both robots
    for a, b in zip(first[4:], second[:2], strict=True):
        np.testing.assert_array_equal(a.scan.ranges, b.scan.ranges)
    assert second[0].scan.ranges[0] == pytest.approx(1.4)
    assert all(s.scan.odom is None for s in first + second), "the log's poses never reach the agent"


def test_a_carmen_source_takes_every_kth_scan_and_the_no_return_reading(carmen_log):
    scans = list(CarmenSource(carmen_log, start=1, stop=8, step=3, range_max=81.91))
    assert [(s.index, round(s.stamp, 6)) for s in scans] == [(1, 100.1), (4, 100.4), (7, 100.7)]
    assert all(s.scan.range_max == 81.91 for s in scans)


def write_bag(path: Path, scans: list[tuple[float, list[float]]], topic: str = "/scan") -> None:
    with path.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef("sensor_msgs/msg/LaserScan", LASER_SCAN_MSGDEF)
        for k, (stamp, ranges) in enumerate(scans):
            sec = int(stamp)
            message = {
                "header": {"stamp": {"sec": sec, "nanosec": round((stamp - sec) * 1e9)}, "frame_id": "laser"},
                "angle_min": -math.pi / 2,
                "angle_max": math.pi / 2,
                "angle_increment": math.pi / (len(ranges) - 1),
                "time_increment": 0.0,
                "scan_time": 0.1,
                "range_min": 0.1,
                "range_max": 8.0,
                "ranges": ranges,
                "intensities": [],
            }
            writer.write_message(topic, schema, message, log_time=(1_000 + k) * 10**9)
        writer.finish()


def test_a_ros2_bag_gives_back_the_simulated_scans_written_to_it(tmp_path):
    simulated = list(ScenarioSource("department", "r1"))[:5]
    bag = tmp_path / "robot.mcap"
    stamps = [1_700_000_000.25 + 0.5 * k for k in range(5)]
    write_bag(bag, [(stamp, [float(r) for r in s.scan.ranges]) for stamp, s in zip(stamps, simulated, strict=True)])
    scans = list(Ros2BagSource(bag))
    assert [s.index for s in scans] == [0, 1, 2, 3, 4]
    assert [s.stamp for s in scans] == pytest.approx(stamps, abs=1e-6)
    for read, written in zip(scans, simulated, strict=True):
        assert read.scan.angle_min == pytest.approx(written.scan.angle_min, abs=1e-6)
        assert read.scan.angle_increment == pytest.approx(written.scan.angle_increment, rel=1e-6)
        assert read.scan.range_max == 8.0
        np.testing.assert_allclose(read.scan.ranges, written.scan.ranges, rtol=1e-6)


def test_ros2_readings_below_range_min_are_no_return(tmp_path):
    bag = tmp_path / "robot.mcap"
    write_bag(bag, [(5.0, [0.05, 1.0, 2.0])])
    [scan] = list(Ros2BagSource(bag))
    assert np.isnan(scan.scan.ranges[0]) and list(scan.scan.ranges[1:]) == [1.0, 2.0]


@pytest.mark.parametrize(
    ("make", "says"),
    [
        (lambda tmp: ScenarioSource("department", "r9"), "not in scenario 'department'"),
        (lambda tmp: ScenarioSource("no-such-scenario", "r1"), "unknown scenario"),
        (lambda tmp: CarmenSource(tmp / "missing.log"), "no such file"),
        (lambda tmp: CarmenSource(tmp, 0), "is not a file"),
        (lambda tmp: Ros2BagSource(tmp / "missing.mcap"), "no such file"),
    ],
)
def test_bad_sources_are_refused_when_made(tmp_path, make, says):
    with pytest.raises(BadInput, match=says):
        make(tmp_path)


def test_a_carmen_slice_past_the_end_says_how_long_the_log_is(carmen_log):
    with pytest.raises(BadInput, match=r"no laser scan from index 20 on \(the log has 10\)"):
        list(CarmenSource(carmen_log, start=20))
    with pytest.raises(BadInput, match="--stop"):
        CarmenSource(carmen_log, start=5, stop=5)


def test_a_bag_without_the_topic_names_the_topics_it_has(tmp_path):
    bag = tmp_path / "robot.mcap"
    write_bag(bag, [(1.0, [1.0, 2.0])], topic="/front/scan")
    with pytest.raises(BadInput, match=r"no topic '/scan' in the bag \(its topics: /front/scan\)"):
        Ros2BagSource(bag)
    assert len(list(Ros2BagSource(bag, "/front/scan"))) == 1


def test_an_empty_bag_and_a_file_that_is_no_bag_are_refused(tmp_path):
    empty = tmp_path / "empty.mcap"
    write_bag(empty, [])
    with pytest.raises(BadInput, match="no topic '/scan'"):
        Ros2BagSource(empty)
    text = tmp_path / "notes.mcap"
    text.write_text("not a bag\n")
    with pytest.raises(BadInput, match="not an MCAP file"):
        Ros2BagSource(text)


def test_a_topic_of_another_type_is_refused(tmp_path):
    bag = tmp_path / "robot.mcap"
    with bag.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef("std_msgs/msg/String", "string data\n")
        writer.write_message("/scan", schema, {"data": "hello"}, log_time=1)
        writer.finish()
    with pytest.raises(BadInput, match="carries std_msgs/msg/String, not sensor_msgs/LaserScan"):
        Ros2BagSource(bag)
