"""Scans that arrived in a burst, and the odometry where each was taken (issue 48; pure, no clock).

A logger that writes what arrives stamps a burst of scans at receipt, milliseconds apart, although
the laser took them a period apart; where the odometry is read at the scan's stamp (a CARMEN logger
interpolates it there, a ROS driver looks it up in tf at the header's stamp) every scan of the
burst reads where the robot was when the burst arrived, just after its last scan. Taken at its
word, that reading puts the burst's first scan where its last one was (a metre or more ahead on a
sparse log) and says the others did not move.

The evidence is in the stamps and readings themselves: two readings taken closer together than
the robot can drive ``ODOMETRY_TRANSLATION_SIGMA`` (at ``max_speed``) cannot differ by more than
the odometry's own noise, so a scan stamped that close after the one before, its reading within
that noise of the one before, brought no new reading: it is in the same burst.
:class:`BurstOdometry` holds a burst's scans until a scan with a new reading ends it. Then
the burst's reading belongs to its last scan, the previous burst's to the scan before its first;
the scans between are spread evenly between the two, in order (a laser scans at a steady rate,
and a log thinned by distance keeps a scan every so many metres). A reading is never moved
outside the two the robot's wheels gave.

Until a log shows its first burst nothing is held, so a robot whose stamps are its scans' times
is tracked as it comes; from then on each scan waits for the next one (live, for the next burst,
which arrives together anyway).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Generic, TypeVar

from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.motion import ODOMETRY_ROTATION_SIGMA, ODOMETRY_TRANSLATION_SIGMA

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class Timed(Generic[T]):
    """A scan (whatever the caller tracks) with its stamp and odometry reading."""

    item: T
    stamp: float
    odometry: Transform2D | None


class BurstOdometry(Generic[T]):
    """One robot's scans in order (:meth:`add`), given back with the odometry where each was taken;
    :meth:`flush` at the end of the log."""

    def __init__(self, max_speed: float, name: str = "the robot") -> None:
        self.resolution = ODOMETRY_TRANSLATION_SIGMA / max_speed if max_speed > 0 else 0.0
        """Seconds within which two readings cannot differ measurably: a scan stamped within this of
        the previous one brings no reading of its own."""
        self.name = name
        self.bursts = 0
        """Bursts of two scans or more seen."""
        self.spread = 0
        """Readings replaced by one between the bursts' readings."""
        self._run: list[Timed[T]] = []
        self._anchor: Transform2D | None = None
        """The reading of the last scan given back: where the robot was at that scan."""
        self._holding = False
        """Whether the log has shown a burst: from then on each scan waits for the next."""
        self._in_burst = False
        self._advanced = False
        """Whether a stamp has come after the one before: the log has a clock."""
        self._last: Timed[T] | None = None
        """The last scan added."""

    def add(self, scan: Timed[T]) -> list[Timed[T]]:
        """The scans ready to track, in order, with their readings (none while a burst may go on)."""
        last, self._last = self._last, scan
        if last is not None and self._same_burst(last, scan):
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
            self._holding = True
            self._run.append(scan)
            return []
        self._in_burst = False
        out = self.flush()
        self._run = [scan]
        return out + (self.flush() if not self._holding else [])

    def _same_burst(self, last: Timed[T], scan: Timed[T]) -> bool:
        """Whether ``scan`` brings no reading of its own: stamped after ``last`` by less than
        :attr:`resolution`, and its reading no farther from ``last``'s than the odometry's noise
        (readings that differ by more were not taken at those stamps). Stamps that have never
        advanced are no clock at all (a log without one): they say nothing of when a reading was
        taken."""
        step = scan.stamp - last.stamp
        self._advanced = self._advanced or step > 0.0
        if not (self._advanced and 0.0 <= step <= self.resolution):
            return False
        a, b = last.odometry, scan.odometry
        if a is None or b is None:
            return a is b
        return (
            math.hypot(b.x - a.x, b.y - a.y) <= ODOMETRY_TRANSLATION_SIGMA
            and abs(math.remainder(b.theta - a.theta, math.tau)) <= ODOMETRY_ROTATION_SIGMA
        )

    def flush(self) -> list[Timed[T]]:
        """The held scans, each with the odometry where it was taken (:class:`BurstOdometry`)."""
        run, self._run = self._run, []
        if not run:
            return []
        reading, start = run[-1].odometry, self._anchor
        self._anchor = reading
        if len(run) == 1 or reading is None or start is None or not (_finite(reading) and _finite(start)):
            return run
        n = len(run)
        out = []
        for k, scan in enumerate(run, 1):
            if scan.odometry is None:
                out.append(scan)
                continue
            out.append(Timed(scan.item, scan.stamp, between(start, reading, k / n)))
            self.spread += k < n
        return out


def between(a: Transform2D, b: Transform2D, f: float) -> Transform2D:
    """The pose a share ``f`` of the way from ``a`` to ``b`` (the turn the short way round)."""
    theta = a.theta + f * math.remainder(b.theta - a.theta, math.tau)
    return Transform2D(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), math.remainder(theta, math.tau))


def _finite(p: Transform2D) -> bool:
    return math.isfinite(p.x) and math.isfinite(p.y) and math.isfinite(p.theta)
