"""A live session whose robots are on ROS 2 topics: ``fleetmap play --ros2`` -> ``fleetmap agent
--ros2`` -> the fleet (``Session(ros2=True)``, what ``benchmarks/live.py --ros2`` measures)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from fleetmap.scenarios import load_scenario
from fleetmap.scenarios.stream import ScenarioSource
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.io.recording_reader import RecordingReader

from fleetmap.runner import Session, SessionError

pytestmark = pytest.mark.slow


def test_robots_on_ros2_topics_reach_the_fleet_scan_for_scan_and_are_placed(tmp_path: Path) -> None:
    base = load_scenario("department")
    scenario = dataclasses.replace(base, robots=base.robots[:2], events=())
    session = Session(scenario, tmp_path, FleetmapConfig(), speed=4.0, fleet="t", progress=False, ros2=True)
    report = session.run()
    assert report["robots_placed"] == 2
    with RecordingReader(tmp_path / "session.mcap") as reader:
        counts = reader.topic_counts()
    for robot in scenario.robots:
        simulated = len(list(ScenarioSource(scenario, robot.id)))
        assert counts[f"fleet/t/robots/{robot.id}/scan"] == simulated
        agent = (tmp_path / "logs" / f"agent-{robot.id}.log").read_text()
        assert f"ROS 2 /{robot.id}/scan" in agent and " 0 dropped" in agent  # heard over ROS 2, none lost
        assert f"{simulated} on /{robot.id}/scan" in (tmp_path / "logs" / f"play-{robot.id}.log").read_text()


def test_a_ros2_session_refuses_events_it_cannot_play(tmp_path: Path) -> None:
    scenario = load_scenario("department-events")
    with pytest.raises(SessionError, match="events"):
        Session(scenario, tmp_path, FleetmapConfig(), ros2=True, progress=False).run()
