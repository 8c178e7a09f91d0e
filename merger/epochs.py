"""A robot's submaps of one epoch chained into one map by their links (pure).

An agent publishes its path as small overlapping submaps, each linked to the previous one by its
own tracking (:mod:`fleetmap.agents.tracker`). :class:`EpochMaps` keeps the latest version of
every submap and chains each epoch's submaps into one map in the epoch's frame (submap 0's): the
submaps' walls and viewpoints placed by the composition of the links, and the robot's pose in the
epoch from the newest submap that says where the robot is. A submap whose predecessor has not
arrived yet waits: the chain stops at the first gap.

A local map of the pivot front end, or of a recording made before submaps, is submap 0 with no
link: its epoch's map is that map itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fleetmap.shared.geometry import Array, Transform2D
from fleetmap.shared.mapgrid import moved_viewpoints
from fleetmap.shared.messages import LocalMap


@dataclass(frozen=True)
class EpochMap:
    """One epoch of one robot as a single map, in the epoch's frame."""

    robot: str
    epoch: int
    segments: Array
    viewpoints: Array
    scans: int
    pose: Transform2D | None
    """The robot's pose in the epoch's frame, by its newest submap that says it (None: unknown)."""
    stamp: float
    """When ``pose`` was true (the stamp of the submap version that gave it); the newest submap's
    stamp when the pose is unknown."""
    submap_poses: dict[int, Transform2D]
    """Each chained submap's frame in the epoch's frame."""


class EpochMaps:
    """The latest version of every submap, by robot and epoch; :meth:`put` one, :meth:`epoch` to read."""

    def __init__(self) -> None:
        self._submaps: dict[tuple[str, int], dict[int, LocalMap]] = {}
        self._newest: dict[tuple[str, int], LocalMap] = {}
        """Per epoch, the newest submap message (by stamp, then arrival) that says where the robot is."""

    def held(self, m: LocalMap) -> LocalMap | None:
        """The version held of ``m``'s submap."""
        return self._submaps.get((m.robot, m.epoch), {}).get(m.submap)

    def put(self, m: LocalMap) -> bool:
        """Keep ``m`` if it is newer than the version held of its submap; whether it was."""
        held = self.held(m)
        if held is not None and m.version <= held.version:
            return False
        self._submaps.setdefault((m.robot, m.epoch), {})[m.submap] = m
        newest = self._newest.get((m.robot, m.epoch))
        says_where = m.pose is not None or not m.final  # a finished submap no longer holds the robot
        if says_where and (newest is None or m.stamp >= newest.stamp):
            self._newest[(m.robot, m.epoch)] = m
        return True

    def messages(self) -> list[LocalMap]:
        """The latest version of every submap held, by robot, epoch and submap."""
        return [self._submaps[key][k] for key in sorted(self._submaps) for k in sorted(self._submaps[key])]

    def epoch(self, robot: str, epoch: int) -> EpochMap | None:
        """The epoch's chained map, or None before its submap 0 has arrived."""
        submaps = self._submaps.get((robot, epoch), {})
        if 0 not in submaps:
            return None
        poses = {0: Transform2D()}
        k = 0
        while k + 1 in submaps and submaps[k + 1].link is not None:
            link = submaps[k + 1].link
            assert link is not None
            poses[k + 1] = poses[k].compose(link.transform)
            k += 1
        segments = [poses[i].apply(np.asarray(submaps[i].segments)) for i in poses]
        views = [
            moved_viewpoints(np.asarray(submaps[i].viewpoints), poses[i])
            for i in poses
            if submaps[i].viewpoints is not None
        ]
        newest = self._newest.get((robot, epoch))
        pose = None
        stamp = max(submaps[i].stamp for i in poses)
        if newest is not None and newest.pose is not None and newest.submap in poses:
            pose = poses[newest.submap].compose(newest.pose)
            stamp = newest.stamp
        return EpochMap(
            robot,
            epoch,
            np.vstack(segments) if segments else np.zeros((0, 4)),
            np.vstack(views) if views else np.zeros((0, 5)),
            sum(submaps[i].scans for i in poses),
            pose,
            stamp,
            poses,
        )
