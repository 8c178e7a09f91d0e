"""A robot's submaps: what one is, how placed scans are inserted, and when one is finished and the
next started (:mod:`fleetmap.agents.tracker`, step 5 of its walk-through).

**Submaps** (Cartographer's scheme): two are active at a time, and every inserted scan goes into
both. A scan is registered on, and placed by, the older one, which holds more. A placed scan is
inserted when the robot has moved :data:`INSERT_DISTANCE` or turned :data:`INSERT_ROTATION` since the last
inserted one (or :data:`INSERT_INTERVAL` has passed). A submap is finished when it covers
``submap_length`` metres of the robot's path or :data:`SUBMAP_SCANS` inserted scans; the next one starts
halfway through, at an inserted scan, whose pose is the new submap's frame. So consecutive submaps
overlap by half, and each is chained to the previous one by the *link*: its frame in the previous
submap's frame, with the uncertainty of the registration that placed it. A finished submap never
changes.

**What a submap publishes** is its walls less those its own scans saw through more than they saw
(:func:`fleetmap.shared.core.tracking.wall_evidence`, the see-through test of the fit's check on
each inserted scan's beams): a person walking past, a door swinging, a cart pushed by. Another
robot there minutes later sees through them too, and left in, they refute the right match of the
two robots' submaps (docs/decisions/002-pose-graph.md). Registration keeps every wall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.mapgrid import scan_viewpoint
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.simplify import SIMPLIFY_TOLERANCE
from fleetmap.shared.core.tracking import (
    VOXEL_SIZE,
    ReferenceMap,
    Registration,
    ScanSamples,
    drift_covariance,
    wall_evidence,
)
from fleetmap.shared.core.walls import WallMap

INSERT_DISTANCE = 0.10
"""A tracked scan is inserted into the submaps when the robot has moved this far (m) ..."""
INSERT_ROTATION = 0.035
"""... or turned this much (rad, 2 degrees) since the last inserted scan ..."""
INSERT_INTERVAL = 5.0
"""... or this much time (s) has passed (a robot standing still refreshes its view)."""
SUBMAP_SCANS = 100
"""A submap holds at most this many inserted scans (or ``submap_length`` of the path); the next starts
halfway, so consecutive submaps overlap by half (docs/decisions/001-tracking-front-end.md)."""
LINK_MIN_SIGMA_TRANSLATION = 0.01
"""A submap link's standard deviation is at least this (m) ..."""
LINK_MIN_SIGMA_ROTATION = 0.005
"""... and this (rad, 0.3 degrees): the registration's covariance, no tighter than these
(docs/decisions/001-tracking-front-end.md)."""


@dataclass(frozen=True)
class PlacedScan:
    """A scan as a submap places it."""

    index: int
    stamp: float
    pose: Transform2D
    """The laser's pose in the submap's frame."""


@dataclass
class Submap:
    """One submap of an epoch (see the module docstring): what the agent publishes of it and the
    reference the tracker registers on."""

    epoch: int
    number: int
    frame_scan: int
    """The index of the scan whose pose is its frame (its first inserted scan)."""
    origin: Transform2D
    """Its frame (the pose of its first scan) in the epoch's frame."""
    link_transform: Transform2D | None
    """Its frame in the previous submap's frame (None for an epoch's first submap)."""
    link_covariance: Array | None
    reference: ReferenceMap
    walls: WallMap
    max_range: float
    """How far the robot's extraction reads a beam (m)."""
    viewpoints_in: list[Array] = field(default_factory=list)
    """The inserted scans' viewpoints ``[x, y, theta, bearing_min, bearing_max]``."""
    scans_in: list[tuple[RangeScan, Transform2D]] = field(default_factory=list)
    """The inserted scans and their poses (what they saw of its walls: :meth:`segment_map`)."""
    placed: list[PlacedScan] = field(default_factory=list)
    """The scans this submap placed (registered on it while it was the matching submap)."""
    path_length: float = 0.0
    path_spread: Array = field(default_factory=lambda: np.zeros((3, 3)))
    """What the walls left open of the steps placed since its frame (the epoch's frame): the sum of
    their window's spread (:attr:`~fleetmap.agents.fitcheck.Fit.spread`). Its successor's link
    carries it."""
    inserted: int = 0
    finished: bool = False
    _last_insert: Transform2D | None = None
    _built: tuple[int, SegmentMap] | None = None

    def insert(self, scan: RangeScan, samples: ScanSamples, segments: Array, pose: Transform2D) -> None:
        """Add a scan taken at ``pose`` (this submap's frame): its beams (which judge the walls),
        and its samples and segments in its own frame."""
        self.reference.insert(samples.moved(pose))
        self.scans_in.append((scan, pose))
        self.walls.add(pose.apply(segments))
        viewpoint = scan_viewpoint(segments)
        if len(viewpoint):
            viewpoint[0, 0:3] = pose.x, pose.y, pose.theta
            self.viewpoints_in.append(viewpoint[0])
        if self._last_insert is not None:
            self.path_length += math.hypot(pose.x - self._last_insert.x, pose.y - self._last_insert.y)
        self._last_insert = pose
        self.inserted += 1

    def segment_map(self) -> SegmentMap:
        """Its walls, one segment per stretch of wall (:class:`fleetmap.shared.core.walls.WallMap`),
        less those its own scans saw through more than they saw (:func:`wall_evidence`): people,
        doors and carts that moved while the robot looked. Another robot's laser, there minutes
        later, sees through them as well; left in, they would refute the right match of the two
        robots' submaps (docs/decisions/002-pose-graph.md)."""
        if self._built is None or self._built[0] != self.inserted:
            walls = self.walls.segments
            seen, through = wall_evidence(walls, self.scans_in, self.max_range)
            walls = walls[through <= seen]
            self._built = (self.inserted, SegmentMap(walls, ordered=False, oriented=True))
        if self.finished:
            self.scans_in = []  # a finished submap never changes: its walls are judged for good
        return self._built[1]

    def viewpoints(self) -> Array:
        return np.array(self.viewpoints_in) if self.viewpoints_in else np.zeros((0, 5))


class SubmapChain:
    """An epoch's chain of submaps as the robot's placed scans build it (see the module docstring):
    the active ones, and those finished since :meth:`take_finished`."""

    def __init__(self, config: FleetmapConfig) -> None:
        self.config = config
        self.params = config.tracking
        self.active: list[Submap] = []
        """The active submaps, oldest (the matching one) first."""
        self.finished: list[Submap] = []
        """Submaps finished since :meth:`take_finished` was last called, in order."""
        self.count = 0
        """The submaps the epoch has started."""
        self.inserted_at: tuple[float, Transform2D] | None = None
        """Stamp and epoch-frame pose of the last inserted scan."""

    def take_finished(self) -> list[Submap]:
        out, self.finished = self.finished, []
        return out

    def due(self, stamp: float, pose: Transform2D) -> bool:
        """Whether a scan placed at ``pose`` (epoch frame) is inserted: the robot has moved or turned
        enough since the last inserted scan, or enough time has passed."""
        if self.inserted_at is None:
            return True
        when, where = self.inserted_at
        moved = math.hypot(pose.x - where.x, pose.y - where.y)
        turned = abs(float(wrap_angle(pose.theta - where.theta)))
        return moved >= INSERT_DISTANCE or turned >= INSERT_ROTATION or stamp - when >= INSERT_INTERVAL

    def insert(
        self,
        epoch: int,
        index: int,
        stamp: float,
        scan: RangeScan,
        segments: Array,
        samples: ScanSamples,
        pose: Transform2D,
        reg: Registration | None,
    ) -> None:
        """Insert a placed scan (epoch-frame ``pose``) into the active submaps; finish and start
        submaps as they fill (see the module docstring)."""
        p = self.params
        self.inserted_at = (stamp, pose)
        for submap in self.active:
            submap.insert(scan, samples, segments, submap.origin.inverse().compose(pose))
        newest = self.active[-1]
        half = newest.path_length >= p.submap_length / 2 or newest.inserted >= max(SUBMAP_SCANS // 2, 1)
        if half and len(self.active) == 1:
            self.start(epoch, index, pose, scan, segments, samples, reg)
        oldest = self.active[0]
        if len(self.active) > 1 and (oldest.path_length >= p.submap_length or oldest.inserted >= SUBMAP_SCANS):
            oldest.finished = True
            self.finished.append(self.active.pop(0))
            newest = self.active[-1]
            if newest.path_length >= p.submap_length / 2 or newest.inserted >= max(SUBMAP_SCANS // 2, 1):
                self.start(epoch, index, pose, scan, segments, samples, reg)

    def start(
        self,
        epoch: int,
        index: int,
        pose: Transform2D,
        scan: RangeScan,
        segments: Array,
        samples: ScanSamples,
        reg: Registration | None,
    ) -> None:
        """Start a submap whose frame is the scan placed at ``pose`` (epoch frame), linked to the
        newest active one by the registration that placed the scan."""
        previous = self.active[-1] if self.active else None
        link = covariance = None
        if previous is not None:
            link = previous.origin.inverse().compose(pose)
            covariance = (
                link_covariance(reg)
                + drift_covariance(previous.path_length)
                + rotated(previous.path_spread, -previous.origin.theta)
            )
        walls = WallMap(SIMPLIFY_TOLERANCE)
        submap = Submap(
            epoch,
            self.count,
            index,
            pose,
            link,
            covariance,
            ReferenceMap(VOXEL_SIZE),
            walls,
            self.config.extraction.max_range,
        )
        self.count += 1
        submap.insert(scan, samples, segments, Transform2D())
        self.active.append(submap)

    def widen(self, spread: Array) -> None:
        """A step placed with ``spread`` (a covariance in the epoch's frame) left open: every active
        submap's successor link carries it."""
        for submap in self.active:
            submap.path_spread = submap.path_spread + spread

    def restart(
        self, epoch: int, index: int, stamp: float, scan: RangeScan, segments: Array, samples: ScanSamples
    ) -> None:
        """Finish every active submap and start the epoch's first one from its first scan."""
        for submap in self.active:
            submap.finished = True
            self.finished.append(submap)
        self.active = []
        self.count = 0
        self.inserted_at = None
        self.start(epoch, index, Transform2D(), scan, segments, samples, None)
        self.inserted_at = (stamp, Transform2D())
        self.active[0].placed.append(PlacedScan(index, stamp, Transform2D()))


def link_covariance(reg: Registration | None) -> Array:
    """The covariance of a submap link from the registration that placed the new submap's frame,
    no tighter than :data:`LINK_MIN_SIGMA_TRANSLATION` and :data:`LINK_MIN_SIGMA_ROTATION`."""
    st, sr = LINK_MIN_SIGMA_TRANSLATION, LINK_MIN_SIGMA_ROTATION
    floor = np.diag([st**2, st**2, sr**2])
    if reg is None:
        return floor
    try:
        cov = np.linalg.inv(reg.information)
    except np.linalg.LinAlgError:
        return floor
    cov = 0.5 * (cov + cov.T) + floor
    return cov


def rotated(covariance: Array, theta: float) -> Array:
    """A pose covariance ``[x, y, theta]`` in a frame turned by ``theta``."""
    c, s = math.cos(theta), math.sin(theta)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r @ covariance @ r.T
