"""Scans that arrived in a burst, and the odometry where each was taken (issue 48; pure, no clock).

A logger that writes what arrives stamps a burst of scans at receipt, milliseconds apart, although
the laser took them a period apart; where the odometry is read at the scan's stamp (a CARMEN logger
interpolates it there, a ROS driver looks it up in tf at the header's stamp) every scan of the
burst reads where the robot was when the burst arrived, just after its last scan. Taken at its
word, that reading puts the burst's first scan where its last one was (a metre or more ahead on a
sparse log) and says the others did not move.

The evidence is in the stamps and readings themselves: two readings taken closer together than
the robot can drive ``ODOMETRY_TRANSLATION_SIGMA`` (at ``max_speed``) cannot differ by more than
the odometry's own noise, so a scan stamped that close after its burst's first, its reading within
that noise of the first's, brought no new reading: it is in the same burst.
:class:`BurstOdometry` holds a burst's scans until a scan with a new reading ends it. Then
the burst's reading belongs to one of its scans, its *owner*: the one whose place in the sequence
makes the robot's drive per scan since the last owner nearest its recent pace
(:meth:`BurstOdometry._owner`). A logger that stamps at receipt reads where the robot was at the
burst's last scan; a driver that repeats a stamp reads, for the repeated scan, where the one
before it was (docs/decisions/025-a-readings-owner-by-the-robots-pace.md). The scans between two
owners are spread evenly, in order, along the arc a robot drives between their readings at
constant speed and turn rate (:func:`between`; a laser scans at a steady rate, and a log thinned
by distance keeps a scan every so many metres); those after a burst's owner wait for the next
reading. Each scan given back says whether its reading is its own (``Timed.exact``): the tracker
predicts such a scan from the last one that was.

Until a log shows its first burst only its first scan waits (for the second, which says whether
they arrived together), so a robot whose stamps are its scans' times is tracked as it comes; from
then on each scan waits for the next one (live, for the next burst, which arrives together
anyway). The log's first burst has no reading before it: it waits for the next one, and its
scans but the last are placed back from its reading at the next burst's pace. A first burst
that begins with a scan already given back (its reading as its own) owes that scan its reading:
the rest of it waits for the next one (docs/decisions/058).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Generic, TypeVar

import gtsam
import numpy as np
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.motion import ODOMETRY_ROTATION_SIGMA, ODOMETRY_TRANSLATION_SIGMA

log = logging.getLogger(__name__)

PACES = 50
"""The recent steps between readings one scan apart whose spread is the robot's pace per scan
(:meth:`BurstOdometry._owner`): a minute of a sparse log, seconds of a dense one, and bounded for a
robot that runs for days. Repeat clock over five draws, aces-c: 10 steps 84.0 %, 50 84.7 %, all of
them 85.0 % (docs/decisions/025-a-readings-owner-by-the-robots-pace.md)."""

T = TypeVar("T")


@dataclass(frozen=True)
class Timed(Generic[T]):
    """A scan (whatever the caller tracks) with its stamp and odometry reading."""

    item: T
    stamp: float
    odometry: Transform2D | None
    burst: int = 1
    """The scans in its burst (given back by :meth:`BurstOdometry.flush`)."""
    exact: bool = True
    """Whether its reading is where it was taken (not spread between two bursts' readings)."""


class BurstOdometry(Generic[T]):
    """One robot's scans in order (:meth:`add`), given back with the odometry where each was taken;
    :meth:`flush` at the end of the log."""

    def __init__(self, max_speed: float, name: str = "the robot") -> None:
        self.resolution = ODOMETRY_TRANSLATION_SIGMA / max_speed if max_speed > 0 else 0.0
        """Seconds within which two readings cannot differ measurably: a scan stamped within this
        after its burst's first brings no reading of its own."""
        self.name = name
        self.bursts = 0
        """Bursts of two scans or more seen."""
        self.spread = 0
        """Readings replaced by one between the bursts' readings."""
        self._run: list[Timed[T]] = []
        self._anchor: Transform2D | None = None
        """The reading of the last scan given back: where the robot was at that scan."""
        self._first: list[Timed[T]] = []
        """The log's first burst, while it waits for the next reading (:meth:`_before`)."""
        self._holding = False
        """Whether the log has shown a burst: from then on each scan waits for the next."""
        self._in_burst = False
        self._advanced = False
        """Whether a stamp has come after the one before: the log has a clock."""
        self._last: Timed[T] | None = None
        """The last scan added."""
        self._waiting: list[Timed[T]] = []
        """Scans after the last burst's owner (:meth:`_owner`): they wait for the next reading."""
        self._late = False
        """Whether the burst being held began with a scan already given back (the log's first burst
        after its first scans: nothing waited then), with the burst's reading as its own."""
        self._paces: deque[float] = deque(maxlen=PACES)
        """The robot's recent drive per scan, between readings one scan apart (m)."""
        self._owned = np.ones(3)
        """Where in their bursts the readings so far belonged, by their drives alone (each burst's
        posterior summed: first, between, last; one of each to start, Laplace's rule): a logger
        reads at one place in a burst, so this is the prior of the next burst's owner."""
        self.own_readings = False
        """Whether the log has shown that its readings are not read at its stamps: two scans
        stamped within :attr:`resolution` of each other whose readings differ by more than the
        odometry's noise (a CARMEN laser line's own odometry, a corrected log's increments, ODOM
        lines taken by file order where the stamps repeat). A clock found wrong then leaves the
        readings right (:meth:`fleetmap.agents.prediction.Predictor.predictions`)."""

    def add(self, scan: Timed[T]) -> list[Timed[T]]:
        """The scans ready to track, in order, with their readings (none while a burst may go on)."""
        last, self._last = self._last, scan
        if last is None:
            self._run = [scan]  # the log's first scan waits for the second: they may be a burst
            return []
        self._advanced = self._advanced or scan.stamp > last.stamp
        if not self.own_readings and abs(scan.stamp - last.stamp) <= self.resolution:
            self.own_readings = _apart(last.odometry, scan.odometry)
        # a burst is the scans read within the odometry's resolution of its first: its whole span,
        # not scan to scan (a laser faster than the resolution would make one endless burst)
        if self._same_burst(self._run[0] if self._run else last, scan):
            if not self._in_burst:
                self._in_burst = True
                self.bursts += 1
                if not self._holding:
                    log.warning(
                        "%s: scans stamped %.4f s apart (at %.3f s): the odometry read at a burst's stamps is "
                        "where the robot was at its last scan; each burst is held until it ends and its scans' "
                        "odometry spread between the bursts' readings",
                        self.name,
                        scan.stamp - last.stamp,
                        scan.stamp,
                    )
            self._late = self._late or not self._run
            self._holding = True
            self._run.append(scan)
            return []
        self._in_burst = False
        out = self._release()
        self._run = [scan]
        return out + (self._release() if not self._holding else [])

    def _same_burst(self, first: Timed[T], scan: Timed[T]) -> bool:
        """Whether ``scan`` brings no reading of its own: stamped after the burst's ``first`` scan
        by less than :attr:`resolution`, and its reading no farther from ``first``'s than the
        odometry's noise (readings that differ by more were not taken at those stamps). Stamps that
        have never advanced are no clock at all (a log without one): they say nothing of when a
        reading was taken."""
        if not (self._advanced and 0.0 <= scan.stamp - first.stamp <= self.resolution):
            return False
        a, b = first.odometry, scan.odometry
        if a is None or b is None:
            return a is b
        return not _apart(a, b)

    def flush(self) -> list[Timed[T]]:
        """Every scan still held, at the end of the log: the last burst's, each with the odometry
        where it was taken, and those still waiting for a reading (with none: none came)."""
        out = self._release()
        return out + self._release()

    def _release(self) -> list[Timed[T]]:
        """The burst just ended, each scan with the odometry where it was taken (:class:`BurstOdometry`)."""
        run, self._run = self._run, []
        first, self._first = self._first, []
        waiting, self._waiting = self._waiting, []
        if not run:
            # the log ended: the scans after the last owner have no reading of their own
            return self._before(first, None, None, 1) + [replace(s, odometry=None, exact=False) for s in waiting]
        reading, start = run[-1].odometry, self._anchor
        self._anchor = reading
        late, self._late = self._late, False
        n = len(run)
        if n > 1 and start is None and reading is not None and not first:
            self._first = [replace(s, burst=n) for s in run]  # waits for the next burst's reading
            return [replace(s, odometry=None, exact=False) for s in waiting]
        if reading is None or start is None or not _finite(reading) or not _finite(start):
            # no reading to spread the waiting scans towards: the one they carry is the last owner's
            stale = [replace(s, odometry=None, exact=False) for s in waiting]
            return self._before(first, start, reading, n) + stale + run
        if late:
            # the reading is the scan's already given back, read where that scan was (a repeated
            # stamp's): the rest of its burst waits for the next reading, as a repeated scan does
            self._waiting = waiting + run
            return self._before(first, start, reading, n)
        k = self._owner(len(waiting), n, start, reading)
        spread = waiting + run[:k]
        m = len(spread) + 1
        out = [
            s if s.odometry is None else Timed(s.item, s.stamp, between(start, reading, i / m), n, False)
            for i, s in enumerate(spread, 1)
        ]
        self.spread += sum(s.odometry is not None for s in spread)
        if m == 1:
            self._paces.append(_drive(start, reading))
        self._waiting = run[k + 1 :]
        return self._before(first, start, reading, n) + out + [replace(run[k], burst=n, exact=True)]

    def _owner(self, waiting: int, n: int, start: Transform2D, reading: Transform2D) -> int:
        """Which of a burst's ``n`` scans its reading belongs to: the one whose place in the
        sequence makes the robot's drive per scan since the last owner (``waiting`` scans after it)
        likeliest among its recent steps (:attr:`_paces`, :func:`pace_density`; the robot at a
        constant pace per scan between two readings, the model :func:`between` spreads by), times
        the prior of its place in the burst (:attr:`_owned`). A logger that stamps at receipt reads
        where the robot was after the burst's last scan; a driver that repeats a stamp reads, for
        the repeated scan, where the one before was: the log's own bursts say which, and decide
        those whose drive does not (a robot speeding up or slowing down steps between its paces).
        Without a pace yet, the last; of equally likely scans, the later."""
        if n == 1 or not self._paces:
            return n - 1
        drive = _drive(start, reading)
        likely = pace_density(np.asarray(self._paces), np.array([drive / (waiting + k + 1) for k in range(n)]))
        place = np.array([0] + [1] * (n - 2) + [2])
        posterior = np.exp(likely - likely.max())
        posterior /= posterior.sum()
        prior = self._owned[place] / np.bincount(place, minlength=3)[place]
        self._owned += np.bincount(place, weights=posterior, minlength=3)
        weighed = likely + np.log(prior)
        return max(range(n), key=lambda k: (weighed[k], k))

    def _before(
        self, first: list[Timed[T]], start: Transform2D | None, reading: Transform2D | None, n: int
    ) -> list[Timed[T]]:
        """The log's first burst, held until the next reading (``reading``, ``n`` scans after the
        burst's own, ``start``): nothing came before it, so its scans but the last are placed back
        from its reading at the pace of the next (constant velocity per scan); without that, no
        odometry (a reading that belongs to a later scan says nothing of where they were)."""
        if not first:
            return []
        known = start is not None and reading is not None and _finite(start) and _finite(reading)
        last = len(first) - 1
        out = []
        for k, s in enumerate(first):
            if k == last or s.odometry is None:
                out.append(s)
            elif known and start is not None and reading is not None:
                out.append(replace(s, odometry=between(start, reading, -(last - k) / n), exact=False))
                self.spread += 1
            else:
                out.append(replace(s, odometry=None))
        return out


def pace_density(paces: np.ndarray, drives: np.ndarray) -> np.ndarray:
    """The log-density of each of ``drives`` (m per scan) among the robot's recent steps
    ``paces``: a Gaussian kernel density with Silverman's bandwidth (Silverman 1986, eq. 3.31:
    0.9 min(sd, IQR / 1.34) n^(-1/5)). A robot that stops to turn in place steps a metre or
    nothing on a log thinned by distance: the median of such steps lies anywhere between the two,
    and a burst's drive was given to the scan whose step matched that median rather than either
    pace (aces-corrected, repeated stamps: 4 of 33 readings to the wrong scan,
    docs/decisions/078). Steps all alike rank by the nearest (the bandwidth then vanishes)."""
    q75, q25 = np.percentile(paces, [75, 25])
    spread = min(float(np.std(paces)), float(q75 - q25) / 1.34) or float(np.std(paces))
    bandwidth = max(0.9 * spread * len(paces) ** -0.2, 1e-9)
    z = (drives[:, None] - paces[None, :]) / bandwidth
    return np.logaddexp.reduce(-0.5 * z * z, axis=1)


def _apart(a: Transform2D | None, b: Transform2D | None) -> bool:
    """Whether two readings differ by more than the odometry's noise (False where one is missing)."""
    if a is None or b is None:
        return False
    return (
        math.hypot(b.x - a.x, b.y - a.y) > ODOMETRY_TRANSLATION_SIGMA
        or abs(math.remainder(b.theta - a.theta, math.tau)) > ODOMETRY_ROTATION_SIGMA
    )


def _twist(a: Transform2D, b: Transform2D) -> np.ndarray:
    """The constant speed and turn rate that drive ``a`` to ``b`` in unit time: ``log(a^-1 b)``,
    GTSAM's ``Pose2`` maps (the turn the short way round)."""
    return gtsam.Pose2.Logmap(gtsam.Pose2(a.x, a.y, a.theta).between(gtsam.Pose2(b.x, b.y, b.theta)))


def _drive(a: Transform2D, b: Transform2D) -> float:
    """The length of the arc a robot drives from ``a`` to ``b`` (:func:`between`), in metres."""
    twist = _twist(a, b)
    return float(math.hypot(twist[0], twist[1]))


def between(a: Transform2D, b: Transform2D, f: float) -> Transform2D:
    """The pose a share ``f`` of the way from ``a`` to ``b`` along the arc a robot drives between
    them at constant speed and turn rate (the geodesic of SE(2): ``a exp(f log(a^-1 b))``, GTSAM's
    ``Pose2`` maps; the turn the short way round). Round a corner, the straight chord cuts it by
    half a metre on a log with a scan a metre."""
    p = gtsam.Pose2(a.x, a.y, a.theta).compose(gtsam.Pose2.Expmap(f * _twist(a, b)))
    return Transform2D(float(p.x()), float(p.y()), float(p.theta()))


def _finite(p: Transform2D) -> bool:
    return math.isfinite(p.x) and math.isfinite(p.y) and math.isfinite(p.theta)
