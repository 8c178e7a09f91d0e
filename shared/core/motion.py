"""Where a robot's next scan should be: odometry or constant velocity, with an uncertainty (pure).

The prediction starts the registration (:func:`fleetmap.shared.core.tracking.register`) and is its
prior: where the walls fix the pose it barely counts, where they leave a direction free (along a
featureless corridor) it decides that direction. Its uncertainty is a motion model's:

- **odometry**: the increment the wheels measured between the two scans, uncertain by a floor
  plus a share of the distance driven and of the turn;
- **constant velocity**: the robot keeps its last tracked velocity; uncertain by a floor plus how
  far a robot can speed up or brake (and start or stop turning) in the time between the scans.

A source's odometry that jumps farther than the robot can drive between two scans, or is not a
number, is not a measurement: :func:`odometry_increment` says so, and the tracker falls back to
constant velocity for that scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D


@dataclass(frozen=True)
class Prediction:
    """The next scan's pose, in the frame of the previous one's, and how sure that is."""

    increment: Transform2D
    """The motion since the previous scan, in the previous scan's laser frame."""
    sigma_translation: float
    """Standard deviation (m) of the increment's translation, the same in every direction."""
    sigma_rotation: float
    """Standard deviation (rad) of its rotation."""
    source: str
    """"odometry" or "velocity"."""

    def information(self) -> Array:
        """The inverse covariance over (x, y, theta)."""
        t = 1.0 / self.sigma_translation**2
        return np.diag([t, t, 1.0 / self.sigma_rotation**2])


def odometry_increment(
    previous: Transform2D | None, current: Transform2D | None, seconds: float, max_speed: float
) -> tuple[Transform2D | None, str | None]:
    """The laser's motion between two odometry readings, in the earlier one's frame, or None with
    the reason it is not a measurement (missing, not finite, or farther than ``max_speed`` allows
    in ``seconds``, plus a metre: a reset or a jump)."""
    if previous is None or current is None:
        return None, "no odometry"
    values = (*previous.as_array(), *current.as_array())
    if not all(math.isfinite(v) for v in values):
        return None, "odometry is not a finite number"
    increment = previous.inverse().compose(current)
    distance = math.hypot(increment.x, increment.y)
    if max_speed > 0 and seconds > 0 and distance > max_speed * seconds + 1.0:
        return None, f"odometry jumped {distance:.2f} m in {seconds:.2f} s"
    return increment, None


def from_odometry(increment: Transform2D, params: TrackingParams) -> Prediction:
    """The odometry's increment as a prediction (see the module docstring)."""
    distance = math.hypot(increment.x, increment.y)
    turn = abs(increment.theta)
    return Prediction(
        increment,
        params.odometry_translation_sigma + params.odometry_translation_rate * distance,
        params.odometry_rotation_sigma + params.odometry_rotation_rate * turn,
        "odometry",
    )


def from_velocity(velocity: Array, seconds: float, params: TrackingParams, max_acceleration: float) -> Prediction:
    """Constant velocity ``(vx, vy, omega)`` (in the laser's frame, per second) over ``seconds``
    as a prediction (see the module docstring)."""
    dt = max(seconds, 0.0)
    v = np.asarray(velocity, dtype=np.float64) * dt
    return Prediction(
        Transform2D(float(v[0]), float(v[1]), float(v[2])),
        params.velocity_translation_sigma + 0.5 * max_acceleration * dt * dt,
        params.velocity_rotation_sigma + 0.5 * params.max_angular_acceleration * dt * dt,
        "velocity",
    )


def velocity_between(a: Transform2D, b: Transform2D, seconds: float) -> Array:
    """The constant velocity (in a's frame, per second) that takes pose ``a`` to pose ``b``."""
    step = a.inverse().compose(b)
    if seconds <= 0:
        return np.zeros(3)
    return np.array([step.x, step.y, step.theta]) / seconds
