"""The robot agent's logic: scans (and odometry) in, bus messages out (no network, no clock).

Two front ends, chosen by ``[tracking] front_end``:

- **tracking** (the default; :mod:`fleetmap.agents.tracker`): each scan is predicted from odometry
  or constant velocity, registered on the active submap and checked; the robot's path is cut into
  small overlapping submaps chained by links; a robot that loses its place (several scans in a
  row that fit nowhere near where it can be) starts a new epoch.
- **pivot** (:mod:`fleetmap.agents.pivot`): the paper's pivot method, one local map per epoch;
  kept so the paper's results can be reproduced.

What :meth:`Agent.add_scan` returns with the tracking front end, in this order:

- the final version of every submap that the scan finished (a submap is published once more,
  ``final``, when it is full, or when its epoch ends);
- on a new epoch, the FleetEvent ``epoch`` (its first scan and why);
- the Scan: its segments, raw ranges, the submap that placed it and its pose there (none if the
  scan did not fit), and the odometry reading; a scan the motion model carried (the walls neither
  placed it nor said it was taken elsewhere) waits, with the scans after it that had nothing to
  track, until the walls place a scan again, and goes out then, placed again by what that scan's
  fit says of the carried steps (:mod:`fleetmap.agents.carried`), or as it was, once its submap is
  final or the run is broken;
- the active submaps that are due: a submap's first version at once, then every
  ``publish_every`` inserted scans; in an epoch after the first, after every inserted scan until
  the merger says it has placed the epoch (:meth:`Agent.relocalized`): the robot is lost until
  then, and each scan can be the one that makes its map unambiguous.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from fleetmap.agents.bursts import BurstOdometry, Timed
from fleetmap.agents.clock_evidence import say_untimed
from fleetmap.agents.counts import AgentCounts
from fleetmap.agents.pivot import LOST_SCANS, PivotFrontEnd
from fleetmap.agents.tracker import KIDNAP_REASON, Submap, Tracker
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Array, Transform2D, lengths
from fleetmap.shared.core.motion import ScanClock
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.segmap import MIN_SEGMENT_LENGTH
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import check_name
from fleetmap.shared.io.messages import EpochLink, FleetEvent, LaserRanges, LocalMap, Message, Scan, SubmapLink

log = logging.getLogger(__name__)

Tracked = tuple[int, int, Transform2D | None]
"""A scan's index, its epoch and its pose in the epoch's frame (None: not placed)."""

__all__ = ["LOST_SCANS", "Agent", "AgentCounts"]


@dataclass(frozen=True)
class _Waiting:
    """A carried scan's message, or one that had nothing to track after it, waiting for its run to
    end (:mod:`fleetmap.agents.carried`), and its :attr:`Agent.tracked` entry."""

    scan: Scan
    tracked: Tracked


class Agent:
    """One robot's front end: ``add_scan`` for each scan, ``finish`` at the end.

    Deterministic: the same scans (and calls of :meth:`relocalized`) give the same messages, byte
    for byte. ``odometry`` False ignores whatever odometry the scans come with.
    """

    def __init__(
        self,
        robot: str,
        config: FleetmapConfig | None = None,
        *,
        odometry: bool = True,
        lost_scans: int = LOST_SCANS,
    ) -> None:
        self.robot = check_name(robot, "robot")
        self.config = config or FleetmapConfig()
        t = self.config.tracking
        for name, value in (("publish_every", t.publish_every), ("kidnap_after", t.kidnap_after)):
            if value < 1:
                raise BadInput(f"[tracking] {name}", f"must be a positive integer, got {value!r}")
        if isinstance(lost_scans, bool) or not isinstance(lost_scans, int) or lost_scans < 0:
            raise BadInput("lost_scans", f"must be a non-negative integer, got {lost_scans!r}")
        self._front: PivotFrontEnd | TrackingFrontEnd
        if t.front_end == "pivot":
            self._front = PivotFrontEnd(robot, self.config, t.publish_every, t.kidnap_after, lost_scans)
        else:
            self._front = TrackingFrontEnd(robot, self.config, odometry, lost_scans)

    @property
    def epoch(self) -> int:
        """The current epoch (the one the next scan goes into)."""
        return self._front.epoch

    @property
    def epoch_pose(self) -> Transform2D | None:
        """The robot's pose in its current epoch's frame after the last scan (None: unplaced)."""
        return self._front.epoch_pose

    @property
    def counts(self) -> AgentCounts:
        return self._front.counts

    @property
    def clock(self) -> ScanClock | None:
        """What the tracking front end made of the scans' stamps (None with the pivot front end)."""
        return self._front.tracker.clock if isinstance(self._front, TrackingFrontEnd) else None

    @property
    def bursts(self) -> BurstOdometry[Any] | None:
        """What the tracking front end made of bursts of scans (None with the pivot front end)."""
        return self._front.bursts if isinstance(self._front, TrackingFrontEnd) else None

    def add_scan(self, index: int, stamp: float, scan: RangeScan, odometry: Transform2D | None = None) -> list[Message]:
        """The messages to publish for one scan, in order (see the module docstring). A scan of a
        burst is tracked when the burst ends (:mod:`fleetmap.agents.bursts`): its messages come then."""
        return self._front.add_scan(index, stamp, scan, odometry)

    @property
    def tracked(self) -> list[Tracked]:
        """The scans the last :meth:`add_scan` (or :meth:`finish`) tracked, in order: each one's
        index, epoch and pose in the epoch's frame (None where it was not placed). Usually the scan
        just added; none while a burst is held, all of it when the burst ends; a carried scan's
        when its run ends (the module docstring)."""
        return self._front.tracked

    def start_at(self, epoch: int) -> None:
        """Number this run's first epoch ``epoch`` (before the first scan): a robot restarted
        under its id begins after the epochs the merger already holds of it, never rewriting one;
        its first epoch has no link to them (it does not know where it is relative to them)."""
        if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
            raise BadInput("epoch", f"expected a non-negative integer, got {epoch!r}")
        if self.counts.scans:
            raise BadInput("epoch", "a run's first epoch is set before its first scan")
        self._front.start_at(epoch)

    def relocalized(self, epoch: int) -> None:
        """The merger placed this robot's ``epoch`` (its "relocalized" event)."""
        self._front.relocalized(epoch)

    def finish(self) -> list[Message]:
        """The final version of every map still being built."""
        return self._front.finish()

    def republish(self) -> list[Message]:
        """The latest version of every map so far, as it was published (for a merger that
        (re)started and must lose nothing)."""
        return self._front.republish()


class TrackingFrontEnd:
    """The tracking front end's messages (see the module docstring)."""

    def __init__(self, robot: str, config: FleetmapConfig, odometry: bool, lost_scans: int) -> None:
        self.robot = robot
        self.config = config
        self.use_odometry = odometry and config.tracking.odometry != "off"
        self.lost_scans = lost_scans
        self.tracker = Tracker(config, self.use_odometry)
        self.bursts: BurstOdometry[tuple[int, RangeScan, Transform2D | None]] = BurstOdometry(
            config.integration.motion.max_speed, robot
        )
        """Scans held while a burst may go on (:mod:`fleetmap.agents.bursts`); only with odometry,
        which is all a burst's stamps make wrong once the clock is judged."""
        self.tracked: list[Tracked] = []
        """The scans the last call tracked (:attr:`Agent.tracked`)."""
        self._waiting: list[_Waiting] = []
        """Carried scans' messages waiting for their run to end, in order."""
        self._unfinal: list[Submap] = []
        """Finished submaps whose final version waits for a carried run that holds their scans."""
        self._latest: dict[tuple[int, int], LocalMap] = {}
        """The latest message of every submap, by (epoch, submap), in publication order."""
        self._found: set[int] = set()
        self._scans = 0
        self._placed = 0
        self._local_maps = 0
        self._stamp = 0.0
        self._first_epoch = 0

    def start_at(self, epoch: int) -> None:
        self.tracker.first_epoch = self._first_epoch = epoch

    @property
    def epoch(self) -> int:
        return max(self.tracker.epoch, self._first_epoch)

    @property
    def epoch_pose(self) -> Transform2D | None:
        return self.tracker.epoch_pose

    @property
    def counts(self) -> AgentCounts:
        epochs = self.tracker.epoch + 1 - self._first_epoch if self.tracker.epoch >= 0 else 0
        return AgentCounts(self._scans, self._placed, epochs, self._local_maps)

    def add_scan(self, index: int, stamp: float, scan: RangeScan, odometry: Transform2D | None) -> list[Message]:
        self._scans += 1
        self.tracked = []
        if not self.use_odometry:
            return self._add(index, stamp, scan, None, odometry)
        out: list[Message] = []
        for ready in self.bursts.add(Timed((index, scan, odometry), stamp, odometry)):
            out += self._released(ready)
        return out

    def _released(self, ready: Timed[tuple[int, RangeScan, Transform2D | None]]) -> list[Message]:
        """Track a scan :attr:`bursts` gave back; one from a burst tells the clock that its stamp is
        not its time (the burst's readings, spread, moved within milliseconds): the intervals it
        bounds are timed by the sequence."""
        clock = self.tracker.clock
        if ready.burst > 1:
            clock.bunched(ready.burst)
            say_untimed(clock, f"scan {ready.item[0]} arrived in a burst of {ready.burst} scans stamped together")
        self.tracker.exact = ready.exact
        self.tracker.by_pace = not ready.exact or ready.burst > 1
        self.tracker.motion.own_readings = self.bursts.own_readings
        return self._add(ready.item[0], ready.stamp, ready.item[1], ready.odometry, ready.item[2])

    def _add(
        self, index: int, stamp: float, scan: RangeScan, odometry: Transform2D | None, reading: Transform2D | None
    ) -> list[Message]:
        """Track one scan with the ``odometry`` where it was taken; its Scan message carries the
        robot's own ``reading``."""
        segments = extract_segments(scan, self.config.extraction)
        self._stamp = stamp
        steps = self.tracker.add(index, stamp, scan, segments, odometry)
        out = self._let_go()
        for step in steps:
            if step.new_epoch:
                out += self._finals(stamp)
                detail = {
                    "epoch": step.epoch,
                    "first_scan": step.first_scan,
                    "previous_epoch": step.epoch - 1,
                    "reason": KIDNAP_REASON.format(n=self.config.tracking.kidnap_after),
                }
                out.append(FleetEvent("epoch", self.robot, stamp, json.dumps(detail)))
            self._placed += step.pose is not None
        out += self._finals(stamp)
        last = steps[-1]
        ranges = LaserRanges.from_range_scan(scan)
        kept = reading if reading is not None and np.isfinite(reading.as_array()).all() else None
        message = Scan(self.robot, last.epoch, index, stamp, _wire(segments), ranges, last.submap, last.pose, kept)
        tracked = (index, self.epoch, self.tracker.epoch_pose)
        if self.tracker.run.holds(index):
            self._waiting.append(_Waiting(message, tracked))
        else:
            out.append(message)
            self.tracked.append(tracked)
        out += self._due(stamp)
        return out

    def _let_go(self) -> list[Message]:
        """The waiting scans' messages whose run ended or whose submap is final, in order, each
        placed again where the run's end moved it (:mod:`fleetmap.agents.carried`)."""
        smoothed = self.tracker.run.take_smoothed()
        out: list[Message] = []
        while self._waiting and not self.tracker.run.holds(self._waiting[0].scan.index):
            waiting = self._waiting.pop(0)
            message, tracked = waiting.scan, waiting.tracked
            moved = smoothed.get(message.index)
            if moved is not None:
                if moved.in_submap is not None:
                    message = replace(message, pose=moved.in_submap)
                tracked = (tracked[0], tracked[1], moved.pose)
            out.append(message)
            self.tracked.append(tracked)
        return out

    def relocalized(self, epoch: int) -> None:
        self._found.add(epoch)

    def finish(self) -> list[Message]:
        self.tracked = []
        out: list[Message] = []
        for ready in self.bursts.flush():
            out += self._released(ready)
        self.tracker.run.drop()
        out += self._let_go()
        out += self._finals(self._stamp)
        for submap in self.tracker.submaps():
            submap.finished = True
            out += self._message(submap, self._stamp, final=True)
        return out

    def republish(self) -> list[Message]:
        return list(self._latest.values())

    # -- internals ---------------------------------------------------------------------------
    def _finals(self, stamp: float) -> list[Message]:
        """The final versions of the submaps finished, in order, but those a carried run holds
        scans of (:mod:`fleetmap.agents.carried`): they wait."""
        out: list[Message] = []
        finished, self._unfinal = [*self._unfinal, *self.tracker.take_finished()], []
        for submap in finished:
            if self._unfinal or self.tracker.run.places(submap):
                self._unfinal.append(submap)
            else:
                out += self._message(submap, stamp, final=True)
        return out

    def _due(self, stamp: float) -> list[Message]:
        out: list[Message] = []
        epoch = self.tracker.epoch
        lost = epoch > 0 and epoch not in self._found
        every = 1 if lost and self._published_count(epoch) < self.lost_scans else self.config.tracking.publish_every
        for submap in self.tracker.submaps():
            held = self._latest.get((epoch, submap.number))
            if held is None or submap.inserted - held.scans >= every:
                out += self._message(submap, stamp, final=False)
        return out

    def _published_count(self, epoch: int) -> int:
        """Inserted scans published so far in ``epoch``'s first submap (the lost robot's map)."""
        held = self._latest.get((epoch, 0))
        return 0 if held is None else held.scans

    def _message(self, submap: Submap, stamp: float, final: bool) -> list[Message]:
        ep = submap.epoch
        held = self._latest.get((ep, submap.number))
        if held is not None and held.final:
            return []
        built = submap.segment_map()
        segments = _wire(built.segments)
        if len(segments) == 0:
            return []
        pose = None
        if not final and ep == self.tracker.epoch:
            epoch_pose = self.tracker.epoch_pose
            pose = None if epoch_pose is None else submap.origin.inverse().compose(epoch_pose)
        link = None
        if submap.link_transform is not None and submap.link_covariance is not None:
            link = SubmapLink(submap.number - 1, submap.link_transform, tuple(submap.link_covariance.ravel().tolist()))
        previous = (
            EpochLink(ep - 1, KIDNAP_REASON.format(n=self.config.tracking.kidnap_after))
            if ep > self._first_epoch
            else None
        )
        placed = submap.placed
        message = LocalMap(
            self.robot,
            ep,
            0 if held is None else held.version + 1,
            stamp,
            segments,
            submap.inserted,
            pose,
            previous,
            submap.viewpoints(),
            submap=submap.number,
            final=final,
            link=link,
            scan_indices=np.array([s.index for s in placed], dtype=np.int64),
            scan_stamps=np.array([s.stamp for s in placed], dtype=np.float64),
            scan_poses=np.array([[s.pose.x, s.pose.y, s.pose.theta] for s in placed]).reshape(-1, 3),
            frame_scan=submap.frame_scan,
        )
        self._latest[(ep, submap.number)] = message
        self._local_maps += 1
        return [message]


def _wire(segments: Array) -> Array:
    """Segments as a message carries them: fusion or simplification may leave a degenerate one."""
    return segments[lengths(segments) >= MIN_SEGMENT_LENGTH]
