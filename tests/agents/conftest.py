"""Scans the agent tests share: a bundled robot's, and a robot that is kidnapped (scanning at 5 Hz
with odometry for the tracking front end; every metre, as in the paper, for the pivot one)."""

from __future__ import annotations

import json
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np
import pytest
from fleetmap.agents.agent import LOST_SCANS, Agent
from fleetmap.scenarios import Scenario, SimulatedScan, load_scenario, robot_stream
from fleetmap.scenarios.loader import parse_scenario
from fleetmap.shared.config import FleetmapConfig, TrackingParams
from fleetmap.shared.io.messages import FleetEvent, Message
from fleetmap.shared.io.sources import SourceScan

KIDNAPPED_DENSE = """
name = "kidnapped-dense"
world = "department"
seed = 5

[[robots]]
id = "r1"
# hall -> passage at 1.5 m/s, scanning at 5 Hz, then (t = 4) carried into the hallway, facing east
path = [[21.5, 4.0], [21.5, 2.0], [20.0, 1.2], [16.0, 1.2], [8.0, 1.2]]
spacing = 0.3
period = 0.2
turn_rate = 1.5

[[events]]
t = 4.0
type = "kidnap"
robot = "r1"
pose = [10.0, 6.0, 0.0]
path = [[16.0, 6.0]]
"""
"""One robot of the department world carried at t = 4 s (scan 20) into the hallway; its odometry
does not see it."""

KIDNAPPED = """
name = "kidnapped"
world = "department"
seed = 5

[[robots]]
id = "r1"
# hall -> passage, then (t = 3) carried into the hallway, facing east
path = [[21.5, 4.0], [21.5, 2.0], [20.0, 1.2], [16.0, 1.2], [8.0, 1.2]]
spacing = 1.0
period = 0.5

[[events]]
t = 3.0
type = "kidnap"
robot = "r1"
pose = [10.0, 6.0, 0.0]
path = [[16.0, 6.0]]
"""
"""One robot of the department world kidnapped at scan 6 into a part of the building its scans
show to be different (the hallway); a test scenario, so that it does not change with the bundled ones."""


def source_scans(stream: Iterable[SimulatedScan]) -> list[SourceScan]:
    """What an agent receives from a simulated robot: no pose, its odometry."""
    return [SourceScan(s.index, s.stamp, s.scan, s.odometry) for s in stream]


def pivot(robot: str, publish_every: int = 3, kidnap_after: int = 2, lost_scans: int = LOST_SCANS) -> Agent:
    """An agent with the paper's pivot front end (``--front-end pivot``)."""
    tracking = TrackingParams(front_end="pivot", publish_every=publish_every, kidnap_after=kidnap_after)
    return Agent(robot, replace(FleetmapConfig(), tracking=tracking), lost_scans=lost_scans)


def run(agent: Agent, scans: Iterable[SourceScan]) -> list[Message]:
    out: list[Message] = []
    for s in scans:
        out += agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
    return out + agent.finish()


def epoch_events(messages: list[Message]) -> list[dict[str, object]]:
    return [json.loads(m.detail) for m in messages if isinstance(m, FleetEvent) and m.kind == "epoch"]


def kidnap_index(stream: list[SimulatedScan]) -> int:
    """The first scan after the (first) kidnap, from the ground truth."""
    return next(s.index for s in stream if s.leg > 0)


@pytest.fixture(scope="session")
def department() -> Scenario:
    return load_scenario("department")


@pytest.fixture(scope="session")
def r2_stream(department: Scenario) -> list[SimulatedScan]:
    """Robot r2 of the department loop, its first 16 scans (3 s, 4.5 m: down the hall)."""
    return list(robot_stream(department, "r2"))[:16]


@pytest.fixture(scope="session")
def sparse_department() -> Scenario:
    from tests.helpers import sparse

    return load_scenario(sparse("department"))


@pytest.fixture(scope="session")
def sparse_r2_stream(sparse_department: Scenario) -> list[SimulatedScan]:
    """Robot r2 of the department loop scanning every metre: its first 16 scans, down the hall
    and along the passage."""
    return list(robot_stream(sparse_department, "r2"))[:16]


@pytest.fixture(scope="session")
def sparse_r2_messages(sparse_r2_stream: list[SimulatedScan]) -> list[Message]:
    return run(pivot("r2"), source_scans(sparse_r2_stream))


@pytest.fixture(scope="session")
def kidnapped() -> Scenario:
    return parse_scenario(tomllib.loads(KIDNAPPED), "kidnapped")


@pytest.fixture(scope="session")
def kidnapped_stream(kidnapped: Scenario) -> list[SimulatedScan]:
    """The kidnapped robot's scans, up to four after the kidnap."""
    stream = list(robot_stream(kidnapped, "r1"))
    return stream[: kidnap_index(stream) + 4]


@dataclass(frozen=True)
class Steps:
    """An agent run scan by scan: what each ``add_scan`` returned, then ``finish``."""

    agent: Agent
    steps: list[tuple[int, list[Message]]]
    """(scan index, messages) per scan."""
    final: list[Message]

    @property
    def messages(self) -> list[Message]:
        return [m for _, out in self.steps for m in out] + self.final


@pytest.fixture(scope="session")
def kidnapped_run(kidnapped_stream: list[SimulatedScan]) -> Steps:
    agent = pivot("r1", kidnap_after=2)
    steps = [(s.index, agent.add_scan(s.index, s.stamp, s.scan)) for s in kidnapped_stream]
    return Steps(agent, steps, agent.finish())


@pytest.fixture(scope="session")
def carried() -> Scenario:
    return parse_scenario(tomllib.loads(KIDNAPPED_DENSE), "kidnapped-dense")


@pytest.fixture(scope="session")
def carried_stream(carried: Scenario) -> list[SimulatedScan]:
    """The carried robot's scans, up to 3 s after it is put down."""
    stream = list(robot_stream(carried, "r1"))
    return stream[: kidnap_index(stream) + 15]


@pytest.fixture(scope="session")
def carried_run(carried_stream: list[SimulatedScan]) -> Steps:
    agent = Agent("r1")
    steps = [(s.index, agent.add_scan(s.index, s.stamp, s.scan, s.odometry)) for s in carried_stream]
    return Steps(agent, steps, agent.finish())


def blocked(s: SimulatedScan, distance: float = 0.5, half_width_deg: float = 60.0) -> SimulatedScan:
    """The scan with its view blocked by a board ``distance`` in front (a person walking by)."""
    scan = s.scan
    angles = scan.angle_min + np.arange(len(scan.ranges)) * scan.angle_increment
    ranges = np.where(np.abs(angles) <= np.radians(half_width_deg), distance / np.cos(angles), np.nan)
    return replace(s, scan=replace(scan, ranges=ranges))
