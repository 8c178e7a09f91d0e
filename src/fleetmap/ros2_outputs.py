"""The fleet's map and poses on ROS 2 topics over rmw_zenoh (``fleetmap merger --ros2``).

What a ROS 2 navigation stack and RViz expect of a map provider:

- ``/map``: nav_msgs/OccupancyGrid in frame ``map``, reliable and transient local (REP-2003), so
  nav2's map server or RViz started later still get the last map: the largest component's
  occupancy grid (:func:`fleetmap.report.occupancy_of`: free along the placed scans' beams, occupied
  on the fused walls), remade at most every ``map_seconds`` when a new global map came. The beams
  are those of the submaps' key scans (:class:`GridScans`), so what is held grows with the
  distance the robots travel, as the merger's key scans do, not with the session's length;
- ``/tf``: tf2_msgs/TFMessage with ``map -> <robot>/odom`` for each robot placed in that component,
  at each of its placed scans: the laser's pose in the map composed with the inverse of its
  odometry pose at the same scan (what a localizer publishes, REP 105);
- ``/<robot>/fleetmap/pose``: geometry_msgs/PoseWithCovarianceStamped, the robot's laser pose in
  ``map`` at each placed scan, stamped with the scan's own stamp (covariance left zero: unknown).

It listens to the fleet's own messages (global maps, submaps, scans, robot poses) on the bus, so
it runs beside the merger without touching it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

from fleetmap.merger.scangraph import is_key
from fleetmap.report import SessionLog, occupancy_of
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.bus import Bus, Handle
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import BadMessage, GlobalMap, LaserRanges, LocalMap, RobotPose, Scan, decode
from fleetmap.shared.io.occupancy import OccupancyGrid
from fleetmap.shared.io.ros2_node import Ros2Node, Ros2Publisher

log = logging.getLogger(__name__)

MAP_FRAME = "map"
MAP_SECONDS = 2.0
"""The occupancy grid on /map is remade at most this often (s): a whole session's beams take time."""
ODOMETRY_KEPT = 2000
"""Scans' odometry kept per robot to find the one a robot pose was taken at."""
NODE_NAME = "fleetmap_merger"


def _time(stamp: float) -> Any:
    sec = math.floor(stamp)
    nanosec = min(round((stamp - sec) * 1e9), 999_999_999)
    return wire.typestore().types["builtin_interfaces/msg/Time"](sec, nanosec)


def _header(stamp: float, frame: str) -> Any:
    return wire.typestore().types["std_msgs/msg/Header"](_time(stamp), frame)


def _quaternion(yaw: float) -> Any:
    return wire.typestore().types["geometry_msgs/msg/Quaternion"](0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def occupancy_message(grid: OccupancyGrid, stamp: float) -> Any:
    """nav_msgs/OccupancyGrid of ``grid``: row-major from cell (0, 0) at ``origin``, -1/0/100."""
    T = wire.typestore().types
    rows, cols = grid.cells.shape
    origin = T["geometry_msgs/msg/Pose"](
        T["geometry_msgs/msg/Point"](float(grid.origin[0]), float(grid.origin[1]), 0.0), _quaternion(0.0)
    )
    info = T["nav_msgs/msg/MapMetaData"](_time(stamp), float(grid.resolution), cols, rows, origin)
    data = np.ascontiguousarray(grid.cells, dtype=np.int8).reshape(-1)
    return T[wire.OCCUPANCY_GRID](_header(stamp, MAP_FRAME), info, data)


def transform_message(parent: str, child: str, pose: Transform2D, stamp: float) -> Any:
    T = wire.typestore().types
    transform = T["geometry_msgs/msg/Transform"](
        T["geometry_msgs/msg/Vector3"](pose.x, pose.y, 0.0), _quaternion(pose.theta)
    )
    return T["geometry_msgs/msg/TransformStamped"](_header(stamp, parent), child, transform)


def pose_message(pose: Transform2D, stamp: float) -> Any:
    T = wire.typestore().types
    point = T["geometry_msgs/msg/Pose"](T["geometry_msgs/msg/Point"](pose.x, pose.y, 0.0), _quaternion(pose.theta))
    with_covariance = T["geometry_msgs/msg/PoseWithCovariance"](point, np.zeros(36))
    return T[wire.POSE_WITH_COVARIANCE_STAMPED](_header(stamp, MAP_FRAME), with_covariance)


class GridScans:
    """The raw ranges the occupancy grid on /map is made of: those of each submap's key scans.

    A placed scan's ranges are kept when it is a key scan of the submap that placed it
    (:func:`fleetmap.merger.scangraph.is_key`: ``SCAN_KEY_SPACING`` along the path or
    ``SCAN_KEY_ROTATION`` turned from the submap's last one), as the merger keeps key scans to
    refine with; a scan that no submap placed is in no grid and is not kept. A robot that stands
    or turns slowly for hours adds nothing; the scans held grow with the distance travelled.
    """

    def __init__(self) -> None:
        self.ranges: dict[tuple[str, int], LaserRanges] = {}
        """The kept ranges by (robot, scan index), as :class:`~fleetmap.report.SessionLog` has them."""
        self._last: dict[str, tuple[int, Transform2D]] = {}
        """Each submap's last key scan: its index and its pose in the submap."""

    def add(self, scan: Scan) -> bool:
        """Keep ``scan``'s ranges if it is a key scan of its submap; whether it was kept."""
        if scan.ranges is None or scan.submap is None or scan.pose is None:
            return False
        submap = f"{scan.robot}/{scan.epoch}/{scan.submap}"
        last = self._last.get(submap)
        if last is not None and scan.index <= last[0]:
            return False  # a scan again, or out of order
        if not is_key(last[1] if last is not None else None, scan.pose):
            return False
        self._last[submap] = (scan.index, scan.pose)
        self.ranges[(scan.robot, scan.index)] = scan.ranges
        return True

    def __len__(self) -> int:
        return len(self.ranges)


class Ros2Outputs:
    """The fleet's map and poses on ``node`` (see the module); :meth:`start` listens on ``bus``."""

    def __init__(
        self,
        bus: Bus,
        keys: FleetKeys,
        node: Ros2Node,
        map_seconds: float = MAP_SECONDS,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.bus = bus
        self.keys = keys
        self.node = node
        self.map_seconds = map_seconds
        self.clock = clock
        self.map = node.publisher("/map", wire.OCCUPANCY_GRID, wire.MAP)
        self.tf = node.publisher("/tf", wire.TF_MESSAGE, wire.TF)
        self._poses: dict[str, Ros2Publisher] = {}
        self._log = SessionLog()
        """The last global map and the latest version of every submap (scans go to ``grid_scans``)."""
        self.grid_scans = GridScans()
        self._odometry: dict[str, OrderedDict[float, Transform2D]] = {}
        self._lock = threading.Lock()
        self._new_map = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._maps, name="ros2-map", daemon=True)
        self._handles: list[Handle] = []
        self.maps_published = 0
        self.poses_published = 0

    def start(self) -> None:
        for keyexpr in (self.keys.globalmap, self.keys.all_localmaps, self.keys.all_scans, self.keys.all_poses):
            self._handles.append(self.bus.subscribe(keyexpr, self.on_message))
        self._thread.start()

    def on_message(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload)
        except BadMessage:
            return  # the merger counts malformed messages
        if isinstance(message, RobotPose):
            self._on_pose(message)
            return
        with self._lock:
            if isinstance(message, Scan):
                if message.odometry is not None:
                    kept = self._odometry.setdefault(message.robot, OrderedDict())
                    kept[message.stamp] = message.odometry
                    while len(kept) > ODOMETRY_KEPT:
                        kept.popitem(last=False)
                self.grid_scans.add(message)
            elif isinstance(message, GlobalMap):
                self._log.global_maps[:] = [message]  # only the last one is ever read
            elif isinstance(message, LocalMap):
                self._log.add(message)
        if isinstance(message, GlobalMap):
            self._new_map.set()

    def _on_pose(self, message: RobotPose) -> None:
        """A placed scan's pose: /<robot>/fleetmap/pose, and map -> <robot>/odom on /tf."""
        if message.pose is None or message.component != 0:
            return  # /map is the largest component's: a robot elsewhere is not in its frame
        with self._lock:
            kept = self._odometry.get(message.robot)
            odometry = kept.get(message.stamp) if kept is not None else None
            publisher = self._poses.get(message.robot)
            if publisher is None:
                topic = f"/{message.robot}/fleetmap/pose"
                publisher = self._poses[message.robot] = self.node.publisher(
                    topic, wire.POSE_WITH_COVARIANCE_STAMPED, wire.Qos(depth=10)
                )
        publisher.publish(pose_message(message.pose, message.stamp))
        if odometry is not None:
            odom = message.pose.compose(odometry.inverse())
            child = f"{message.robot}/odom"
            tf = wire.typestore().types[wire.TF_MESSAGE]([transform_message(MAP_FRAME, child, odom, message.stamp)])
            self.tf.publish(tf)
        self.poses_published += 1

    def _maps(self) -> None:
        while not self._stop.is_set():
            if not self._new_map.wait(0.2):
                continue
            self._new_map.clear()
            try:
                self.publish_map()
            except Exception:  # the map thread must go on: the next global map may do
                log.exception("the occupancy grid for /map failed")
            self._stop.wait(self.map_seconds)

    def publish_map(self) -> bool:
        """Publish the largest component's occupancy grid on /map; whether there was one."""
        with self._lock:
            if self._log.main is None:
                return False
            # what the grid is made of, so that scans and poses go on while it is made
            snapshot = SessionLog(
                global_maps=list(self._log.global_maps),
                local_maps=dict(self._log.local_maps),
                ranges=dict(self.grid_scans.ranges),
            )
        grid = occupancy_of(snapshot)
        stamp = snapshot.global_maps[-1].stamp
        if grid.cells.size == 0:
            return False
        self.map.publish(occupancy_message(grid, stamp))
        self.maps_published += 1
        log.info("/map: %d x %d cells of %.2f m published", grid.cells.shape[1], grid.cells.shape[0], grid.resolution)
        return True

    def close(self) -> None:
        for handle in self._handles:
            handle.close()
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(10)
        if self._new_map.is_set() or self.maps_published == 0:
            self.publish_map()  # the last global map's grid: what a late subscriber gets
