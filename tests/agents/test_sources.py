"""Scan sources: a simulated robot, a CARMEN log split among robots, a ROS 2 bag; and bad input."""

from __future__ import annotations

import itertools
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from fleetmap.scenarios import robot_stream
from fleetmap.scenarios.stream import ScenarioSource
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.sources import CarmenSource, Ros2BagSource, SourceScan
from mcap_ros2.writer import Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore

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


def test_a_scenario_source_gives_the_robots_scans_and_odometry_without_their_poses():
    source = ScenarioSource("department", "r3")
    scans = list(source)
    assert [s.index for s in scans] == list(range(len(scans))) and len(scans) > 100
    assert [s.stamp for s in scans] == pytest.approx([0.2 * i for i in range(len(scans))])
    assert all(s.scan.odom is None and s.scan.stamp == s.stamp for s in scans)
    index, stamp, scan = scans[3]
    assert (index, stamp, scan) == (3, scans[3].stamp, scans[3].scan)
    # the robot's odometry: it starts at zero, each step a few per cent off the true one, and over
    # the whole loop it drifts by metres (a degree and a half per metre)
    assert source.has_odometry and scans[0].odometry == Transform2D()
    truth = list(robot_stream(source.scenario, "r3"))
    for a, b, ta, tb in zip(scans[10:20], scans[11:21], truth[10:20], truth[11:21], strict=True):
        step, true = a.odometry.inverse().compose(b.odometry), ta.pose.inverse().compose(tb.pose)
        assert step.distance(true)[0] < 0.1 * math.hypot(true.x, true.y) + 0.01
    driven = truth[0].pose.inverse().compose(truth[-1].pose)
    assert scans[-1].odometry.distance(driven)[0] > 1.0


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
        (lambda tmp: Ros2BagSource(tmp), "is a directory without metadata.yaml, not a rosbag2 bag"),
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
    with pytest.raises(BadInput, match=r"no topic '/scan' in the bag \(its topics: /front/scan \(sensor_msgs"):
        Ros2BagSource(bag, "/scan")
    # found by its type where none is named
    assert Ros2BagSource(bag).topic == "/front/scan" and len(list(Ros2BagSource(bag))) == 1


def test_an_empty_bag_and_a_file_that_is_no_bag_are_refused(tmp_path):
    empty = tmp_path / "empty.mcap"
    write_bag(empty, [])
    with pytest.raises(BadInput, match=r"no sensor_msgs/LaserScan topic in the bag \(its topics: none\)"):
        Ros2BagSource(empty)
    text = tmp_path / "notes.mcap"
    text.write_text("not a bag\n")
    with pytest.raises(BadInput, match=r"notes\.mcap: not a readable ROS bag"):
        Ros2BagSource(text)
    csv = tmp_path / "notes.csv"
    csv.write_text("a,b\n")
    with pytest.raises(BadInput, match=r"notes.csv: is not a ROS bag"):
        Ros2BagSource(csv)


def test_a_topic_of_another_type_is_refused(tmp_path):
    bag = tmp_path / "robot.mcap"
    with bag.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef("std_msgs/msg/String", "string data\n")
        writer.write_message("/scan", schema, {"data": "hello"}, log_time=1)
        writer.finish()
    with pytest.raises(BadInput, match="carries std_msgs/msg/String, not sensor_msgs/LaserScan"):
        Ros2BagSource(bag, "/scan")
    with pytest.raises(BadInput, match=r"no sensor_msgs/LaserScan topic in the bag \(its topics: /scan \(std_msgs"):
        Ros2BagSource(bag)


def test_a_carmen_logs_odometry_is_its_odom_lines_interpolated_at_each_scan(tmp_path):
    # ODOM lines every 0.1 s, the robot driving 1 m/s along x and turning 0.2 rad/s; scans between them
    lines = []
    for i in range(12):
        t = 100.0 + 0.1 * i
        lines.append(f"ODOM {0.1 * i:.6f} 0 {0.02 * i:.6f} 0 0 0 {t:.6f} host {t:.6f}\n")
        if 0 < i < 11:
            lines.append(flaser_line([2.0] * 181, t + 0.05, pose=(99.0, 99.0, 3.0)))  # a corrected pose: unused
    log = tmp_path / "robot.log"
    log.write_text("".join(lines))
    scans = list(CarmenSource(log))
    assert CarmenSource(log).has_odometry and len(scans) == 10
    for k, s in enumerate(scans, start=1):
        assert s.odometry.x == pytest.approx(0.1 * k + 0.05) and s.odometry.theta == pytest.approx(0.02 * k + 0.01)


def _odom_lines(speed_sign: float) -> list[str]:
    # heading along x: 1 m/s forward for 0.5 s, then reversing at 1 m/s for 0.5 s; the poses as a
    # logger that adds up the speed without its sign writes them (always forward) when
    # speed_sign < 0, else as it should
    lines, x = [], 0.0
    for i in range(11):
        t = 100.0 + 0.1 * i
        tv = 1.0 if i < 5 else -1.0
        lines.append(f"ODOM {x:.6f} 0 0 {tv:.3f} 0 0 {t:.6f} host {t:.6f}\n")
        if 0 < i < 10:
            lines.append(flaser_line([2.0] * 181, t + 0.05))
        x += 0.1 * (1.0 if tv > 0 or speed_sign < 0 else -1.0)
    return lines


def test_a_carmen_log_whose_odometry_forgets_reversing_is_integrated_again_with_its_speeds_sign(tmp_path, caplog):
    unsigned = tmp_path / "unsigned.log"
    unsigned.write_text("".join(_odom_lines(-1.0)))
    signed = tmp_path / "signed.log"
    signed.write_text("".join(_odom_lines(1.0)))
    with caplog.at_level(logging.WARNING):
        fixed = [s.odometry.x for s in CarmenSource(unsigned)]
        right = [s.odometry.x for s in CarmenSource(signed)]
    # forward to 0.45 m, then back: the same as the log that wrote its reversing as reversing
    assert fixed == pytest.approx(right)
    assert fixed[3] == pytest.approx(0.45) and fixed[-1] == pytest.approx(0.05)
    assert "unsigned.log: the odometry moves forward while its speed says the robot reverses (5 of 5 steps)" in (
        caplog.text
    )
    assert "signed.log:" not in caplog.text.replace("unsigned.log", "")


def test_a_carmen_log_without_usable_times_takes_the_odom_line_before_each_scan(tmp_path):
    lines = []
    for i in range(4):
        lines.append(f"ODOM {float(i):.1f} 0 0 0 0 0 0 host 0\n")
        lines.append(flaser_line([2.0] * 181, 0.0, pose=(99.0, 99.0, 3.0)))
    log = tmp_path / "robot.log"
    log.write_text("".join(lines))
    assert [s.odometry.x for s in CarmenSource(log)] == [0.0, 1.0, 2.0, 3.0]


def _corrected_log(wheel_readings: bool) -> str:
    # a SLAM's corrected log as GMapping writes it: each scan at its corrected pose, the odometry
    # reading after it at that same pose, then the wheels' readings (1 m along x a scan, no turn)
    # from there; the corrected poses turn 0.3 rad a scan, which the wheels never did
    lines = []
    for i in range(5):
        corrected = (float(i), 0.5 * i, 0.3 * i)
        lines.append(flaser_line([2.0] * 181, 0.0, pose=corrected))
        lines.append(f"ODOM {corrected[0]:.6f} {corrected[1]:.6f} {corrected[2]:.6f} 0 0 0 0 host 0\n")
        if wheel_readings:
            for f in (0.5, 1.0):
                x = corrected[0] + f * math.cos(corrected[2])
                y = corrected[1] + f * math.sin(corrected[2])
                lines.append(f"ODOM {x:.6f} {y:.6f} {corrected[2]:.6f} 0 0 0 0 host 0\n")
    return "".join(lines)


def test_a_corrected_logs_odometry_is_the_wheels_increments_not_its_corrected_poses(tmp_path):
    log = tmp_path / "corrected.log"
    log.write_text(_corrected_log(wheel_readings=True))
    scans = list(CarmenSource(log))
    steps = [a.odometry.inverse().compose(b.odometry) for a, b in itertools.pairwise(scans[1:])]
    # scan to scan the wheels went 1 m straight on; read as one track, the corrections' 0.3 rad and
    # half a metre sideways a scan would be in it
    for step in steps:
        assert step.x == pytest.approx(1.0, abs=1e-5) and step.y == pytest.approx(0.0, abs=1e-5)
        assert step.theta == pytest.approx(0.0, abs=1e-5)


def test_a_corrected_log_with_no_wheel_reading_between_two_scans_gives_no_odometry_there(tmp_path):
    log = tmp_path / "corrected.log"
    log.write_text(_corrected_log(wheel_readings=False))
    # the reading before each scan but the first is the last scan's corrected pose: no motion known
    assert [s.odometry is None for s in CarmenSource(log)] == [True, True, True, True, True]


def test_a_carmen_log_without_odom_lines_takes_the_odometry_on_its_laser_lines(carmen_log, tmp_path):
    no_odom = tmp_path / "laser-only.log"
    no_odom.write_text("".join(line for line in carmen_log.read_text().splitlines(True) if not line.startswith("ODOM")))
    scans = list(CarmenSource(no_odom))
    assert [s.odometry.x for s in scans] == [float(i) for i in range(10)]
    assert all(s.scan.odom is None and s.scan.odometry is None for s in scans), "travels beside the scan only"


SEPARATOR = "=" * 80 + "\n"
ROS_TYPES = {
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/Twist": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
}


def msgdef(body: str, *uses: str) -> str:
    """A message definition as ros2 bag stores it: the body, then every type it uses."""
    return body + "".join(f"{SEPARATOR}MSG: {name}\n{ROS_TYPES[name]}" for name in uses)


ODOMETRY_MSGDEF = msgdef(
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
    "geometry_msgs/TwistWithCovariance twist\n",
    "std_msgs/Header",
    "builtin_interfaces/Time",
    "geometry_msgs/PoseWithCovariance",
    "geometry_msgs/Pose",
    "geometry_msgs/Point",
    "geometry_msgs/Quaternion",
    "geometry_msgs/TwistWithCovariance",
    "geometry_msgs/Twist",
    "geometry_msgs/Vector3",
)
"""nav_msgs/msg/Odometry as ros2 bag stores its definition."""

TF_MSGDEF = msgdef(
    "geometry_msgs/TransformStamped[] transforms\n",
    "geometry_msgs/TransformStamped",
    "std_msgs/Header",
    "builtin_interfaces/Time",
    "geometry_msgs/Transform",
    "geometry_msgs/Vector3",
    "geometry_msgs/Quaternion",
)
"""tf2_msgs/msg/TFMessage as ros2 bag stores its definition."""


def _stamp(t: float) -> dict[str, int]:
    return {"sec": int(t), "nanosec": round((t - int(t)) * 1e9)}


def _quaternion(yaw: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}


def write_robot_bag(path: Path, odometry: str) -> list[float]:
    """Five scans at 10 Hz and the base's odometry at 50 Hz (1 m/s along x, turning 0.5 rad/s),
    as nav_msgs/Odometry on /odom or as tf odom -> base_link; the laser 0.2 m ahead of the base
    (/tf_static). The scans' stamps."""
    with path.open("wb") as stream:
        writer = Writer(stream)
        scan_schema = writer.register_msgdef("sensor_msgs/msg/LaserScan", LASER_SCAN_MSGDEF)
        odom_schema = writer.register_msgdef("nav_msgs/msg/Odometry", ODOMETRY_MSGDEF)
        tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_MSGDEF)
        mount = {
            "header": {"stamp": _stamp(0.0), "frame_id": "base_link"},
            "child_frame_id": "laser",
            "transform": {"translation": {"x": 0.2, "y": 0.0, "z": 0.1}, "rotation": _quaternion(0.0)},
        }
        writer.write_message("/tf_static", tf_schema, {"transforms": [mount]}, log_time=1)
        for k in range(60):
            t = 50.0 + 0.02 * k
            pose = {"position": {"x": t - 50.0, "y": 0.0, "z": 0.0}, "orientation": _quaternion(0.5 * (t - 50.0))}
            if odometry == "odom":
                message = {
                    "header": {"stamp": _stamp(t), "frame_id": "odom"},
                    "child_frame_id": "base_link",
                    "pose": {"pose": pose, "covariance": [0.0] * 36},
                    "twist": {
                        "twist": {"linear": {"x": 1.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.5}},
                        "covariance": [0.0] * 36,
                    },
                }
                writer.write_message("/odom", odom_schema, message, log_time=round(t * 1e9))
            else:
                tf = {
                    "header": {"stamp": _stamp(t), "frame_id": "odom"},
                    "child_frame_id": "base_link",
                    "transform": {"translation": pose["position"], "rotation": pose["orientation"]},
                }
                writer.write_message("/tf", tf_schema, {"transforms": [tf]}, log_time=round(t * 1e9))
        stamps = [50.1 + 0.1 * k for k in range(5)]
        for t in stamps:
            scan = {
                "header": {"stamp": _stamp(t), "frame_id": "laser"},
                "angle_min": -math.pi / 2,
                "angle_max": math.pi / 2,
                "angle_increment": math.pi / 180,
                "time_increment": 0.0,
                "scan_time": 0.1,
                "range_min": 0.1,
                "range_max": 8.0,
                "ranges": [2.0] * 181,
                "intensities": [],
            }
            writer.write_message("/scan", scan_schema, scan, log_time=round(t * 1e9))
        writer.finish()
    return stamps


@pytest.mark.parametrize("odometry", ["odom", "tf"])
def test_a_ros2_bags_odometry_is_read_at_each_scan_on_the_laser(tmp_path, odometry):
    bag = tmp_path / "robot.mcap"
    stamps = write_robot_bag(bag, odometry)
    source = Ros2BagSource(bag)
    assert source.has_odometry
    scans = list(source)
    assert [s.stamp for s in scans] == pytest.approx(stamps)
    for s in scans:
        base = Transform2D(s.stamp - 50.0, 0.0, 0.5 * (s.stamp - 50.0))
        laser = base.compose(Transform2D(0.2, 0.0, 0.0))  # the mounting, from /tf_static
        assert s.odometry.distance(laser)[0] < 1e-3 and s.odometry.distance(laser)[1] < 1e-3


def test_a_ros2_bag_without_odometry_says_so(tmp_path):
    bag = tmp_path / "robot.mcap"
    write_bag(bag, [(5.0, [1.0, 2.0, 3.0])])
    source = Ros2BagSource(bag)
    assert not source.has_odometry and next(iter(source)).odometry is None
    with pytest.raises(BadInput, match="is not nav_msgs/Odometry"):
        Ros2BagSource(bag, odometry_topic="/odom")


def write_rosbag2(path: Path, storage: StoragePlugin, laser_topics: tuple[str, ...] = ("/scan",)) -> None:
    """The scans and odometry of :func:`write_robot_bag` (nav_msgs/Odometry on /odom) as a rosbag2
    directory written by ``rosbags`` in ``storage`` (what ``ros2 bag record`` leaves)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    with Rosbag2Writer(path, version=9, storage_plugin=storage) as writer:
        odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store)
        lasers = [writer.add_connection(t, "sensor_msgs/msg/LaserScan", typestore=store) for t in laser_topics]

        def header(t: float, frame: str) -> object:
            sec = int(t)
            return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](sec, round((t - sec) * 1e9)), frame)

        vector = T["geometry_msgs/msg/Vector3"]
        for k in range(60):
            t = 50.0 + 0.02 * k
            q = _quaternion(0.5 * (t - 50.0))
            pose = T["geometry_msgs/msg/Pose"](
                T["geometry_msgs/msg/Point"](t - 50.0, 0.0, 0.0), T["geometry_msgs/msg/Quaternion"](**q)
            )
            twist = T["geometry_msgs/msg/Twist"](vector(1.0, 0.0, 0.0), vector(0.0, 0.0, 0.5))
            message = T["nav_msgs/msg/Odometry"](
                header(t, "odom"),
                "base_link",
                T["geometry_msgs/msg/PoseWithCovariance"](pose, np.zeros(36)),
                T["geometry_msgs/msg/TwistWithCovariance"](twist, np.zeros(36)),
            )
            writer.write(odom, round(t * 1e9), store.serialize_cdr(message, "nav_msgs/msg/Odometry"))
        for t in [50.1 + 0.1 * k for k in range(5)]:
            ranges = np.array([2.0 + 0.01 * i for i in range(181)], dtype=np.float32)
            scan = T["sensor_msgs/msg/LaserScan"](
                header(t, "laser"),
                -math.pi / 2,
                math.pi / 2,
                math.pi / 180,
                0.0,
                0.1,
                0.1,
                8.0,
                ranges,
                np.zeros(0, dtype=np.float32),
            )
            for laser in lasers:
                writer.write(laser, round(t * 1e9), store.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "db3"])
def test_a_rosbag2_directory_and_its_own_file_give_the_same_scans_and_odometry(tmp_path, storage):
    bag = tmp_path / "robot"
    write_rosbag2(bag, storage)
    (file,) = [f for f in bag.iterdir() if f.suffix in (".mcap", ".db3")]
    from_dir, from_file = list(Ros2BagSource(bag)), list(Ros2BagSource(file))
    assert len(from_dir) == len(from_file) == 5
    for a, b in zip(from_dir, from_file, strict=True):
        assert a.stamp == b.stamp and a.index == b.index
        np.testing.assert_array_equal(a.scan.ranges, b.scan.ranges)
        # nav_msgs/Odometry at the scan's stamp (no /tf_static here: the base is the laser)
        base = Transform2D(a.stamp - 50.0, 0.0, 0.5 * (a.stamp - 50.0))
        assert a.odometry.distance(base)[0] < 1e-3 and a.odometry.distance(base)[1] < 1e-3
        assert b.odometry.distance(a.odometry)[0] < 1e-9
    assert from_dir[2].scan.ranges[10] == pytest.approx(2.1)


def test_a_bag_with_several_laser_topics_takes_scan_or_asks_for_one(tmp_path):
    both = tmp_path / "both"
    write_rosbag2(both, StoragePlugin.MCAP, ("/scan", "/rear/scan"))
    assert Ros2BagSource(both).topic == "/scan"
    assert Ros2BagSource(both, "/rear/scan").topic == "/rear/scan"
    two = tmp_path / "two"
    write_rosbag2(two, StoragePlugin.MCAP, ("/front/scan", "/rear/scan"))
    with pytest.raises(BadInput, match=r"has 2 LaserScan topics \(/front/scan, /rear/scan\): name one \(--topic\)"):
        Ros2BagSource(two)


def write_scans_rosbag2(path: Path, storage: StoragePlugin, scans: list[SourceScan], epoch: float = 1.7e9) -> None:
    """A robot's scans as ``ros2 bag record`` would leave them (written by ``rosbags``): each as
    sensor_msgs/LaserScan on /scan and its odometry as nav_msgs/Odometry on /odom, stamped
    ``epoch`` seconds on."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    with Rosbag2Writer(path, version=9, storage_plugin=storage) as writer:
        odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store)
        laser = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        vector = T["geometry_msgs/msg/Vector3"]
        for s in scans:
            t = epoch + s.stamp
            sec = int(t)
            stamp = T["builtin_interfaces/msg/Time"](sec, round((t - sec) * 1e9))
            pose = T["geometry_msgs/msg/Pose"](
                T["geometry_msgs/msg/Point"](s.odometry.x, s.odometry.y, 0.0),
                T["geometry_msgs/msg/Quaternion"](**_quaternion(s.odometry.theta)),
            )
            twist = T["geometry_msgs/msg/Twist"](vector(0.0, 0.0, 0.0), vector(0.0, 0.0, 0.0))
            message = T["nav_msgs/msg/Odometry"](
                T["std_msgs/msg/Header"](stamp, "odom"),
                "base_link",
                T["geometry_msgs/msg/PoseWithCovariance"](pose, np.zeros(36)),
                T["geometry_msgs/msg/TwistWithCovariance"](twist, np.zeros(36)),
            )
            writer.write(odom, round(t * 1e9), store.serialize_cdr(message, "nav_msgs/msg/Odometry"))
            n = len(s.scan.ranges)
            ranges = np.where(np.isfinite(s.scan.ranges), s.scan.ranges, np.inf).astype(np.float32)
            scan = T["sensor_msgs/msg/LaserScan"](
                T["std_msgs/msg/Header"](stamp, "base_link"),
                s.scan.angle_min,
                s.scan.angle_min + (n - 1) * s.scan.angle_increment,
                s.scan.angle_increment,
                0.0,
                0.2,
                0.05,
                s.scan.range_max,
                ranges,
                np.zeros(0, dtype=np.float32),
            )
            writer.write(laser, round(t * 1e9), store.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))


def test_a_garbled_or_impossible_scan_in_a_bag_is_skipped_with_a_warning_naming_it(tmp_path, caplog):
    # a message cut short (a recorder that died while writing it) and one whose beams have no angle
    # step: each skipped and said once; every other scan read
    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    bag = tmp_path / "robot"

    def scan(t: float, increment: float) -> bytes:
        header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](int(t), 0), "laser")
        ranges = np.full(181, 2.0, dtype=np.float32)
        msg = T["sensor_msgs/msg/LaserScan"](
            header, -math.pi / 2, math.pi / 2, increment, 0.0, 0.1, 0.1, 8.0, ranges, np.zeros(0, np.float32)
        )
        return bytes(store.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))

    with Rosbag2Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        laser = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for t in range(1, 6):
            data = scan(float(t), math.pi / 180)
            if t == 2:
                data = data[:40]
            if t == 4:
                data = scan(float(t), 0.0)
            writer.write(laser, t * 10**9, data)
    with caplog.at_level(logging.WARNING):
        scans = list(Ros2BagSource(bag))
    assert [s.stamp for s in scans] == [1.0, 3.0, 5.0]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2, warnings
    assert "message 2 on /scan" in warnings[0] and "cannot be decoded" in warnings[0]
    assert "bad beam angles" in warnings[1] and "skipped" in warnings[1]


def test_a_log_whose_clock_is_in_milliseconds_is_refused_naming_the_scan(tmp_path):
    log = tmp_path / "ms.log"
    log.write_text(flaser_line([2.0] * 181, 1.7e12))
    with pytest.raises(BadInput, match=r"scan 0: stamp 1.7e\+12 s is after the year 2262"):
        list(CarmenSource(log))
