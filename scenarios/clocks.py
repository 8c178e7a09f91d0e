"""A robot's scans with their clock broken the ways real robots' clocks are (issue 48's test data).

A log's stamps are not the times its scans were taken. A logger that writes what arrives stamps a
burst of scans at receipt, a few milliseconds apart, although the laser took them a period apart;
a driver repeats a stamp or drops a scan; stamps jitter with the host's load; the odometry runs on
another clock than the laser. Where the odometry is read at the scan's stamp (a CARMEN logger
interpolates it there, a ROS driver looks it up in tf), a wrong stamp makes the odometry wrong too:
a burst's scans all read the odometry of its last one, as if the robot had stood still.

:func:`break_clock` turns a source's scans (anything with ``stamp`` and ``odometry`` fields, such as
:class:`fleetmap.shared.io.sources.SourceScan` or a scenario's scans) into the same scans as such a
robot would have recorded them: the ranges and the order are the laser's; the stamps are the
broken clock's; the odometry is the true odometry track read at the broken clock's stamps (or at
a skewed clock's). The true stamps stay with the caller, who scores by scan index.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import math
import random
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, TypeVar

from fleetmap.shared.core.geometry import Transform2D

CLOCKS = ("true", "burst", "jitter", "drop", "skew", "repeat", "nudge")
"""``true`` keeps the log's clock; ``nudge`` moves it by less than any robot's clock resolves (its draws
measure how far a tracker's figures move for nothing: ``benchmarks/clock_spread.py``); the others
break it (see :func:`break_clock`)."""

BURST_SIZES = (2, 3, 4)
"""Scans in one burst, each as likely."""
BURST_SPREAD = 0.002
"""A burst's scans are stamped within this many seconds of each other."""
JITTER = 0.05
"""Stamps move by up to this many seconds either way."""
DROP_EVERY = 10
"""One scan in this many is lost."""
SKEW = 0.1
"""The odometry's clock runs this many seconds ahead of the laser's."""
REPEAT_EVERY = 10
"""One scan in this many carries the stamp of the scan before it."""
NUDGE = 0.001
"""A nudged clock moves each stamp by up to this many seconds either way: no clock this good is broken."""

S = TypeVar("S")


def break_clock(scans: Iterable[S], clock: str, seed: int = 0) -> Iterator[S]:
    """The scans as a robot with a ``clock`` clock records them (one of :data:`CLOCKS`):

    - ``burst``: groups of 2-4 consecutive scans stamped at the group's last scan's time (when the
      burst arrived), :data:`BURST_SPREAD` apart at most;
    - ``jitter``: each stamp moved by up to :data:`JITTER` either way (they may go backwards; none
      before 0);
    - ``drop``: one scan in :data:`DROP_EVERY` missing;
    - ``skew``: the odometry read :data:`SKEW` seconds after the scan's stamp (a seed other than 0
      nudges the stamps too, as ``nudge`` does: one skew, drawn several ways);
    - ``repeat``: one scan in :data:`REPEAT_EVERY` stamped as the scan before it;
    - ``nudge``: each stamp moved by up to :data:`NUDGE` either way (in order where the scans are
      further apart than twice that): the true clock as a draw, not broken.

    The odometry of every scan is the true odometry track read (interpolated) at its broken stamp.
    The same ``seed`` breaks the same scans the same way. A source whose stamps do not increase from
    scan to scan (rounded, or all 0) has no clock to break (a ``ValueError`` says so)."""
    if clock not in CLOCKS:
        raise ValueError(f"unknown clock {clock!r} (known: {', '.join(CLOCKS)})")
    items = list(scans)
    if clock == "true" or len(items) < 2:
        yield from items
        return
    stamps = [float(_field(s, "stamp")) for s in items]
    if any(b <= a for a, b in itertools.pairwise(stamps)):
        raise ValueError("the log's stamps do not increase from scan to scan: it has no clock to break")
    track = OdometryTrack(stamps, [_field(s, "odometry") for s in items])
    rng = random.Random(seed)
    if clock == "drop":
        lost = {i for i in range(len(items)) if i > 0 and rng.randrange(DROP_EVERY) == 0}
        yield from (s for i, s in enumerate(items) if i not in lost)
        return
    broken = list(stamps)
    if clock == "burst":
        start = 0
        while start < len(items):
            size = rng.choice(BURST_SIZES)
            group = range(start, min(start + size, len(items)))
            arrived = stamps[group[-1]]
            step = BURST_SPREAD / max(len(group) - 1, 1)
            for k, i in enumerate(group):
                broken[i] = arrived + k * step * rng.random()
            start += size
        # a later burst never arrives before an earlier one's stamps
        for i in range(1, len(broken)):
            broken[i] = max(broken[i], broken[i - 1])
    elif clock in ("jitter", "nudge") or (clock == "skew" and seed):  # (one skew: its later draws nudged)
        spread = JITTER if clock == "jitter" else NUDGE
        broken = [max(t + rng.uniform(-spread, spread), 0.0) for t in stamps]  # no clock reads before 0
    elif clock == "repeat":
        for i in range(1, len(items)):
            if rng.randrange(REPEAT_EVERY) == 0:
                broken[i] = broken[i - 1]
    read_at = [t + SKEW for t in broken] if clock == "skew" else broken
    for s, stamp, at in zip(items, broken, read_at, strict=True):
        yield _replaced(s, stamp, track.at(at))


class OdometryTrack:
    """The true odometry as a function of the true time (linear between scans, held at the ends)."""

    def __init__(self, stamps: Sequence[float], poses: Sequence[Transform2D | None]) -> None:
        known = [(t, p) for t, p in zip(stamps, poses, strict=True) if p is not None]
        self.stamps = [t for t, _ in known]
        self.poses = [p for _, p in known]
        self.theta: list[float] = []
        for p in self.poses:  # unwrapped, so a turn through pi interpolates the short way
            last = self.theta[-1] if self.theta else p.theta
            self.theta.append(last + math.remainder(p.theta - last, math.tau))

    def at(self, stamp: float) -> Transform2D | None:
        if not self.poses:
            return None
        j = bisect.bisect_right(self.stamps, stamp)
        if j == 0:
            return self.poses[0]
        if j >= len(self.poses):
            return self.poses[-1]
        a, b = self.poses[j - 1], self.poses[j]
        span = self.stamps[j] - self.stamps[j - 1]
        f = (stamp - self.stamps[j - 1]) / span if span > 0 else 0.0
        theta = self.theta[j - 1] + f * (self.theta[j] - self.theta[j - 1])
        return Transform2D(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), math.remainder(theta, math.tau))


def _field(item: Any, name: str) -> Any:
    return getattr(item, name)


def _replaced(item: S, stamp: float, odometry: Transform2D | None) -> S:
    """The scan with another stamp and odometry (its ranges' own stamp too, where it carries one)."""
    changes: dict[str, Any] = {"stamp": stamp}
    if _field(item, "odometry") is not None:
        changes["odometry"] = odometry
    scan = getattr(item, "scan", None)
    if dataclasses.is_dataclass(scan) and not isinstance(scan, type) and hasattr(scan, "stamp"):
        changes["scan"] = dataclasses.replace(scan, stamp=stamp)
    return dataclasses.replace(item, **changes)  # type: ignore[type-var]
