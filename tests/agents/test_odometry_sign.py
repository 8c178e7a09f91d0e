"""The odometry's sign judged from the motion the walls placed the scans with
(:meth:`fleetmap.agents.prediction.Predictor.judge_odometry_sign`): a robot's stops say how likely a
stop is to turn it (docs/decisions/009-clocks-evidence-over-stamps.md)."""

from __future__ import annotations

from fleetmap.agents.prediction import Predictor
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.motion import from_odometry

STEP = 0.1
"""The odometry's increment while the robot drives (m a scan)."""
WEAK = Transform2D(-0.02, 0.0, 0.0)
"""A placed step the negated odometry explains about three times as well as the odometry (a
ratio of 3, as robot 3 of aces cut in 4 met after a stop)."""


def _step(p: Predictor, odometry: float, moved: float) -> None:
    p.odometry_step = from_odometry(Transform2D(odometry, 0.0, 0.0))
    p.judge_odometry_sign(Transform2D(moved, 0.0, 0.0))


def _drive(p: Predictor, stops: int, reverse_at_stops: bool) -> None:
    """Drive and stop ``stops`` times, the robot going the other way after every stop when
    ``reverse_at_stops`` (its odometry adding up the speed without its sign, always forward)."""
    direction = 1.0
    for _ in range(stops):
        for _ in range(5):
            _step(p, STEP, direction * STEP)
        _step(p, 0.0, 0.0)
        if reverse_at_stops:
            direction = -direction


def _weak_step_after_a_stop(p: Predictor) -> float:
    p.odometry_step = from_odometry(Transform2D(STEP, 0.0, 0.0))
    p.judge_odometry_sign(WEAK)
    return p.reversed_odometry


def test_a_robot_whose_stops_never_turned_its_sign_keeps_it_on_weak_evidence_after_a_stop() -> None:
    p = Predictor(FleetmapConfig())
    _drive(p, 6, reverse_at_stops=False)
    assert _weak_step_after_a_stop(p) < 0.5  # the odometry's prediction is not negated


def test_a_robot_that_reversed_at_every_stop_expects_to_reverse_at_the_next() -> None:
    p = Predictor(FleetmapConfig())
    _drive(p, 5, reverse_at_stops=True)  # drove forward since its fourth stop, now stopped
    assert p.reversed_odometry > 0.5  # its unsigned odometry's forward is now likely backward
    assert _weak_step_after_a_stop(p) > 0.5


def test_at_a_robots_first_stop_either_sign_is_as_likely() -> None:
    p = Predictor(FleetmapConfig())
    _drive(p, 1, reverse_at_stops=False)
    assert p.reversed_odometry == 0.5
    assert _weak_step_after_a_stop(p) > 0.5
