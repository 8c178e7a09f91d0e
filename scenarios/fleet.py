"""A simulated fleet: robots that follow waypoints and scan at fixed spacing, and timed events.

A robot drives its path (waypoints in the world frame) at ``spacing / period`` metres per second
and takes a scan every ``period`` scenario seconds from its ``start``; its laser looks along the
path (the heading of the leg it is on). At a waypoint it turns on the spot to the next leg's
heading at ``turn_rate`` radians per second, scanning as it turns (``turn_rate`` 0: it faces the
next leg at once, between two scans). Events change that plan:

- ``join``: the robot starts at ``t`` (a late join); its first scan is at ``t``.
- ``leave`` / ``crash``: the robot takes no scan at or after ``t`` (a clean exit / killed).
- ``kidnap``: from the first scan slot at or after ``t`` the robot is at ``pose`` (teleported,
  facing ``pose.theta``) and then follows the kidnap's own waypoints.
- ``merger_restart``: the merger is killed at ``t`` and started again ``down_for`` seconds later
  (no effect on the robots).

Everything here is pure: the plan of a robot (:func:`plan_robot`) is a function of its spec and
its events, so every run of a scenario drives the same poses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from fleetmap.scenarios.laser import LaserParams
from fleetmap.scenarios.odometry import OdometryParams
from fleetmap.scenarios.worlds import World
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle

Point = tuple[float, float]


@dataclass(frozen=True)
class RobotSpec:
    """One robot of a scenario."""

    id: str
    path: tuple[Point, ...]
    """Waypoints in the world frame (m); the robot drives straight from one to the next."""
    spacing: float
    """Path length between consecutive scans (m)."""
    period: float
    """Scenario seconds between consecutive scans."""
    start: float = 0.0
    """Scenario time of the first scan (s); a join event's time when there is one."""
    turn_rate: float = 0.0
    """How fast (rad/s) the robot turns on the spot at a waypoint; 0: at once, between two scans."""


@dataclass(frozen=True)
class RobotEventBase:
    t: float
    """Scenario seconds."""
    robot: str


@dataclass(frozen=True)
class Join(RobotEventBase):
    kind: ClassVar[str] = "join"


@dataclass(frozen=True)
class Leave(RobotEventBase):
    kind: ClassVar[str] = "leave"


@dataclass(frozen=True)
class Crash(RobotEventBase):
    kind: ClassVar[str] = "crash"


@dataclass(frozen=True)
class Kidnap(RobotEventBase):
    pose: Transform2D
    """Where the robot is put down (world frame), facing ``pose.theta``."""
    path: tuple[Point, ...]
    """The waypoints it follows from there."""
    kind: ClassVar[str] = "kidnap"


@dataclass(frozen=True)
class MergerRestart:
    t: float
    down_for: float
    """Seconds between the merger's death and its restart."""
    kind: ClassVar[str] = "merger_restart"


RobotEvent = Join | Leave | Crash | Kidnap
Event = RobotEvent | MergerRestart
EVENT_KINDS: tuple[str, ...] = ("join", "leave", "crash", "kidnap", "merger_restart")


@dataclass(frozen=True)
class Scenario:
    """A world, a laser, robots and timed events (see :mod:`fleetmap.scenarios.loader` for the file)."""

    name: str
    description: str
    world: World
    seed: int
    """Seeds the laser noise: every run of the scenario gives the same scans."""
    laser: LaserParams
    robots: tuple[RobotSpec, ...]
    events: tuple[Event, ...]
    """Sorted by time (file order among equal times)."""
    source: str = ""
    """The file the scenario came from."""
    odometry: OdometryParams = field(default_factory=OdometryParams)
    """The robots' wheel odometry (:mod:`fleetmap.scenarios.odometry`)."""

    @property
    def robot_ids(self) -> tuple[str, ...]:
        return tuple(r.id for r in self.robots)

    def robot(self, robot_id: str) -> RobotSpec:
        for r in self.robots:
            if r.id == robot_id:
                return r
        raise KeyError(f"scenario {self.name!r} has no robot {robot_id!r} (robots: {', '.join(self.robot_ids)})")

    def robot_events(self, robot_id: str) -> tuple[RobotEvent, ...]:
        return tuple(e for e in self.events if not isinstance(e, MergerRestart) and e.robot == robot_id)

    def kidnaps(self) -> tuple[Kidnap, ...]:
        return tuple(e for e in self.events if isinstance(e, Kidnap))


@dataclass(frozen=True)
class PlannedScan:
    """Where and when a robot takes one scan: ground truth, never sent to the algorithms."""

    robot: str
    index: int
    """Scans of the robot are numbered 0, 1, 2, ... across kidnaps."""
    stamp: float
    """Scenario seconds."""
    pose: Transform2D
    """The true laser pose in the world frame."""
    leg: int
    """0 before the robot's first kidnap, k after its k-th."""


@dataclass(frozen=True)
class PathSamples:
    """Scan poses along a path: ``poses`` ``(m, 3)`` and the path leg each one is on ``(m,)``."""

    poses: Array
    legs: Array


def sample_path(path: Sequence[Point], spacing: float, heading: float | None = None) -> PathSamples:
    """Poses every ``spacing`` metres along ``path`` (first waypoint included), facing along the leg.

    ``heading`` replaces the direction of the first pose (a kidnapped robot is put down facing
    anywhere).
    """
    pts = np.asarray(path, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 1:
        return PathSamples(np.array([[pts[0, 0], pts[0, 1], heading or 0.0]]), np.zeros(1, np.int64))
    steps = np.diff(pts, axis=0)
    leg_len = np.hypot(steps[:, 0], steps[:, 1])
    ends = np.cumsum(leg_len)
    s = np.arange(math.floor(float(ends[-1]) / spacing + 1e-9) + 1) * spacing
    legs = np.minimum(np.searchsorted(ends, s, side="right"), len(leg_len) - 1)
    before = ends[legs] - leg_len[legs]
    frac = np.clip((s - before) / leg_len[legs], 0.0, 1.0)
    xy = pts[legs] + steps[legs] * frac[:, None]
    theta = np.arctan2(steps[legs, 1], steps[legs, 0])
    if heading is not None:
        theta[0] = heading
    return PathSamples(np.column_stack([xy, wrap_angle(theta)]), legs)


def sample_motion(
    path: Sequence[Point], spacing: float, period: float, turn_rate: float, heading: float | None = None
) -> PathSamples:
    """Poses every ``period`` seconds of a robot driving ``path`` at ``spacing / period`` m/s and
    turning on the spot at each waypoint at ``turn_rate`` rad/s (:func:`sample_path` when it is 0).

    It starts facing ``heading`` (the first leg's direction when None) and first turns to the first
    leg; a sample turning at waypoint i belongs to leg i (the leg it turns to).
    """
    if turn_rate <= 0:
        return sample_path(path, spacing, heading)
    pts = np.asarray(path, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 1:
        return PathSamples(np.array([[pts[0, 0], pts[0, 1], heading or 0.0]]), np.zeros(1, np.int64))
    speed = spacing / period
    steps = np.diff(pts, axis=0)
    leg_len = np.hypot(steps[:, 0], steps[:, 1])
    leg_heading = np.arctan2(steps[:, 1], steps[:, 0])
    facing = float(leg_heading[0] if heading is None else heading)
    # phases: (start time, duration, leg, kind, start heading, turn) with kind 0 = turn, 1 = drive
    phases: list[tuple[float, float, int, int, float, float]] = []
    t = 0.0
    for i in range(len(leg_len)):
        turn = float(wrap_angle(leg_heading[i] - facing))
        if abs(turn) > 1e-9:
            phases.append((t, abs(turn) / turn_rate, i, 0, facing, turn))
            t += abs(turn) / turn_rate
        phases.append((t, float(leg_len[i]) / speed, i, 1, float(leg_heading[i]), 0.0))
        t += float(leg_len[i]) / speed
        facing = float(leg_heading[i])
    times = np.arange(math.floor(t / period + 1e-9) + 1) * period
    starts = np.array([ph[0] for ph in phases])
    poses = np.empty((len(times), 3))
    legs = np.empty(len(times), dtype=np.int64)
    for k, tk in enumerate(times):
        j = max(int(np.searchsorted(starts, tk, side="right")) - 1, 0)
        t0, duration, leg, kind, h0, turn = phases[j]
        f = min(max((tk - t0) / duration, 0.0), 1.0) if duration > 0 else 1.0
        if kind == 0:
            poses[k] = (pts[leg, 0], pts[leg, 1], h0 + turn * f)
        else:
            xy = pts[leg] + steps[leg] * f
            poses[k] = (xy[0], xy[1], h0)
        legs[k] = leg
    poses[:, 2] = wrap_angle(poses[:, 2])
    return PathSamples(poses, legs)


def plan_robot(robot: RobotSpec, events: Sequence[RobotEvent]) -> list[PlannedScan]:
    """Every scan the robot takes, in order: its path cut by its events (see the module docstring)."""
    start = next((e.t for e in events if isinstance(e, Join)), robot.start)
    end = min((e.t for e in events if isinstance(e, (Leave, Crash))), default=math.inf)
    kidnaps = sorted((e for e in events if isinstance(e, Kidnap)), key=lambda e: e.t)
    samples = sample_motion(robot.path, robot.spacing, robot.period, robot.turn_rate).poses
    out: list[PlannedScan] = []
    leg, j, k = 0, 0, 0
    while True:
        stamp = start + k * robot.period
        if stamp >= end - 1e-9:
            break
        if leg < len(kidnaps) and stamp >= kidnaps[leg].t - 1e-9:
            kid = kidnaps[leg]
            waypoints = ((kid.pose.x, kid.pose.y), *kid.path)
            samples = sample_motion(waypoints, robot.spacing, robot.period, robot.turn_rate, kid.pose.theta).poses
            leg, j = leg + 1, 0
        if j >= len(samples):
            break
        x, y, theta = samples[j]
        out.append(PlannedScan(robot.id, k, stamp, Transform2D(float(x), float(y), float(theta)), leg))
        j += 1
        k += 1
    return out


def plan(scenario: Scenario, robot_id: str) -> list[PlannedScan]:
    """The scans of one robot of ``scenario``."""
    return plan_robot(scenario.robot(robot_id), scenario.robot_events(robot_id))


def scenario_end(scenario: Scenario) -> float:
    """The scenario time when the last robot has taken its last scan and every event has happened."""
    last = [p[-1].stamp for r in scenario.robots if (p := plan(scenario, r.id))]
    for e in scenario.events:
        last.append(e.t + e.down_for if isinstance(e, MergerRestart) else e.t)
    return max(last, default=0.0)
