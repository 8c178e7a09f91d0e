"""A scenario's simulated robot as a ROS 2 bag: what a real robot on rmw_zenoh would publish.

:func:`write_robot_bag` writes one robot's simulated scans as ``sensor_msgs/msg/LaserScan`` on
``/scan`` (frame ``laser``), its odometry as ``nav_msgs/msg/Odometry`` on ``/odom`` (``odom ->
base_link``, at each scan's stamp and written before it, as a driver's faster odometry would be
there first) and the laser's mounting (at the base) on ``/tf_static``, with log times at the scans'
own stamps. ``fleetmap play BAG --ros2 --namespace <robot>`` then puts the robot on rmw_zenoh
topics for ``fleetmap agent --ros2``: the live session's ROS 2 path (``Session(ros2=True)``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from fleetmap.scenarios import Scenario
from fleetmap.scenarios.stream import robot_stream
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io import ros2_wire as wire

LASER_FRAME, BASE_FRAME, ODOM_FRAME = "laser", "base_link", "odom"
SCAN_TIME = 0.2
"""The simulated laser's period (s): a scenario's 5 Hz."""


def _stamp(t: float) -> Any:
    sec = math.floor(t)
    return wire.typestore().types["builtin_interfaces/msg/Time"](sec, min(round((t - sec) * 1e9), 999_999_999))


def _header(t: float, frame: str) -> Any:
    return wire.typestore().types["std_msgs/msg/Header"](_stamp(t), frame)


def _pose(pose: Transform2D) -> Any:
    T = wire.typestore().types
    q = T["geometry_msgs/msg/Quaternion"](0.0, 0.0, math.sin(pose.theta / 2), math.cos(pose.theta / 2))
    return T["geometry_msgs/msg/Pose"](T["geometry_msgs/msg/Point"](pose.x, pose.y, 0.0), q)


def mounting_message() -> Any:
    """/tf_static: the laser at the base (the scenario's odometry is the laser's)."""
    T = wire.typestore().types
    identity = _pose(Transform2D(0.0, 0.0, 0.0))
    translation = T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
    transform = T["geometry_msgs/msg/Transform"](translation, identity.orientation)
    stamped = T["geometry_msgs/msg/TransformStamped"](_header(0.0, BASE_FRAME), LASER_FRAME, transform)
    return T[wire.TF_MESSAGE]([stamped])


def odometry_message(pose: Transform2D, t: float) -> Any:
    T = wire.typestore().types
    covariance = np.zeros(36)
    zero = T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
    twist = T["geometry_msgs/msg/TwistWithCovariance"](T["geometry_msgs/msg/Twist"](zero, zero), covariance)
    with_covariance = T["geometry_msgs/msg/PoseWithCovariance"](_pose(pose), covariance)
    return T[wire.ODOMETRY](_header(t, ODOM_FRAME), BASE_FRAME, with_covariance, twist)


def scan_message(angle_min: float, angle_increment: float, range_max: float, ranges: np.ndarray, t: float) -> Any:
    """A LaserScan of a simulated scan: NaN (no return) stays NaN, as REP 117 allows."""
    n = len(ranges)
    return wire.typestore().types[wire.LASER_SCAN](
        _header(t, LASER_FRAME),
        float(angle_min),
        float(angle_min + angle_increment * (n - 1)),
        float(angle_increment),
        0.0,
        SCAN_TIME,
        0.0,
        float(range_max),
        np.asarray(ranges, dtype=np.float32),
        np.zeros(0, dtype=np.float32),
    )


def write_robot_bag(scenario: Scenario, robot: str, path: Path) -> int:
    """Write robot ``robot``'s simulated scans and odometry as a rosbag2 (MCAP) at ``path`` (a new
    folder); the number of scans."""
    store = wire.typestore()
    scans = 0
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        tf_static = writer.add_connection("/tf_static", wire.TF_MESSAGE, typestore=store)
        odom = writer.add_connection("/odom", wire.ODOMETRY, typestore=store)
        scan = writer.add_connection("/scan", wire.LASER_SCAN, typestore=store)
        writer.write(tf_static, 0, wire.encode(mounting_message(), wire.TF_MESSAGE))
        for simulated in robot_stream(scenario, robot):
            t = simulated.stamp
            log_time = round(t * 1e9)
            if simulated.odometry is not None:
                writer.write(odom, log_time, wire.encode(odometry_message(simulated.odometry, t), wire.ODOMETRY))
            s = simulated.scan
            message = scan_message(s.angle_min, s.angle_increment, s.range_max, s.ranges, t)
            writer.write(scan, log_time, wire.encode(message, wire.LASER_SCAN))
            scans += 1
    return scans
