"""Tracking on clocks as real robots have them (issue 48): the scans' registrations, not their
stamps, say where the robot is; a broken clock is said once, and a kidnap is still a kidnap."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from fleetmap.agents.agent import Agent
from fleetmap.scenarios import SimulatedScan, load_scenario, robot_stream
from fleetmap.scenarios.clocks import break_clock
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.logs import read_carmen
from fleetmap.shared.io.sources import CarmenSource

from tests.agents.conftest import epoch_events, kidnap_index
from tests.helpers import steps_off


def epoch_poses(stream: list[SimulatedScan], agent: Agent) -> tuple[dict[int, tuple[int, Transform2D]], list]:
    poses: dict[int, tuple[int, Transform2D]] = {}
    messages = []
    for s in [*stream, None]:
        messages += agent.finish() if s is None else agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        # a burst's scans are tracked when it ends (fleetmap.agents.bursts)
        poses.update({index: (epoch, pose) for index, epoch, pose in agent.tracked if pose is not None})
    return poses, messages


@pytest.fixture(scope="module")
def r2_loop() -> list[SimulatedScan]:
    """Robot r2 of the department loop, all of it (122 scans at 5 Hz, drifting odometry)."""
    return list(robot_stream(load_scenario("department"), "r2"))


@pytest.fixture(scope="module")
def true_clock(r2_loop: list[SimulatedScan]) -> dict[bool, dict[int, tuple[int, Transform2D]]]:
    return {odometry: epoch_poses(r2_loop, Agent("r2", odometry=odometry))[0] for odometry in (True, False)}


@pytest.mark.parametrize(
    ("clock", "within"),
    [
        ("burst", 0.05),
        ("repeat", 0.05),
        ("drop", 0.05),
        # stamps within physics (+-50 ms at 5 Hz; odometry 0.1 s late): trusted, their error is drift
        ("jitter", 0.15),
        ("skew", 0.15),
    ],
)
@pytest.mark.slow  # tracks a robot's loop twelve times over (about 8 s in all)
@pytest.mark.parametrize("odometry", [True, False], ids=["odometry", "no-odometry"])
def test_a_robot_on_a_broken_clock_is_tracked_as_on_the_true_one(r2_loop, true_clock, clock, within, odometry) -> None:
    broken = list(break_clock(r2_loop, clock, seed=7))
    poses, messages = epoch_poses(broken, Agent("r2", odometry=odometry))
    assert epoch_events(messages) == [], "no kidnap"
    assert set(poses) == {s.index for s in broken}, "every scan placed"
    off = [(i, round(p.distance(true_clock[odometry][i][1])[0], 3)) for i, (_, p) in poses.items()]
    worst = max(off, key=lambda x: x[1])
    assert worst[1] < within, f"scan {worst[0]} is {worst[1]} m from where the true clock's tracking put it"


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_stamps_that_are_not_the_scans_times_are_said_once_with_counts(r2_loop, caplog) -> None:
    broken = list(break_clock(r2_loop, "burst", seed=7))
    with caplog.at_level(logging.WARNING, logger="fleetmap.agents.tracker"):
        epoch_poses(broken, Agent("r2"))
    said = [r.getMessage() for r in caplog.records if "scans' times" in r.getMessage()]
    assert len(said) == 1 and "stamps repeated" in said[0] and "in bursts" in said[0] and "mean period" in said[0]
    with caplog.at_level(logging.WARNING, logger="fleetmap.agents.tracker"):
        caplog.clear()
        epoch_poses(r2_loop, Agent("r2"))
    assert not [r for r in caplog.records if "scans' times" in r.getMessage()], "a true clock is trusted"


def test_a_kidnap_on_a_bursting_clock_is_still_a_new_epoch(carried_stream) -> None:
    kidnap = kidnap_index(carried_stream)
    broken = list(break_clock(carried_stream, "burst", seed=7))
    poses, messages = epoch_poses(broken, Agent("r1"))
    [event] = epoch_events(messages)
    assert event["first_scan"] == kidnap
    assert all(poses[s.index][0] == 1 for s in broken if s.index >= kidnap + TrackingParams().kidnap_after)


def person_in_front(s: SimulatedScan, distance: float = 0.5) -> SimulatedScan:
    """The scan with a person standing ``distance`` in front of the laser's left half: half of its
    beams end on them, the other half still see the walls."""
    scan = s.scan
    angles = scan.angle_min + np.arange(len(scan.ranges)) * scan.angle_increment
    ranges = np.where(angles >= 0, distance / np.maximum(np.cos(angles), 0.2), scan.ranges)
    return replace(s, scan=replace(scan, ranges=ranges))


def test_a_person_in_front_of_half_the_laser_for_two_seconds_is_no_kidnap(department) -> None:
    stream = list(robot_stream(department, "r2"))[:40]
    blocked = 2 * TrackingParams().kidnap_after  # 10 scans at 5 Hz
    stream = [*stream[:20], *(person_in_front(s) for s in stream[20 : 20 + blocked]), *stream[20 + blocked :]]
    poses, messages = epoch_poses(stream, Agent("r2"))
    assert epoch_events(messages) == []
    frame = stream[0].pose
    after = stream[20 + blocked]
    assert after.index in poses, "the scan after the person is placed"
    truth = frame.inverse().compose(after.pose)
    assert poses[after.index][1].distance(truth)[0] < 0.05


@pytest.mark.slow  # tracks 20 scans of a real log (about 2 s)
def test_a_scan_that_fits_only_in_the_time_its_sequence_takes_is_placed_and_the_stamps_doubted(
    datasets: Path, caplog
) -> None:
    # freiburg-101-corrected (a scan every 3 s) stamped in bursts, without odometry: scan 4 is a
    # metre and 27 degrees from scan 3, stamped a millisecond after it, before anything has shown
    # the stamps wrong. Within a millisecond's reach only a fit scoring 0.79 a metre off was found
    # (the true pose's scores 6.08); placed there, scans 5, 6, 8 and 9 then fitted nowhere
    path = datasets / "corrected" / "freiburg-101-corrected.log.gz"
    given = list(break_clock(list(CarmenSource(path)), "burst", seed=0))[:20]
    assert given[4].stamp - given[3].stamp < 0.01
    agent = Agent("r1", odometry=False)
    poses: dict[int, Transform2D] = {}
    with caplog.at_level(logging.WARNING, logger="fleetmap.agents"):
        for s in given:
            agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
            poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    assert agent.counts.epochs == 1
    assert sorted(poses) == [s.index for s in given], f"unplaced: {sorted({s.index for s in given} - set(poses))}"
    off = steps_off(truth, poses, range(1, 20), 0.3, 3.0)
    assert not off, f"steps 0.3 m or 3 degrees or more off their truth (m, deg), by scan: {off}"
    said = [r.getMessage() for r in caplog.records if "not the scans' times" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("scan 4 moved"), said


@pytest.mark.slow  # tracks 20 scans of a real log (about 2 s)
def test_a_scan_no_fit_places_within_the_stamps_interval_is_searched_about_constant_velocity_by_its_sequence(
    datasets: Path,
) -> None:
    # aces-corrected stamped in bursts, without odometry: scans 3-6 stamped within a millisecond,
    # scan 4 a metre from scan 3. Constant velocity over 0.6 ms (5 cm wide) held it where scan 3
    # was, at a fifth of the robot's score; neither the scan pair nor the re-acquisition is valid
    # there, and scans 4 and 5 were placed 0.9 and 0.8 m short (record 075)
    path = datasets / "corrected" / "aces-corrected.log.gz"
    given = list(break_clock(list(CarmenSource(path)), "burst", seed=0))[:20]
    assert given[4].stamp - given[3].stamp < 0.01
    agent = Agent("r1", odometry=False)
    poses: dict[int, Transform2D] = {}
    for s in given:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    assert agent.counts.epochs == 1
    assert sorted(poses) == [s.index for s in given], f"unplaced: {sorted({s.index for s in given} - set(poses))}"
    off = steps_off(truth, poses, range(1, 20), 0.3, 3.0)
    assert not off, f"steps 0.3 m or 3 degrees or more off their truth (m, deg), by scan: {off}"
