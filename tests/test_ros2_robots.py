"""A scenario's robot as a ROS 2 bag: read back, it is the robot's own simulated stream."""

from __future__ import annotations

import numpy as np
import pytest
from fleetmap.scenarios import load_scenario
from fleetmap.scenarios.stream import ScenarioSource
from fleetmap.shared.io.sources import Ros2BagSource

from fleetmap.ros2_robots import write_robot_bag


def test_a_robots_bag_holds_its_simulated_scans_and_odometry_at_their_stamps(tmp_path):
    scenario = load_scenario("department")
    robot = scenario.robots[1].id
    scans = write_robot_bag(scenario, robot, tmp_path / "bag")
    played = list(Ros2BagSource(tmp_path / "bag"))
    simulated = list(ScenarioSource(scenario, robot))
    assert scans == len(played) == len(simulated) > 50
    for p, s in zip(played, simulated, strict=True):
        assert p.stamp == pytest.approx(s.stamp, abs=1e-9)  # a ROS stamp is whole nanoseconds
        # the ranges as LaserScan carries them (float32), no return where the simulation has none
        np.testing.assert_allclose(p.scan.ranges, s.scan.ranges, rtol=1e-6, equal_nan=True)
        # LaserScan's angles are float32
        assert p.scan.angle_min == pytest.approx(s.scan.angle_min, abs=1e-6)
        assert p.scan.angle_increment == pytest.approx(s.scan.angle_increment, abs=1e-7)
        assert p.scan.range_max == s.scan.range_max
        assert p.odometry is not None and s.odometry is not None
        assert max(p.odometry.distance(s.odometry)) < 1e-9
