"""Whether a robot's stamps are its scans' times, judged by the tracker as it places scans, and the
warnings a log gets when they are not (docs/decisions/009-clocks-evidence-over-stamps.md, 078).

The clock itself (:class:`fleetmap.shared.core.motion.ScanClock`) weighs the evidence: stamps that
repeat or go back and scans that arrived in a burst untime the intervals they bound; motion the
stamps' interval cannot hold untimes them all. This module gives it the motion between two placed
scans, as uncertain as the walls fix the two poses along it, and says once of each kind why.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.motion import ScanClock

log = logging.getLogger(__name__)


def check_order(clock: ScanClock, previous: float | None, index: int, stamp: float) -> None:
    """Say once per log (:func:`say_untimed`) when scan ``index``'s stamp, just ticked, repeats the
    ``previous`` scan's or is before it: the intervals such stamps bound are timed by the scans'
    sequence (:meth:`ScanClock.times`)."""
    if previous is not None and stamp <= previous:
        said = "repeats" if stamp == previous else f"is {previous - stamp:.4f} s before"
        say_untimed(clock, f"scan {index}'s stamp {said} the previous scan's")


def check_motion(
    clock: ScanClock,
    index: int,
    seconds: float,
    last: Transform2D,
    pose: Transform2D,
    information: Array,
    heading: float,
    scans: int = 1,
    end: int | None = None,
) -> None:
    """Judge the stamps by the motion from the last placed scan (``last``) to scan ``index``
    placed at ``pose`` (both in the epoch's frame) ``seconds`` later by their stamps
    (:meth:`ScanClock.check`), uncertain as the walls fix the two poses along it (the scan's
    registration ``information``, in the frame of the submap turned by ``heading``); say once when
    they fail. The interval, ``scans`` scans ending at scan ``end`` (:meth:`ScanClock.times`), is
    no evidence where a stamp that is not its scan's time bounds it."""
    dx, dy = pose.x - last.x, pose.y - last.y
    distance = math.hypot(dx, dy)
    if distance == 0 or not clock.times(scans, end):
        return
    sigma = sigma_along(information, heading, dx / distance, dy / distance)
    was = clock.trusted
    clock.check(seconds, distance, math.sqrt(2.0) * sigma)
    if was and not clock.trusted:
        say_distrusted(clock, f"scan {index} moved {distance:.2f} m in the {seconds:.4f} s its stamp allows")


def say_untimed(clock: ScanClock, evidence: str) -> None:
    """Say once per log that some of its stamps are not its scans' times (a stamp that repeated or
    went back, scans that arrived in a burst), the first ``evidence`` of it, and how the tracker
    times their intervals."""
    if clock.said:
        return
    clock.said = True
    log.warning(
        "%s: some stamps are not their scans' times; the intervals such scans bound are timed by their sequence at "
        "the log's mean period (%.3f s so far), the others by their stamps (%d scans in: %d stamps repeated, "
        "%d going back, %d scans in bursts)",
        evidence,
        clock.period,
        clock.scans,
        clock.repeated,
        clock.backwards,
        clock.bunches,
    )


def say_distrusted(clock: ScanClock, evidence: str) -> None:
    """Say once per log that the stamps are not the scans' times anywhere (the motion showed them
    wrong, or a kidnap only they concluded), and why: every interval from here is timed by the
    sequence."""
    log.warning(
        "%s: the stamps are not the scans' times; tracking by their sequence at the log's mean period "
        "(%.3f s so far) from here (%d scans in: %d stamps repeated, %d going back)",
        evidence,
        clock.period,
        clock.scans,
        clock.repeated,
        clock.backwards,
    )


def sigma_along(information: Array, heading: float, ux: float, uy: float) -> float:
    """The standard deviation (m) along the unit direction ``(ux, uy)`` (epoch frame) of a pose
    fixed with ``information`` in a frame turned by ``heading``; infinite where the walls leave that
    direction free."""
    c, s = math.cos(heading), math.sin(heading)
    u = np.array([c * ux + s * uy, -s * ux + c * uy, 0.0])
    try:
        covariance = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return math.inf
    variance = float(u @ covariance @ u)
    return math.sqrt(variance) if variance > 0 and math.isfinite(variance) else math.inf
