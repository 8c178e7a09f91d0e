"""A robot's global pose between merges: the last merged pose of the submap its tracking placed a
scan in, composed with the scan's pose in that submap.

The merger places submaps every second or two; a robot scans five times a second. Each placed
scan names its submap and its pose there (:class:`~fleetmap.shared.messages.Scan`), so its pose in
the global map is ``frames[submap] * scan.pose`` with the frames of the last merge
(:meth:`fleetmap.merger.service.Merger.pose_frames`): poses stream at scan rate and move with the
map when a merge refines it. A scan in a submap no merge has placed yet (a robot's newest, or one
never merged), an unplaced scan or one of an older epoch says nothing: the last pose stands until a
merge or a placed scan gives a new one, never a guess.
"""

from __future__ import annotations

import threading

from fleetmap.shared.geometry import Transform2D
from fleetmap.shared.messages import RobotPose, Scan

Frames = dict[str, tuple[int, Transform2D]]
"""Per submap key: the global map component it is in, and its pose in that component's frame."""


class PoseFollower:
    """Robot poses from the last merge's frames and the newest placed scans (thread-safe: scans
    arrive on one thread, merges on another)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._frames: Frames = {}
        self._latest: dict[str, Scan] = {}
        """Each robot's newest placed scan of its newest epoch."""
        self._said: dict[str, float] = {}
        """The stamp of the last pose given for each robot (never one older after it)."""

    def merged(self, frames: Frames) -> None:
        """A merge landed: its submaps' frames replace the previous ones."""
        with self._lock:
            self._frames = frames

    def scan(self, scan: Scan) -> RobotPose | None:
        """A robot's scan: its pose in the global map, if the scan is its newest and lies in a
        placed submap (else None: nothing to say)."""
        if scan.pose is None or scan.submap is None:
            return None
        with self._lock:
            held = self._latest.get(scan.robot)
            if held is not None and (scan.epoch, scan.stamp) < (held.epoch, held.stamp):
                return None
            self._latest[scan.robot] = scan
            return self._pose(scan)

    def current(self, robot: str, epoch: int, stamp: float) -> RobotPose | None:
        """The robot's pose from its newest placed scan with the current frames, if that scan is of
        ``epoch`` and newer than ``stamp`` (a merge's own pose of the robot, from its submaps)."""
        with self._lock:
            held = self._latest.get(robot)
            if held is None or held.epoch != epoch or held.stamp <= stamp:
                return None
            return self._pose(held)

    def said_after(self, robot: str, epoch: int, stamp: float) -> bool:
        """Whether a pose of the robot's ``epoch`` newer than ``stamp`` was given already."""
        with self._lock:
            held = self._latest.get(robot)
            return held is not None and held.epoch == epoch and self._said.get(robot, -1.0) > stamp

    def _pose(self, scan: Scan) -> RobotPose | None:
        assert scan.pose is not None
        frame = self._frames.get(f"{scan.robot}/{scan.epoch}/{scan.submap}")
        if frame is None or scan.stamp < self._said.get(scan.robot, -1.0):
            return None
        self._said[scan.robot] = scan.stamp
        component, pose = frame
        return RobotPose(scan.robot, scan.epoch, scan.stamp, pose.compose(scan.pose), component)
