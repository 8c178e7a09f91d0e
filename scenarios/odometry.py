"""Simulated wheel odometry: it drifts, and it does not see a robot being carried.

A robot's odometry integrates its wheels' measurement of each step between two scans (in the
robot's own frame): the step's distance off by ``translation_error`` (a systematic share: a
wheel's radius a little off) plus random noise, its turn off by ``rotation_error`` per metre
driven (a systematic drift: one wheel a little larger than the other) plus random noise in
proportion to the turn and the distance. The signs of the systematic errors are drawn per robot.
A kidnapped robot's wheels do not turn while it is carried: its odometry reads no motion across
the kidnap, and then goes on from there.

Everything is seeded by the scenario's seed and the robot's id: every run gives the same odometry.
"""

from __future__ import annotations

import itertools
import math
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from fleetmap.shared.core.geometry import Transform2D

if TYPE_CHECKING:
    from fleetmap.scenarios.fleet import PlannedScan


@dataclass(frozen=True)
class OdometryParams:
    """The robots' wheel odometry (the scenario file's ``[odometry]`` table)."""

    enabled: bool = True
    """False: the robots have no odometry (constant velocity only)."""
    translation_error: float = 0.03
    """Systematic share of each step's distance (3 %: a wheel's radius off by that much)."""
    rotation_error: float = math.radians(1.5)
    """Systematic drift of heading per metre driven (rad/m; 1.5 degrees per metre)."""
    noise: float = 0.01
    """Random error of each step: this share of its distance and of its turn, and this many
    radians per metre driven (standard deviations)."""


def simulate_odometry(
    scans: list[PlannedScan], params: OdometryParams, seed: int, robot: str
) -> list[Transform2D | None]:
    """The odometry pose at each of a robot's planned scans (None for all if disabled)."""
    if not params.enabled or not scans:
        return [None] * len(scans)
    rng = np.random.default_rng([seed, zlib.crc32(robot.encode("utf-8")), 0x0D0])
    scale_sign, drift_sign = (float(v) for v in rng.choice([-1.0, 1.0], size=2))
    scale = 1.0 + scale_sign * params.translation_error
    drift = drift_sign * params.rotation_error
    out: list[Transform2D | None] = [Transform2D()]
    odom = Transform2D()
    for before, after in itertools.pairwise(scans):
        if after.leg != before.leg:
            out.append(odom)  # carried: the wheels did not turn
            continue
        step = before.pose.inverse().compose(after.pose)
        distance = math.hypot(step.x, step.y)
        n = [float(v) for v in rng.normal(0.0, params.noise, size=3)]
        factor = scale + n[0]
        turn = step.theta * (1.0 + n[1]) + (drift + n[2]) * distance
        odom = odom.compose(Transform2D(step.x * factor, step.y * factor, turn))
        out.append(odom)
    return out
