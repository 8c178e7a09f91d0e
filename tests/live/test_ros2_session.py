"""A live session whose robots are on ROS 2 topics: ``fleetmap play --ros2`` -> ``fleetmap agent
--ros2`` -> the fleet (``Session(ros2=True)``, what ``benchmarks/live.py --ros2`` measures)."""

from __future__ import annotations

import dataclasses
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from fleetmap.scenarios import load_scenario
from fleetmap.scenarios.stream import ScenarioSource
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import decode
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

from fleetmap.ros2_robots import write_robot_bag
from fleetmap.runner import Session, SessionError
from tests.bus_helpers import Inbox, eventually

pytestmark = pytest.mark.slow

WAIT = 60.0
"""The longest a test waits on a process (s): a busy machine starts one in seconds."""


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


def test_agents_flooded_by_their_robots_stop_on_sigterm_and_put_every_scan_they_took_on_the_bus(tmp_path: Path) -> None:
    # four robots publish their whole runs as fast as their players can while their agents track;
    # each agent gets SIGTERM once its first scan is on the fleet's bus, in the middle of the flood.
    # Each must stop (a zenoh thread holding the interpreter would keep it from ever seeing the
    # signal) and lose nothing it took: its summary's scans are on the bus, in order
    scenario = load_scenario("department-16")
    robots = [r.id for r in scenario.robots[:4]]
    endpoint = free_loopback_endpoint()
    keys = FleetKeys("t")
    procs: list[subprocess.Popen[bytes]] = []

    def start(name: str, *args: str) -> subprocess.Popen[bytes]:
        with open(tmp_path / f"{name}.log", "wb") as log:
            procs.append(subprocess.Popen([sys.executable, "-m", "fleetmap", *args], stdout=log, stderr=log))
        return procs[-1]

    where = ["--mode", "client", "--connect", endpoint]
    try:
        start("router", "router", "--listen", endpoint)
        with ZenohBus.open(ZenohOptions(mode="client", connect=(endpoint,), fleet="t", connect_wait=WAIT)) as bus:
            inboxes = {robot: Inbox() for robot in robots}
            for robot in robots:
                bus.subscribe(keys.scan(robot), inboxes[robot])
                bus.subscribe(keys.localmap(robot), Inbox())  # the agent's first scan waits for a listener
            agents = {
                robot: start(f"agent-{robot}", "agent", "--robot", robot, "--ros2", "--namespace", robot,
                             "--wait-for-listener", str(WAIT), *where, "--fleet", "t")
                for robot in robots
            }  # fmt: skip
            for robot in robots:
                bag = tmp_path / "bags" / robot
                bag.parent.mkdir(exist_ok=True)
                write_robot_bag(scenario, robot, bag)
                assert eventually(
                    lambda robot=robot: "listening on" in (tmp_path / f"agent-{robot}.log").read_text(), WAIT
                )
                start(f"play-{robot}", "play", str(bag), "--ros2", "--namespace", robot, "--speed", "0", *where)
            for robot, agent in agents.items():
                assert inboxes[robot].wait_for(1, WAIT), f"{robot}: no scan reached the bus"
                agent.send_signal(signal.SIGTERM)
            for robot, agent in agents.items():
                assert agent.wait(WAIT) == 0, (tmp_path / f"agent-{robot}.log").read_text()[-3000:]
            for robot in robots:
                summary = re.search(r"agent \S+ stopped: (\d+) scans", (tmp_path / f"agent-{robot}.log").read_text())
                assert summary is not None
                took = int(summary.group(1))
                assert eventually(lambda robot=robot, took=took: len(inboxes[robot].items) >= took, WAIT)
                indices = [decode(payload).index for _, payload in inboxes[robot].items]  # type: ignore[attr-defined]
                assert indices == list(range(took)), robot
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait(10)
