"""A robot's global pose between merges: the last merged pose of the submap its tracking placed a
scan in, composed with the scan's pose in that submap.

The merger places submaps every second or two; a robot scans five times a second. Each placed
scan names its submap and its pose there (:class:`~fleetmap.shared.io.messages.Scan`), so its pose in
the global map is ``frames[submap] * scan.pose`` with the frames of the last merge
(:meth:`fleetmap.merger.engine.Merger.pose_frames`): poses stream at scan rate and move with the
map when a merge refines it. A scan in a submap no merge has placed yet (a robot's newest, or one
never merged), an unplaced scan or one of an older epoch says nothing: the last pose stands until a
merge or a placed scan gives a new one, never a guess.

Which scan is newer is the robot's own count (epoch, then scan index), not its stamps: a robot
whose clock steps back (its count going on) starts a new *clock epoch*, ordered after the one
before, instead of having every later pose judged older than the last one said.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.messages import RobotPose, Scan

Frames = dict[str, tuple[int, Transform2D]]
"""Per submap key: the global map component it is in, and its pose in that component's frame."""


class PoseFollower:
    """Robot poses from the last merge's frames and the newest placed scans, each said (``say``,
    e.g. published) under one lock, so a robot's poses go out in stamp order whichever thread
    says them (scans arrive on one thread, merges on another)."""

    def __init__(self, say: Callable[[RobotPose], object] | None = None, max_robots: int | None = None) -> None:
        self._say = say if say is not None else (lambda pose: None)
        self.max_robots = max_robots
        self._lock = threading.Lock()
        self._frames: Frames = {}
        self._latest: dict[str, Scan] = {}
        """Each robot's newest placed scan of its newest epoch."""
        self._said: dict[str, tuple[int, int, float]] = {}
        """(epoch, clock epoch, stamp) of the last pose said of each robot: never an older one after it."""
        self._clock: dict[str, int] = {}
        """Per robot: how many times its clock stepped back while its scan count went on."""
        self.clock_steps = 0
        """Clock epochs started, all robots together."""

    def merged(self, frames: Frames) -> None:
        """A merge landed: its submaps' frames replace the previous ones."""
        with self._lock:
            self._frames = frames

    def scan(self, scan: Scan) -> RobotPose | None:
        """A robot's scan: its pose in the global map, said, if the scan is its newest and lies in
        a placed submap (else None: nothing said)."""
        if scan.pose is None or scan.submap is None:
            return None
        with self._lock:
            held = self._latest.get(scan.robot)
            if held is None and self.max_robots is not None and len(self._latest) >= self.max_robots:
                return None
            if held is not None:
                if (scan.epoch, scan.index) <= (held.epoch, held.index):
                    return None  # older, or again
                if scan.epoch == held.epoch and scan.stamp < held.stamp:
                    self._clock[scan.robot] = self._clock.get(scan.robot, 0) + 1
                    self.clock_steps += 1
            self._latest[scan.robot] = scan
            return self._said_from(scan)

    def step(self, pose: RobotPose) -> RobotPose | None:
        """A merge's own pose of a robot (from its submaps): said as the robot's newest placed scan
        puts it under the new frames where that scan is newer, else as it is; not said (None) if
        older than the last pose said of the robot."""
        with self._lock:
            held = self._latest.get(pose.robot)
            clock = self._clock.get(pose.robot, 0)
            same = held is not None and held.epoch == pose.epoch
            if held is not None and same and (held.stamp > pose.stamp or clock):
                fresher = self._said_from(held)
                if fresher is not None:
                    return fresher
            if held is not None and same and clock and pose.stamp > held.stamp:
                clock -= 1  # stamped past the newest scan since the robot's clock stepped back: of the clock before
            said = (pose.epoch, clock, pose.stamp)
            if said < self._said.get(pose.robot, (-1, -1, -1.0)):
                return None
            self._said[pose.robot] = said
            self._say(pose)
            return pose

    def _said_from(self, scan: Scan) -> RobotPose | None:
        assert scan.pose is not None
        frame = self._frames.get(f"{scan.robot}/{scan.epoch}/{scan.submap}")
        said = (scan.epoch, self._clock.get(scan.robot, 0), scan.stamp)
        if frame is None or said < self._said.get(scan.robot, (-1, -1, -1.0)):
            return None
        component, at = frame
        pose = RobotPose(scan.robot, scan.epoch, scan.stamp, at.compose(scan.pose), component)
        self._said[scan.robot] = said
        self._say(pose)
        return pose
