"""Known start poses: robots placed from their first submap, refined where their maps meet.

Dugarjav & Lee (2015), Section III: when the robots' start poses in one frame are known (measured
at the dock, given by a fleet manager), their local maps are merged from those poses at once, and
where the robots meet, matching their maps aligns them again. Here a start pose is a prior on its
robot's first submap (epoch 0, submap 0: its frame is the laser's pose at the robot's first placed
scan), as uncertain as ``MergeParams.start_pose_sigma_translation`` and
``start_pose_sigma_rotation`` in the shared frame.

The shared frame is not a node of the pose graph (it has no walls to integrate, draw or fuse):
each prior enters as a link between two robots' first submaps, from the first robot with a start
pose whose first submap the merger took (the *hub*) to each later one, its transform the two start
poses' relative pose and its covariance what the two priors give it (first order, the hub's heading
error swinging the other robot about the hub). A link is what the pose graph already holds a
robot's own chain with: its forest takes it first, its cycle check allows what it can be off by,
and its refinement weighs it by its covariance, so robots with start poses are one component from
their first submaps, and where their maps overlap the integrations, far firmer than a start pose,
pull them right (an integration that closes the cycle through a start link is a loop closure, as
one through a robot's drifting chain is). Only pairs through the hub get the two priors' covariance
exactly; a pair of two other robots gets the hub's prior twice (looser than the truth: the cycle
check allows a little more).

A pair of robots tied by nothing but start poses is not registered near where they put it
(:meth:`~fleetmap.merger.outputs.Placement.tied`): the start poses are metres off where
registration reaches centimetres, so such a pair is integrated pose-free, as robots nobody placed
are, until an integration ties them.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable

import numpy as np
from fleetmap.merger.joins import JoinJudge
from fleetmap.shared.config import MergeParams
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import parse_submap_key

log = logging.getLogger(__name__)


def relative_prior(hub: Transform2D, other: Transform2D, sigma_t: float, sigma_r: float) -> tuple[Transform2D, Array]:
    """``other``'s start pose in ``hub``'s frame, and its covariance (3x3, on ``x, y, theta`` of
    that relative pose) when each start pose is off by ``sigma_t`` (m, each axis) and ``sigma_r``
    (rad) in the shared frame, independently: both translations add ``sigma_t^2`` each, both
    headings ``sigma_r^2``, and the hub's heading error also swings ``other`` about the hub."""
    t = hub.inverse().compose(other)
    swing = np.array([t.y, -t.x, -1.0])  # d(x, y, theta of t) / d(hub's heading)
    covariance = np.diag([2.0 * sigma_t**2, 2.0 * sigma_t**2, sigma_r**2]) + sigma_r**2 * np.outer(swing, swing)
    return t, covariance


class StartFrame:
    """The known start poses of a fleet (robot id -> the laser's start pose in the shared frame),
    put into a pose graph as links between the robots' first submaps (see the module)."""

    def __init__(self, poses: dict[str, Transform2D], merge: MergeParams) -> None:
        for name in ("start_pose_sigma_translation", "start_pose_sigma_rotation"):
            if not getattr(merge, name) > 0:
                raise BadInput(name, f"must be positive with start poses, got {getattr(merge, name)!r}")
        self.poses = dict(poses)
        self.merge = merge
        self.hub: str | None = None
        """The first submap the others' priors are linked from."""
        self._firsts: list[str] = []
        """The first submaps of the robots with a start pose, in the order the graph took them."""
        self._said: set[str] = set()

    def warn_unknown(self, robots: Iterable[str], what: str) -> list[str]:
        """Warn of the start poses given for none of ``robots`` (``what`` names where they come
        from); the robots named, sorted."""
        known = set(robots)
        unknown = sorted(set(self.poses) - known)
        if unknown:
            log.warning(
                "start poses given for %s, which %s does not hold (%s): not used",
                ", ".join(unknown),
                what,
                ", ".join(sorted(known)) or "none",
            )
        return unknown

    def enter(self, graph: JoinJudge, key: str) -> None:
        """A submap the graph has just taken: the first submap of a robot with a start pose is
        linked to the hub (or becomes it); a hub the graph forgot is replaced by the next first
        submap, and the first submaps it held are linked to that."""
        robot, epoch, submap = parse_submap_key(key)
        if epoch != 0 or submap != 0:
            return
        if robot not in self.poses:
            if self.poses and robot not in self._said:
                self._said.add(robot)
                log.info("robot %s has no start pose: it is merged by its maps alone", robot)
            return
        if key not in self._firsts:
            self._firsts.append(key)
        if self.hub is None or self.hub not in graph:
            self.hub = next(k for k in self._firsts if k in graph)
        for k in self._firsts:
            if k == self.hub or k not in graph:
                continue
            held = graph.link_to(k)
            if held is not None and held.a == self.hub:
                continue
            t, covariance = relative_prior(
                self.poses[parse_submap_key(self.hub)[0]],
                self.poses[parse_submap_key(k)[0]],
                self.merge.start_pose_sigma_translation,
                self.merge.start_pose_sigma_rotation,
            )
            graph.put_link(self.hub, k, t, covariance)
            log.debug("%s placed from its start pose: %.2f m, %.1f deg from %s", k, math.hypot(t.x, t.y),
                      math.degrees(t.theta), self.hub)  # fmt: skip
