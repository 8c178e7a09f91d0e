"""The merger's ROS 2 outputs: the occupancy grid's layout as nav_msgs/OccupancyGrid has it, and the
map -> odom transform of a robot pose (the wire itself is tested live in tests/live/test_ros2.py)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from fleetmap.merger.scangraph import SCAN_KEY_ROTATION, SCAN_KEY_SPACING
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.memory_bus import InMemoryBus
from fleetmap.shared.io.messages import LaserRanges, RobotPose, Scan
from fleetmap.shared.io.occupancy import OccupancyGrid
from fleetmap.shared.io.ros2_node import Ros2Node
from fleetmap.shared.io.zenoh_config import ZenohOptions

from fleetmap.ros2_outputs import GridScans, Ros2Outputs, occupancy_message
from tests.bus_helpers import open_zenoh


def test_the_grid_is_row_major_from_its_south_west_cell_at_the_origin():
    cells = np.array([[0, 100, -1], [-1, -1, 0]], dtype=np.int8)  # row 0 the southernmost
    grid = OccupancyGrid(cells, (-1.5, 2.25), 0.05)
    message = wire.decode(wire.encode(occupancy_message(grid, 1234.5), wire.OCCUPANCY_GRID), wire.OCCUPANCY_GRID)
    assert message.header.frame_id == "map" and (message.header.stamp.sec, message.header.stamp.nanosec) == (
        1234,
        500_000_000,
    )
    assert (message.info.width, message.info.height) == (3, 2)
    assert message.info.resolution == pytest.approx(0.05)
    assert (message.info.origin.position.x, message.info.origin.position.y) == (-1.5, 2.25)
    # REP / nav_msgs: data[row * width + col], row 0 at the origin's y
    assert message.data.tolist() == [0, 100, -1, -1, -1, 0]


def test_a_placed_scan_gives_the_robots_pose_and_map_to_odom_from_its_odometry():
    keys = FleetKeys("t")
    got: dict[str, list[object]] = {"tf": [], "pose": []}
    done = threading.Event()
    with (
        open_zenoh(ZenohOptions(listen=("tcp/127.0.0.1:0",))) as zbus,
        Ros2Node(zbus.session, "fleetmap_merger") as node,
    ):
        topics = (("tf", "/tf", wire.TF_MESSAGE), ("pose", "/r1/fleetmap/pose", wire.POSE_WITH_COVARIANCE_STAMPED))
        for what, topic, typename in topics:
            zbus.session.declare_subscriber(
                wire.data_key(0, topic, typename),
                lambda s, what=what, typename=typename: (
                    got[what].append(wire.decode(s.payload.to_bytes(), typename)),
                    done.set() if got["tf"] and got["pose"] else None,
                ),
            )
        outputs = Ros2Outputs(InMemoryBus(), keys, node)
        odometry = Transform2D(3.0, -1.0, 0.4)  # the laser's pose in the robot's odometry frame
        in_map = Transform2D(10.0, 5.0, 2.0)  # the laser's pose in the map, by the merger
        scan = Scan("r1", 0, 7, 100.25, np.zeros((0, 4)), odometry=odometry)
        outputs.on_message(keys.scan("r1"), scan.to_msgpack())
        outputs.on_message(keys.pose("r1"), RobotPose("r1", 0, 100.25, in_map, 0).to_msgpack())
        outputs.on_message(keys.pose("r1"), RobotPose("r1", 0, 100.5, in_map, 1).to_msgpack())  # not /map's frame
        assert done.wait(5.0)
        outputs.close()
    (tf,) = got["tf"]
    (pose,) = got["pose"]
    (t,) = tf.transforms  # type: ignore[attr-defined]
    assert (t.header.frame_id, t.child_frame_id) == ("map", "r1/odom")
    map_to_odom = Transform2D(
        t.transform.translation.x,
        t.transform.translation.y,
        2 * math.atan2(t.transform.rotation.z, t.transform.rotation.w),
    )
    laser = map_to_odom.compose(odometry)
    assert laser.distance(in_map)[0] < 1e-9 and laser.distance(in_map)[1] < 1e-9
    p = pose.pose.pose  # type: ignore[attr-defined]
    assert (p.position.x, p.position.y) == (10.0, 5.0) and 2 * math.atan2(
        p.orientation.z, p.orientation.w
    ) == pytest.approx(2.0)
    assert pose.header.frame_id == "map"  # type: ignore[attr-defined]


def _scan(index: int, pose: Transform2D | None, submap: int | None = 0) -> Scan:
    ranges = LaserRanges(-math.pi / 2, math.pi / 180, 8.0, np.full(181, 2.0))
    return Scan("r1", 0, index, 0.2 * index, np.zeros((0, 4)), ranges, submap, pose)


@pytest.mark.slow  # one of the fast suite's slowest (about 1 s): CI runs it with the slow ones
def test_the_grid_holds_the_ranges_of_key_scans_only_so_a_long_session_stays_bounded():
    keys = FleetKeys("t")
    with (
        open_zenoh(ZenohOptions(listen=("tcp/127.0.0.1:0",))) as zbus,
        Ros2Node(zbus.session, "fleetmap_merger") as node,
    ):
        outputs = Ros2Outputs(InMemoryBus(), keys, node)
        # ten minutes at 5 Hz of a robot that stands, in one submap: one key scan
        for index in range(3_000):
            outputs.on_message(keys.scan("r1"), _scan(index, Transform2D(1.0, 2.0, 0.3)).to_msgpack())
        assert len(outputs.grid_scans) == 1
        # then 20 m along x in 0.05 m steps (400 scans), its submaps 20 scans each: a key scan every
        # scan_key_spacing along the path, and each submap's first
        start = 3_000
        for k in range(400):
            pose = Transform2D(0.05 * (k % 20), 0.0, 0.0)  # in its submap's frame
            outputs.on_message(keys.scan("r1"), _scan(start + k, pose, submap=1 + k // 20).to_msgpack())
        driven = 1 + 20 * math.ceil(20 * 0.05 / SCAN_KEY_SPACING)
        assert len(outputs.grid_scans) <= driven
        # scans no submap placed are in no grid
        outputs.on_message(keys.scan("r1"), _scan(start + 400, None, submap=None).to_msgpack())
        assert len(outputs.grid_scans) <= driven
        assert ("r1", 0) in outputs.grid_scans.ranges and ("r1", 2_999) not in outputs.grid_scans.ranges


def test_a_submaps_key_scans_are_spaced_along_the_path_or_turned():
    grid = GridScans()
    step = SCAN_KEY_SPACING / 4
    kept = [grid.add(_scan(k, Transform2D(step * k, 0.0, 0.0))) for k in range(9)]
    assert kept == [True, False, False, False, True, False, False, False, True]
    assert grid.add(_scan(9, Transform2D(step * 8, 0.0, SCAN_KEY_ROTATION + 0.01)))  # turned in place
    assert not grid.add(_scan(9, Transform2D(50.0, 0.0, 0.0)))  # the same scan again
    assert len(grid) == 4
