"""A range scan: one laser sweep in the laser's frame (x forward, y left).

Beam i points at ``angle_min + i * angle_increment``. A range that is not finite, is <= 0 or is
>= ``range_max`` is "no return". The pose a log may carry (``odom``) is kept for benchmarks only;
the algorithms never read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from fleetmap.shared.core.geometry import Array


@dataclass(frozen=True)
class RangeScan:
    stamp: float
    angle_min: float
    angle_increment: float
    range_max: float
    ranges: Array
    odom: tuple[float, float, float] | None = None
    """The pose written on the log line (odometry or SLAM-corrected): never used by the algorithms
    (benchmarks score against it where it is a corrected pose)."""
    odometry: tuple[float, float, float] | None = None
    """The robot's odometry written on the log line (FLASER/RLASER: its odom_x, odom_y,
    odom_theta; ROBOTLASER1: the laser's pose by odometry), for a source that has no ODOM lines."""

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "stamp": self.stamp,
            "angle_min": self.angle_min,
            "angle_increment": self.angle_increment,
            "range_max": self.range_max,
            "ranges": [float(r) if math.isfinite(r) else None for r in self.ranges],
        }
