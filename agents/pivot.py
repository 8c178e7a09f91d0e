"""The paper's front end, selectable as ``--front-end pivot``: one local map per epoch, grown by the
pivot method (scans in, bus messages out; no network, no clock).

For every scan the agent extracts segments (paper III-D) and grows its local map online with the
pivot method (paper IV-C, Algorithm 6; :class:`~fleetmap.shared.core.pivotmap.PivotMapBuilder`): each
scan is integrated with the previous placed one, its transform composed with that scan's pose, and
the scan fused into the map, whose frame is the first scan's laser frame.

A robot that knows nothing of where it is cannot tell a kidnap from any other change of view but
by geometry: when ``kidnap_after`` scans in a row cannot be placed (no valid integration with the
previous scan nor with the local map), the agent closes the local map and starts a new *epoch*
whose frame is the first of those scans; the others are integrated into it. A scan is placed
only where the robot can have gone since its last placed scan (``max_speed`` times the time
between their stamps): a look-alike corridor 9 m away matches well, but a robot carried off in
half a second did not drive there; nor, while it drives on straight, farther along its way than
it can brake or speed up (``max_acceleration``). Where a scan matches two places almost equally
(a hallway one door further, or turned round), or matches better one rack back of where it
validly matches as the robot drove, the robot's own recent motion decides (the builder's motion
prior, ``motion_prior_radius``; see :class:`~fleetmap.shared.core.pivotmap.PivotMapBuilder`). One
unplaced scan
followed by a placed one (a person walking by the laser) changes nothing, but for an epoch's
second scan: a local map of one scan is no context to place a later scan on across one that
would not integrate with it (with no motion prior yet either), so the epoch starts again from the
scan that did not integrate (:data:`ONE_SCAN_REASON`). Scans without any
segment (nothing within reach) are not placed, and count neither for nor against a kidnap: they
say nothing about where the robot is.

What :meth:`PivotFrontEnd.add_scan` returns, in this order:

- on a new epoch: the closed epoch's final LocalMap (when it changed since its last version), the
  FleetEvent ``epoch`` (the two again for each epoch of one scan that its next unplaced scan
  started again), the Scan (in the new epoch) and the new epoch's LocalMap version 0;
- otherwise: the Scan, then the LocalMap when it is due: the epoch's first scan, then every
  ``publish_every`` placed scans; in an epoch after the first, after each of its first
  ``lost_scans`` placed scans, until the merger says it has placed it (:meth:`PivotFrontEnd.relocalized`).

Why every scan then: a robot that started a new epoch has lost its place (it was carried off, or
its view changed completely), and it stays lost until the merger places the new local map against
the others. Each scan can be the one that makes that map unambiguous (in a warehouse, the first
view of a lane matches every lane; the forklift's bay, two scans later, matches one), and the
merger integrates the latest version it has: publishing every third scan would hold back the
decisive one by up to two scans.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass

from fleetmap.agents.counts import AgentCounts
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Array, Transform2D, lengths
from fleetmap.shared.core.mapgrid import viewpoints_of
from fleetmap.shared.core.pivotmap import PivotMapBuilder
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.segmap import MIN_SEGMENT_LENGTH, SegmentMap
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import check_name
from fleetmap.shared.io.messages import EpochLink, FleetEvent, LaserRanges, LocalMap, Message, Scan

log = logging.getLogger(__name__)

KIDNAP_REASON = "{n} consecutive scans did not integrate with the local map"
"""The reason of an epoch started by the kidnap check (EpochLink.reason and the event's detail)."""

ONE_SCAN_REASON = "a scan did not integrate with the local map's only scan"
"""The reason of an epoch started because its previous one held a single scan when the next one did
not integrate with it: a local map of one scan is no context to place a later scan on across one
that would not integrate with it, and a scan placed so can take every later one off with it
(docs/decisions/008-pivot-local-maps.md)."""

LOST_SCANS = 20
"""An epoch after the first publishes its local map after each of its first this many placed scans
(the robot is lost until the merger places that map; see the module docstring)."""


@dataclass(frozen=True)
class EpochMap:
    """One epoch's local map as the front end built it (:attr:`PivotFrontEnd.epochs`)."""

    number: int
    map: SegmentMap
    """The built map (its first scan's frame), carrying its placed scans' viewpoints."""
    scans: tuple[tuple[int, Transform2D], ...]
    """Each scan placed in it, in order: its index (as given to ``add_scan``) and its pose in the map's frame."""


@dataclass(frozen=True)
class _Unplaced:
    index: int
    stamp: float
    map: SegmentMap


class _Epoch:
    """One local map of the robot being built: the pivot builder and what was last published of it."""

    def __init__(self, number: int, config: FleetmapConfig, link: EpochLink | None) -> None:
        self.number = number
        self.link = link
        self.builder = PivotMapBuilder(config.integration)
        self.placed = 0
        self.scans: list[tuple[int, Transform2D]] = []
        """(index, pose) of each placed scan, in order."""
        self.pose: Transform2D | None = None
        self.version = -1
        self.published_placed = 0
        self.published_pose: Transform2D | None = None
        self.latest: LocalMap | None = None
        self.found = False
        """The merger said it placed this epoch (relocalized the robot)."""

    @property
    def started(self) -> bool:
        return self.placed > 0

    @property
    def changed(self) -> bool:
        return self.placed != self.published_placed or self.pose != self.published_pose

    def add(self, index: int, scan: SegmentMap, stamp: float) -> bool:
        """Integrate one scan (Algorithm 6, steps 3-6) with its stamp (the motion bound and prior);
        whether it was placed."""
        step = self.builder.add(scan, stamp)
        self.pose = step.pose
        if step.pose is not None:
            self.placed += 1
            self.scans.append((index, step.pose))
        return step.pose is not None

    def built(self) -> EpochMap:
        return EpochMap(self.number, self.builder.map, tuple(self.scans))


class PivotFrontEnd:
    """One robot's local mapping by the pivot method: ``add_scan`` for each scan, ``finish`` at the end.

    Deterministic: the same scans (and calls of :meth:`relocalized`) give the same messages, byte
    for byte.
    """

    def __init__(
        self,
        robot: str,
        config: FleetmapConfig | None = None,
        publish_every: int = 3,
        kidnap_after: int = 2,
        lost_scans: int = LOST_SCANS,
    ):
        self.robot = check_name(robot, "robot")
        for name, value in (("publish_every", publish_every), ("kidnap_after", kidnap_after)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise BadInput(name, f"must be a positive integer, got {value!r}")
        if isinstance(lost_scans, bool) or not isinstance(lost_scans, int) or lost_scans < 0:
            raise BadInput("lost_scans", f"must be a non-negative integer, got {lost_scans!r}")
        self.config = config or FleetmapConfig()
        self.publish_every = publish_every
        self.kidnap_after = kidnap_after
        self.lost_scans = lost_scans
        self._epoch = _Epoch(0, self.config, None)
        self._first_epoch = 0
        self._closed: list[LocalMap] = []
        """The latest version of every closed epoch, in epoch order."""
        self._closed_maps: list[EpochMap] = []
        """The final local map of every closed epoch, in epoch order."""
        self._unplaced: list[_Unplaced] = []
        """The scans with segments that could not be placed since the last placed one."""
        self._scans = 0
        self._placed = 0
        self._local_maps = 0
        self._last_stamp = 0.0
        self.tracked: list[tuple[int, int, Transform2D | None]] = []
        """The scan the last :meth:`add_scan` placed: its index, epoch and epoch-frame pose."""

    def start_at(self, epoch: int) -> None:
        self._epoch = _Epoch(epoch, self.config, None)
        self._first_epoch = epoch

    @property
    def epoch(self) -> int:
        """The current epoch (the one the next scan goes into)."""
        return self._epoch.number

    @property
    def epoch_pose(self) -> Transform2D | None:
        """The robot's pose in its current epoch's local map after the last scan (None: unplaced)."""
        return self._epoch.pose

    @property
    def epochs(self) -> list[EpochMap]:
        """Every epoch so far that holds a placed scan, in order: the closed ones as they were
        closed, and the current one as it is now (read-only; publishes nothing)."""
        current = [self._epoch.built()] if self._epoch.started else []
        return [*self._closed_maps, *current]

    @property
    def counts(self) -> AgentCounts:
        epochs = self.epoch - self._first_epoch + int(self._epoch.started)
        return AgentCounts(self._scans, self._placed, epochs, self._local_maps)

    def add_scan(self, index: int, stamp: float, scan: RangeScan, odometry: Transform2D | None = None) -> list[Message]:
        """The messages to publish for one scan, in order (see the module docstring); the pivot
        method places scans by their geometry alone and does not read ``odometry``."""
        del odometry
        segments = extract_segments(scan, self.config.extraction)
        scan_map = SegmentMap(segments, ordered=True, oriented=True)
        ranges = LaserRanges.from_range_scan(scan)
        self._scans += 1
        self._last_stamp = stamp
        out: list[Message] = []
        current = self._epoch
        if len(segments) == 0:
            current.pose = None  # nothing in reach: the robot cannot say where it is
        elif not current.started:
            self._place(current, index, scan_map, stamp)  # the epoch's frame
        elif self._place(current, index, scan_map, stamp):
            self._unplaced.clear()
        else:
            self._unplaced.append(_Unplaced(index, stamp, scan_map))
            if len(self._unplaced) >= self.kidnap_after:
                out += self._new_epoch(stamp, KIDNAP_REASON.format(n=len(self._unplaced)))
            elif current.placed == 1:
                out += self._new_epoch(stamp, ONE_SCAN_REASON)
        out.append(Scan(self.robot, self.epoch, index, stamp, segments, ranges))
        current = self._epoch
        lost = current.number > 0 and current.placed <= self.lost_scans and not current.found
        every = 1 if lost else self.publish_every
        due = current.version < 0 or current.placed - current.published_placed >= every
        if current.started and due:
            out.append(self._local_map(stamp))
        self.tracked = [(index, self.epoch, self.epoch_pose)]
        return out

    def relocalized(self, epoch: int) -> None:
        """The merger placed this robot's ``epoch`` (its "relocalized" event): if that is the current
        epoch, the robot is no longer lost, and its map goes back to every ``publish_every`` scans."""
        if epoch == self._epoch.number:
            self._epoch.found = True

    def finish(self) -> list[Message]:
        """The current epoch's final LocalMap, unless its latest version already says it all."""
        self.tracked = []
        if self._epoch.started and self._epoch.changed:
            return [self._local_map(self._last_stamp)]
        return []

    def republish(self) -> list[Message]:
        """The latest LocalMap of every epoch so far, as they were published (for a merger that
        (re)started and must lose nothing)."""
        latest = [] if self._epoch.latest is None else [self._epoch.latest]
        return [*self._closed, *latest]

    # --- internals ---

    def _place(self, epoch: _Epoch, index: int, scan_map: SegmentMap, stamp: float) -> bool:
        placed = epoch.add(index, scan_map, stamp)
        self._placed += int(placed)
        return placed

    def _new_epoch(self, stamp: float, reason: str) -> list[Message]:
        """Close the current epoch and start the next from the unplaced scans (the first is its
        frame); again from a later one of them that does not integrate with the new epoch's only
        scan (:data:`ONE_SCAN_REASON`)."""
        out: list[Message] = []
        seeds, self._unplaced = self._unplaced, []
        while seeds:
            old = self._epoch
            old.pose = None  # the robot is no longer anywhere in the old local map
            if old.changed:
                out.append(self._local_map(stamp))
            if old.latest is not None:
                self._closed.append(old.latest)
            if old.started:
                self._closed_maps.append(old.built())
            new = _Epoch(old.number + 1, self.config, EpochLink(old.number, reason, transform=None))
            self._epoch = new
            detail = {"epoch": new.number, "first_scan": seeds[0].index, "previous_epoch": old.number, "reason": reason}
            log.info("%s: epoch %d from scan %d (%s)", self.robot, new.number, seeds[0].index, reason)
            out.append(FleetEvent("epoch", self.robot, stamp, json.dumps(detail)))
            rest, seeds = seeds, []
            for n, seed in enumerate(rest):  # the first one is placed: it is the new epoch's frame
                if self._place(new, seed.index, seed.map, seed.stamp):
                    self._unplaced.clear()
                elif new.placed == 1:
                    seeds, self._unplaced, reason = rest[n:], [], ONE_SCAN_REASON
                    break
                else:
                    self._unplaced.append(seed)
        return out

    def _local_map(self, stamp: float) -> LocalMap:
        epoch = self._epoch
        epoch.version += 1
        built = epoch.builder.map
        message = LocalMap(
            self.robot,
            epoch.number,
            epoch.version,
            stamp,
            _wire_segments(built.segments),
            epoch.placed,
            epoch.pose,
            epoch.link,
            viewpoints_of(built),
        )
        epoch.published_placed, epoch.published_pose, epoch.latest = epoch.placed, epoch.pose, message
        self._local_maps += 1
        return message


def _wire_segments(segments: Array) -> Array:
    """The map's segments as a message carries them: fusion may leave a degenerate one behind."""
    return segments[lengths(segments) >= MIN_SEGMENT_LENGTH]
