"""Simulated buildings, a laser simulator, fleets with events, and ground-truth scoring.

- :mod:`~fleetmap.scenarios.worlds`: floor plans (walls as ``(n, 4)`` arrays) by name.
- :mod:`~fleetmap.scenarios.laser`: the SICK LMS 200-like laser of the paper's Section V.
- :mod:`~fleetmap.scenarios.fleet`: robots, events, and the plan of every robot's scans.
- :mod:`~fleetmap.scenarios.loader`: scenario files (TOML), validated; the bundled scenarios.
- :mod:`~fleetmap.scenarios.stream`: a robot's scans as a live agent receives them.
- :mod:`~fleetmap.scenarios.truth` and :mod:`~fleetmap.scenarios.metrics`: ground truth and scores.
"""

from fleetmap.scenarios.fleet import (
    Crash,
    Event,
    Join,
    Kidnap,
    Leave,
    MergerRestart,
    PlannedScan,
    RobotSpec,
    Scenario,
    plan,
    scenario_end,
)
from fleetmap.scenarios.laser import LaserParams, simulate_scan
from fleetmap.scenarios.loader import DEFAULT_SCENARIO, list_scenarios, load_scenario, scenario_to_toml
from fleetmap.scenarios.metrics import (
    MapError,
    MapScore,
    PoseError,
    coverage,
    map_error,
    pose_error,
    pose_errors,
    score_map,
    visible_walls,
    world_from_global,
)
from fleetmap.scenarios.stream import SimulatedScan, robot_stream
from fleetmap.scenarios.truth import GroundTruth, ground_truth
from fleetmap.scenarios.worlds import WORLDS, World, get_world

__all__ = [
    "DEFAULT_SCENARIO",
    "WORLDS",
    "Crash",
    "Event",
    "GroundTruth",
    "Join",
    "Kidnap",
    "LaserParams",
    "Leave",
    "MapError",
    "MapScore",
    "MergerRestart",
    "PlannedScan",
    "PoseError",
    "RobotSpec",
    "Scenario",
    "SimulatedScan",
    "World",
    "coverage",
    "get_world",
    "ground_truth",
    "list_scenarios",
    "load_scenario",
    "map_error",
    "plan",
    "pose_error",
    "pose_errors",
    "robot_stream",
    "scenario_end",
    "scenario_to_toml",
    "score_map",
    "simulate_scan",
    "visible_walls",
    "world_from_global",
]
