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

import bisect
import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle

ODOMETRY_TRANSLATION_SIGMA = 0.05
"""Odometry's uncertainty per scan step: this (m) ..."""
ODOMETRY_TRANSLATION_RATE = 0.1
"""... plus this share of the distance driven ..."""
ODOMETRY_ROTATION_SIGMA = 0.087
"""... and this (rad, 5 degrees) ..."""
ODOMETRY_ROTATION_RATE = 0.5
"""... plus this share of the turn: deliberately loose, real robots' odometry is off by 10-25 degrees
on single fast turns (mit-csail), and where the walls fix the pose they decide
(docs/decisions/005-parameters-beyond-the-paper.md)."""
VELOCITY_TRANSLATION_SIGMA = 0.05
"""Constant velocity's uncertainty per scan step: this (m) plus ``max_acceleration`` dt^2 / 2 ..."""
VELOCITY_ROTATION_SIGMA = 0.087
"""... and this (rad, 5 degrees) plus :data:`MAX_ANGULAR_ACCELERATION` dt^2 / 2."""
MAX_ANGULAR_ACCELERATION = 6.0
"""The hardest a robot starts or stops turning (rad/s^2): it reaches mit-csail's 90 degrees a second
on a fast turn (docs/decisions/001-tracking-front-end.md) in a quarter of a second."""


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

    def distance2(self, predicted: Transform2D, placed: Transform2D) -> float:
        """The squared Mahalanobis distance of ``placed`` from where this prediction put the scan,
        ``predicted`` (both in one frame), under its uncertainty."""
        off = predicted.inverse().compose(placed).as_array()
        off[2] = float(wrap_angle(off[2]))
        return float(off @ self.information() @ off)


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


def from_odometry(increment: Transform2D) -> Prediction:
    """The odometry's increment as a prediction (see the module docstring)."""
    distance = math.hypot(increment.x, increment.y)
    turn = abs(increment.theta)
    return Prediction(
        increment,
        ODOMETRY_TRANSLATION_SIGMA + ODOMETRY_TRANSLATION_RATE * distance,
        ODOMETRY_ROTATION_SIGMA + ODOMETRY_ROTATION_RATE * turn,
        "odometry",
    )


def from_velocity(velocity: Array, seconds: float, max_acceleration: float) -> Prediction:
    """Constant velocity ``(vx, vy, omega)`` (in the laser's frame, per second) over ``seconds``
    as a prediction (see the module docstring)."""
    dt = max(seconds, 0.0)
    v = np.asarray(velocity, dtype=np.float64) * dt
    return Prediction(
        Transform2D(float(v[0]), float(v[1]), float(v[2])),
        VELOCITY_TRANSLATION_SIGMA + 0.5 * max_acceleration * dt * dt,
        VELOCITY_ROTATION_SIGMA + 0.5 * MAX_ANGULAR_ACCELERATION * dt * dt,
        "velocity",
    )


def velocity_between(a: Transform2D, b: Transform2D, seconds: float) -> Array:
    """The constant velocity (in a's frame, per second) that takes pose ``a`` to pose ``b``."""
    step = a.inverse().compose(b)
    if seconds <= 0:
        return np.zeros(3)
    return np.array([step.x, step.y, step.theta]) / seconds


CHI2_1DOF_99 = 6.635
"""The chi-square bound of one degree of freedom at 99 %: how far (in standard deviations, squared)
a registered motion may lie beyond what the robot can drive before it says the clock is wrong."""

CHI2_3DOF_99 = 11.345
"""The chi-square bound of three degrees of freedom at 99 %: an SE(2) increment's squared
Mahalanobis distance past which its prediction does not explain it (the validation gate)."""


UNORDERED_KEPT = 4096
"""The scans with a stamp that is not their time a clock remembers (:attr:`ScanClock.unordered`): the
intervals it is asked about end at the scans being tracked, so one reaching back past the oldest
kept holds the newer ones and is untimed by them. A bound for a robot that runs for days, not a
figure (minutes of a log in bursts at 40 Hz; any span longer than a robot's unplaced run holds)."""


class ScanClock:
    """How much time passed between a robot's scans, as the evidence supports it.

    A log's stamps are not always the scans' times: a logger stamps a burst of scans at receipt a
    few milliseconds apart, a driver repeats a stamp, stamps jitter with the host's load. The
    robot's motion is the evidence: a scan registered half a metre from the last one 2 ms later,
    or at the same stamp, says the clock is wrong, not the robot (no robot drives that fast).

    While the stamps agree with the motion, the time between two scans is their stamps'
    difference. A stamp that repeats or goes back, or a scan that arrived in a burst stamped
    together, is not its scan's time: the intervals it bounds are timed by the sequence, the rest
    of the log by its stamps (:meth:`times`; docs/decisions/078). From the first scan whose
    registered motion no ordinary robot can have driven in its stamps' interval (beyond
    ``max_speed``, by more than the registration's own uncertainty at 99 %), the stamps are not
    trusted for the rest of the log. An untimed interval is the number of scans in it times the
    log's mean scan period (its whole span over its scans, which bursts, jitter and repeats do not
    change).
    A laser scans at a steady rate; its sequence is the clock a burst cannot break. A log whose
    stamps never advance has a period of one "second" per scan: the motion models then run per
    scan. It takes two steps to measure a rate: stamps that advanced once only are a reset, a
    wrap or a stamp printed coarser than the log runs (csail-corrected's six digits, 1.13486e9,
    step once by 1e4 s in 406 scans; infinite-corridor-corrected's go back for four scans, then
    wrap to 4.29e9 s, a period of 2.2 million seconds), and time nothing either.
    """

    def __init__(self, max_speed: float) -> None:
        self.max_speed = max_speed
        self.scans = 0
        """Scans seen (:meth:`tick`)."""
        self.first: float | None = None
        self.latest: float | None = None
        self.previous: float | None = None
        self.advances = 0
        """Stamps after the previous scan's."""
        self.trusted = True
        """Whether the stamps have agreed with the motion so far."""
        self.repeated = 0
        """Stamps equal to the previous scan's."""
        self.backwards = 0
        """Stamps before the previous scan's."""
        self.too_fast = 0
        """Intervals over which the registered motion is farther than ``max_speed`` allows."""
        self.before_first = 0
        """Scans taken before the first stamp: a burst's first scans, stamped when it arrived."""
        self.distrusted_at: int | None = None
        """The scan (count from 1) from which no stamp times its interval: the motion showed them
        wrong (:meth:`check`), or a kidnap only they concluded (:meth:`distrust`)."""
        self.unordered: list[int] = []
        """The scans (count from 1, ascending) whose stamps are not their times: stamps that
        repeated or went back, and scans that arrived in a burst (:meth:`bunched`); the latest
        :data:`UNORDERED_KEPT` of them."""
        self.bunches = 0
        """Scans that arrived in a burst (:meth:`bunched`)."""
        self.untimed = 0
        """Scans whose stamps were not their times (:attr:`unordered`, all of them)."""
        self.first_untimed: int | None = None
        """The first of them (count from 1)."""
        self.said = False
        """Whether the log was told that some of its stamps are not its scans' times
        (:func:`fleetmap.agents.clock_evidence.say_untimed`)."""

    def tick(self, stamp: float) -> None:
        """A scan with ``stamp`` arrived (every scan, placed or not)."""
        self.scans += 1
        if self.previous is not None and stamp <= self.previous:
            # no laser takes two scans at one instant, or one before the other it took first
            if stamp == self.previous:
                self.repeated += 1
            else:
                self.backwards += 1
            self._unordered(self.scans)
        elif self.previous is not None:
            self.advances += 1
        self.first = stamp if self.first is None else min(self.first, stamp)
        self.latest = stamp if self.latest is None else max(self.latest, stamp)
        self.previous = stamp

    @property
    def period(self) -> float:
        """The log's mean time between scans (s); 1.0 where the stamps have not advanced twice."""
        periods = self.scans - 1 - self.before_first
        if periods < 1 or self.first is None or self.latest is None or self.advances < 2:
            return 1.0
        return (self.latest - self.first) / periods

    def times(self, scans: int, end: int | None = None) -> bool:
        """Whether the stamps time the interval of ``scans`` scans that ends at scan ``end`` (count
        from 1; the latest by default): they agree with the motion so far, and neither end nor any
        scan between is in :attr:`unordered` (a stamp that repeated or went back is wrong, or the
        one before it is; a burst's scans were stamped as they arrived: both intervals such a scan
        bounds are untimed, not the rest of the log)."""
        if not self.trusted:
            return False
        if not self.unordered:
            return True
        end = self.scans if end is None else end
        k = bisect.bisect_left(self.unordered, end - max(scans, 1))
        return k == len(self.unordered) or self.unordered[k] > end

    def _unordered(self, scan: int) -> None:
        """Scan ``scan``'s stamp is not its time (:attr:`unordered`)."""
        if self.unordered and self.unordered[-1] >= scan:
            return
        self.unordered.append(scan)
        self.untimed += 1
        self.first_untimed = scan if self.first_untimed is None else self.first_untimed
        if len(self.unordered) > UNORDERED_KEPT:
            del self.unordered[0]

    def elapsed(self, seconds: float, scans: int, end: int | None = None) -> float:
        """The time (s) between two scans ``scans`` apart whose stamps are ``seconds`` apart, the
        later one scan ``end`` (:meth:`times`)."""
        if seconds > 0 and self.times(scans, end):
            return seconds
        return max(scans, 1) * self.period

    def check(self, seconds: float, distance: float, sigma: float) -> bool:
        """Judge the stamps by a registered motion: ``distance`` metres (uncertain by ``sigma``)
        between two placed scans stamped ``seconds`` apart. False (and the clock distrusted from
        now on) when no robot drives that far in that time."""
        if self.max_speed <= 0:
            return self.trusted
        excess = distance - self.max_speed * max(seconds, 0.0)
        if excess > 0 and excess * excess > CHI2_1DOF_99 * sigma * sigma:
            self.too_fast += 1
            self.distrust()
        return self.trusted

    def bunched(self, size: int) -> None:
        """The next scan (the one :meth:`tick` counts next) arrived in a burst of ``size`` scans
        the laser took apart and the logger stamped together (:mod:`fleetmap.agents.bursts`): its
        stamp is not its time, so neither interval it bounds is timed by the stamps
        (:meth:`times`), and the rest of the log keeps its clock. A burst before the first scan was
        taken before the first stamp: the log's span leaves it out (:attr:`period`)."""
        if self.scans == 0:
            self.before_first = size - 1
        self.bunches += 1
        self._unordered(self.scans + 1)

    def distrust(self) -> None:
        """Trust the stamps no more: the evidence is :meth:`check`'s, or the caller's (a kidnap
        that only the stamps' time concluded)."""
        if self.trusted:
            self.trusted = False
            self.distrusted_at = self.scans


def fused(a: Prediction, b: Prediction) -> Prediction:
    """Two predictions of one increment combined by their information (the product of their
    Gaussians): where one drifts and the other does not, the other holds it."""
    ia, ib = a.information().diagonal(), b.information().diagonal()
    xa, xb = a.increment.as_array(), b.increment.as_array()
    xb = xb.copy()
    xb[2] = xa[2] + math.remainder(xb[2] - xa[2], math.tau)
    x = (ia * xa + ib * xb) / (ia + ib)
    info = ia + ib
    return Prediction(
        Transform2D(float(x[0]), float(x[1]), math.remainder(float(x[2]), math.tau)),
        1.0 / math.sqrt(info[0]),
        1.0 / math.sqrt(info[2]),
        f"{a.source}+{b.source}",
    )
