"""The robot stream: the same scans on every run, what the laser sees from the true pose, events applied."""

from __future__ import annotations

import numpy as np
from fleetmap.scenarios.fleet import plan
from fleetmap.scenarios.laser import true_ranges
from fleetmap.scenarios.loader import load_scenario
from fleetmap.scenarios.stream import robot_stream


def test_every_run_gives_the_same_scans_and_a_restart_resumes_them() -> None:
    sc = load_scenario("department")
    first = list(robot_stream(sc, "r2"))
    second = list(robot_stream(sc, "r2"))
    resumed = list(robot_stream(sc, "r2", start_index=10))
    assert len(first) == len(plan(sc, "r2")) and [s.index for s in first] == list(range(len(first)))
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a.scan.ranges, b.scan.ranges)
    for a, b in zip(first[10:], resumed, strict=True):
        assert a.pose == b.pose and a.stamp == b.stamp
        np.testing.assert_array_equal(a.scan.ranges, b.scan.ranges)
    other = next(robot_stream(sc, "r3"))
    assert not np.array_equal(np.nan_to_num(other.scan.ranges), np.nan_to_num(first[0].scan.ranges))


def test_each_scan_is_what_the_laser_sees_from_the_true_pose_and_carries_no_pose() -> None:
    sc = load_scenario("office")
    for s in list(robot_stream(sc, "r1"))[::7]:
        true, _ = true_ranges(sc.world.walls, (s.pose.x, s.pose.y, s.pose.theta), sc.laser)
        seen = np.isfinite(s.scan.ranges) & np.isfinite(true)
        assert seen.sum() > 100
        assert np.abs(s.scan.ranges[seen] - true[seen]).max() < 6 * sc.laser.noise
        assert s.scan.odom is None and s.scan.stamp == s.stamp


def test_a_crashed_robot_stops_and_a_kidnapped_one_jumps() -> None:
    sc = load_scenario("department-events")
    crash = next(e for e in sc.events if e.kind == "crash")
    stamps = [s.stamp for s in robot_stream(sc, crash.robot)]
    assert stamps and max(stamps) < crash.t
    kidnap = sc.kidnaps()[0]
    scans = list(robot_stream(sc, kidnap.robot))
    jump = next(i for i, s in enumerate(scans) if s.leg == 1)
    assert scans[jump].stamp >= kidnap.t > scans[jump - 1].stamp
    assert scans[jump].pose.distance(scans[jump - 1].pose)[0] > 5.0
    assert scans[jump].pose.distance(kidnap.pose) == (0.0, 0.0)
