"""A robot's global pose follows its tracking between merges: last merged submap pose composed
with each placed scan's pose in it, at scan rate, never older than one already given."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from fleetmap.merger.engine import Merger
from fleetmap.merger.follow import PoseFollower
from fleetmap.merger.service import MergerService
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.memory_bus import InMemoryBus
from fleetmap.shared.io.messages import RobotPose, Scan

from tests.helpers import true_local_map

KEYS = FleetKeys("test")
NO_SEGMENTS = np.zeros((0, 4))


def _scan(robot: str, stamp: float, submap: int | None, pose: Transform2D | None, epoch: int = 0) -> Scan:
    return Scan(robot, epoch, int(stamp * 5), stamp, NO_SEGMENTS, submap=submap, pose=pose)


def _close(a: Transform2D, b: Transform2D) -> bool:
    dt, dr = a.distance(b)
    return dt < 1e-9 and dr < 1e-9


def test_a_placed_scan_gives_the_merged_submap_pose_composed_with_its_own() -> None:
    said: list[RobotPose] = []
    follower = PoseFollower(said.append)
    frame = Transform2D(4.0, -1.0, 0.5)
    follower.merged({"r1/0/3": (0, frame)})
    in_submap = Transform2D(0.7, 0.2, -0.1)
    pose = follower.scan(_scan("r1", 10.0, 3, in_submap))
    assert pose is not None and pose.component == 0 and pose.stamp == 10.0 and said == [pose]
    assert pose.pose is not None and _close(pose.pose, frame.compose(in_submap))
    # a scan in a submap no merge placed yet, an unplaced one, an older one: nothing said
    assert follower.scan(_scan("r1", 10.2, 4, in_submap)) is None
    assert follower.scan(_scan("r1", 10.4, None, None)) is None
    assert follower.scan(_scan("r1", 9.0, 3, in_submap)) is None
    assert len(said) == 1
    # a merge that places submap 4: the step's own pose of r1 (from its submap, at 9.8) gives way
    # to the newest placed scan's (10.2) under the new frames
    follower.merged({"r1/0/3": (0, frame), "r1/0/4": (1, Transform2D(1.0, 1.0, 0.0))})
    stepped = follower.step(RobotPose("r1", 0, 9.8, Transform2D(0.0, 0.0, 0.0), 0))
    assert stepped is not None and stepped.component == 1 and stepped.stamp == 10.2 and said[-1] is stepped
    assert stepped.pose is not None and _close(stepped.pose, Transform2D(1.0, 1.0, 0.0).compose(in_submap))
    # a step's pose older than one said is not said (its newest scan's submap placed no more); a
    # newer epoch's (the robot lost) is
    follower.merged({"r1/0/3": (0, frame)})
    assert follower.step(RobotPose("r1", 0, 10.1, Transform2D(0.0, 0.0, 0.0), 0)) is None
    lost = RobotPose("r1", 1, 10.0, None, None)
    assert follower.step(lost) is lost and said[-1] is lost
    # a robot whose newest epoch is not placed (kidnapped): its scans say nothing
    assert follower.scan(_scan("r1", 11.0, 0, in_submap, epoch=1)) is None
    assert len(said) == 3


def test_a_robot_whose_clock_steps_back_an_hour_keeps_getting_poses() -> None:
    # ordered by stamps, every pose after the step was older than the last one said: the robot's
    # pose froze for the hour
    said: list[RobotPose] = []
    follower = PoseFollower(said.append)
    follower.merged({"r1/0/0": (0, Transform2D(0.0, 0.0, 0.0))})
    at = Transform2D(0.1, 0.0, 0.0)
    for index, stamp in enumerate([5000.0, 5000.2, 1400.4, 1400.6, 1400.8]):
        assert follower.scan(Scan("r1", 0, index, stamp, NO_SEGMENTS, submap=0, pose=at)) is not None
    assert [p.stamp for p in said] == [5000.0, 5000.2, 1400.4, 1400.6, 1400.8] and follower.clock_steps == 1
    # a merge's pose from a submap stamped on the clock before the step is older than the scans since
    assert follower.step(RobotPose("r1", 0, 5000.1, at, 0)).stamp == 1400.8
    # the same scan again, or an earlier one by its count, says nothing whatever its stamp
    assert follower.scan(Scan("r1", 0, 4, 1400.8, NO_SEGMENTS, submap=0, pose=at)) is None
    assert follower.scan(Scan("r1", 0, 3, 9000.0, NO_SEGMENTS, submap=0, pose=at)) is None


def test_no_more_robots_are_followed_than_the_merger_keeps() -> None:
    follower = PoseFollower(max_robots=2)
    follower.merged({f"r{i}/0/0": (0, Transform2D(0.0, 0.0, 0.0)) for i in range(3)})
    poses = [follower.scan(_scan(f"r{i}", 1.0, 0, Transform2D(0.0, 0.0, 0.0))) for i in range(3)]
    assert poses[0] is not None and poses[1] is not None and poses[2] is None


@pytest.mark.slow  # merges whole-path maps of 200 simulated scans of three robots
def test_poses_stream_at_scan_rate_between_steps_on_the_bus() -> None:
    maps = {r: true_local_map("department", r, 0, 200) for r in ("r1", "r2", "r3")}
    bus = InMemoryBus()
    robot = bus.peer()
    merger = Merger(KEYS)
    service = MergerService(bus, merger, step_seconds=0)
    poses: list[RobotPose] = []
    got = threading.Condition()

    def on_pose(key: str, payload: bytes) -> None:
        with got:
            poses.append(RobotPose.from_msgpack(payload))
            got.notify_all()

    robot.subscribe(KEYS.pose("r1"), on_pose)
    service.start()
    try:
        for r, (m, _) in maps.items():
            robot.declare_liveliness(KEYS.alive(r))  # a live merger listens to robots holding their token
            robot.publish(KEYS.localmap(r), m.to_msgpack())
        assert service.run_once()
        stepped = [p for p in poses if p.robot == "r1"]
        assert stepped and stepped[-1].pose is not None  # the step placed r1 at its map's last scan
        frame = merger.global_map.components[0].poses["r1/0/0"]
        last = maps["r1"][0].stamp
        # five scans after the step, each moving 10 cm in r1's submap: five poses, no step between
        for k in range(1, 6):
            in_submap = maps["r1"][0].pose.compose(Transform2D(0.1 * k, 0.0, 0.0))
            robot.publish(KEYS.scan("r1"), _scan("r1", last + 0.2 * k, 0, in_submap).to_msgpack())
        with got:
            assert got.wait_for(lambda: len(poses) >= len(stepped) + 5, timeout=30.0), poses
        followed = poses[len(stepped) :]
        for k, p in enumerate(followed, 1):
            assert math.isclose(p.stamp, last + 0.2 * k) and p.component == 0 and p.pose is not None
            expected = frame.compose(maps["r1"][0].pose.compose(Transform2D(0.1 * k, 0.0, 0.0)))
            assert _close(p.pose, expected)
        # a scan stamped far past this clock (9.2e9 s: under the format's limit) is dropped; had it
        # been followed, no later pose of r1 would have been newer than it
        future = maps["r1"][0].pose.compose(Transform2D(0.7, 0.0, 0.0))
        robot.publish(KEYS.scan("r1"), Scan("r1", 0, 10**6, 9.2e9, NO_SEGMENTS, submap=0, pose=future).to_msgpack())
        robot.publish(KEYS.scan("r1"), _scan("r1", last + 1.4, 0, future).to_msgpack())
        with got:
            assert got.wait_for(lambda: len(poses) >= len(stepped) + 6, timeout=30.0), poses
        assert math.isclose(poses[-1].stamp, last + 1.4) and service.future_scans == 1
        assert merger.stats.steps == 1
    finally:
        service.close()
