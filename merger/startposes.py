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
error swinging the other robot about the hub). Only pairs through the hub get the two priors'
covariance exactly; a pair of two other robots gets the hub's prior twice (looser than the truth).

The pose graph takes these links as the weakest edges of its forest, after every integration
(:meth:`~fleetmap.merger.posegraph.PoseGraph.solve`): an integration between two robots is judged
as any join is (the pairs it then makes bear it out, no rival alignment holds as well), and a start
pose unites only what no integration joins, so robots with start poses are one component from their
first submaps. Once integrations join them, the start link closes a cycle and weighs in the
refinement by its covariance, far less than the integrations: a start pose 3 m off is corrected
where the maps meet. Taken before the integrations (as a robot's own links are), a loose start
pose would let any integration within its metres of uncertainty in unjudged, as a loop closure
(the warehouse: aisles 14 m apart alike, a robot placed 17 m off with its true start pose).

Where the merger searches, robots held together by start poses alone count as apart
(:attr:`~fleetmap.merger.outputs.Placement.groups`): they search each other pose-free as robots
nobody placed do, and a pair of them is not registered near where the start poses put it (metres
off, where registration reaches centimetres), until an integration ties them.
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
