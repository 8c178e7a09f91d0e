"""The scans a simulated robot takes, as a live agent receives them.

:func:`robot_stream` yields, for each scan of a robot's plan (:func:`fleetmap.scenarios.fleet.plan`),
its index, stamp (scenario seconds), true laser pose (world frame) and the simulated
:class:`~fleetmap.shared.core.rangescan.RangeScan`. The noise of scan k of robot r is drawn from its own
generator seeded by (scenario seed, robot id, k): every run of a scenario gives the same scans,
and a stream restarted at scan k gives the same scans from there on. :class:`ScenarioSource` is
the same stream as an agent's scan source.

The true pose is ground truth for scoring: an agent sends the scan, never the pose (the scan's
``odom`` is left empty for that reason).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from fleetmap.scenarios.fleet import PlannedScan, Scenario, plan
from fleetmap.scenarios.laser import noisy_ranges, true_ranges
from fleetmap.scenarios.loader import load_scenario
from fleetmap.scenarios.odometry import simulate_odometry
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.sources import SourceScan, checked_scan


@dataclass(frozen=True)
class SimulatedScan:
    """One scan of a simulated robot, with its ground truth."""

    robot: str
    index: int
    stamp: float
    """Scenario seconds."""
    pose: Transform2D
    """True laser pose in the world frame: ground truth, never sent to the algorithms."""
    leg: int
    """0 before the robot's first kidnap, k after its k-th."""
    scan: RangeScan
    odometry: Transform2D | None = None
    """The robot's wheel odometry at the scan (:mod:`fleetmap.scenarios.odometry`); None if it
    has none."""


def scan_rng(seed: int, robot_id: str, index: int) -> np.random.Generator:
    """The generator of one scan's noise, independent of every other scan's."""
    return np.random.default_rng([seed, zlib.crc32(robot_id.encode("utf-8")), index])


def simulate(scenario: Scenario, planned: PlannedScan) -> SimulatedScan:
    """The scan of one planned pose (deterministic)."""
    p = scenario.laser
    pose = planned.pose
    r, _ = true_ranges(scenario.world.walls, (pose.x, pose.y, pose.theta), p)
    r = noisy_ranges(r, p, scan_rng(scenario.seed, planned.robot, planned.index))
    scan = RangeScan(planned.stamp, -p.fov / 2.0, p.resolution, p.max_range, r)
    return SimulatedScan(planned.robot, planned.index, planned.stamp, pose, planned.leg, scan)


def robot_stream(scenario: Scenario, robot_id: str, start_index: int = 0) -> Iterator[SimulatedScan]:
    """The scans of one robot, in order, from scan ``start_index`` on, with its odometry.

    The stream ends when the robot's path ends or it leaves or crashes (the live runner stops the
    process); a kidnap shows only as a jump in the (true) poses, and not in the odometry.
    """
    planned = plan(scenario, robot_id)
    odometry = simulate_odometry(planned, scenario.odometry, scenario.seed, robot_id)
    for p, odom in zip(planned[start_index:], odometry[start_index:], strict=True):
        yield replace(simulate(scenario, p), odometry=odom)


class ScenarioSource:
    """The scans of one robot of a scenario (bundled name, file, or a loaded Scenario), as a
    :class:`~fleetmap.shared.io.sources.ScanSource`: what ``fleetmap agent --scenario`` plugs into
    an agent. A robot the scenario does not have is :class:`~fleetmap.shared.errors.BadInput`."""

    def __init__(self, scenario: str | Path | Scenario, robot: str) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        if robot not in self.scenario.robot_ids:
            raise BadInput(
                f"robot {robot!r}",
                f"not in scenario {self.scenario.name!r} (its robots: {', '.join(self.scenario.robot_ids)})",
            )
        self.robot = robot
        self.name = f"scenario {self.scenario.name}, robot {robot}"
        self.has_odometry = self.scenario.odometry.enabled

    def __iter__(self) -> Iterator[SourceScan]:
        for simulated in robot_stream(self.scenario, self.robot):
            # simulated.pose is the ground truth: it stays here
            yield checked_scan(self.name, simulated.index, simulated.stamp, simulated.scan, simulated.odometry)
