"""What the merger publishes after a step, from what its last solve placed where.

- ``GlobalMap``: every component of the graph (anchor, member submaps, their poses, fused
  walls), the largest first;
- ``RobotPose`` for every robot: its pose in its component's frame, composed from its newest
  submap's pose and its pose in that submap; *unknown* (None, never a guess) while its current
  epoch is merged with no other epoch (a kidnapped robot not relocalized yet), except a robot's
  first epoch when it is the largest component (it is the global map);
- ``FleetEvent`` "relocalized" when a later epoch of a robot is placed for the first time;
- on request, every scan's pose (:func:`scan_poses`, what ``fleetmap map`` writes to ``poses.csv``).

:class:`Placement` indexes one solve's result (which component holds each submap and each epoch);
the pair schedule (:mod:`fleetmap.merger.schedule`) reads it too.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field, replace

import numpy as np
from fleetmap.merger.graph import Component as GraphComponent
from fleetmap.merger.graph import MergeResult
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.scangraph import SCAN_CONSTRAINTS, IntegrationEdge, KeyScan, follow_key_scans, refine_key_scans
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys, parse_submap_key
from fleetmap.shared.io.messages import Component, FleetEvent, GlobalMap, LocalMap, RobotPose
from fleetmap.shared.io.occupancy import placed_scans


@dataclass(frozen=True)
class Outgoing:
    key: str
    payload: bytes


@dataclass
class Robot:
    """What the merger knows of a robot."""

    epoch: int = 0
    stamp: float = 0.0
    """Stamp of the robot's newest submap that says where it is: when its pose there was true."""
    at: tuple[str, Transform2D] | None = None
    """The robot's newest pose: (submap key, pose in that submap); None when it is lost."""
    relocalized: set[int] = field(default_factory=set)
    present: bool = False
    live: bool = False
    """A message of it was taken since its liveliness token appeared (what ``max_robots`` counts,
    with ``present``, in a live merger)."""
    epochs: set[int] = field(default_factory=set)
    """The epochs of it the merger took a submap of."""
    refused: set[int] = field(default_factory=set)
    """Epochs of a second agent under its id, and those that descend from them."""


@functools.lru_cache(maxsize=1 << 16)
def epoch_of(key: str) -> str:
    """The ``robot/epoch`` a submap key belongs to (kept: every step asks it of every submap)."""
    robot, epoch, _ = parse_submap_key(key)
    return f"{robot}/{epoch}"


def _shape(result: MergeResult) -> tuple[tuple[int, ...], ...]:
    """What :meth:`Placement.of` reads of a result, by identity: its components and its edges."""
    return tuple(map(id, result.components)), tuple(map(id, result.tree)), tuple(map(id, result.loops))


@dataclass(frozen=True)
class Placement:
    """One solve's result, indexed: which component holds each submap and each epoch, and which
    epochs each component holds (none before the first solve)."""

    result: MergeResult | None = None
    where: dict[str, int] = field(default_factory=dict)
    epoch_where: dict[str, int] = field(default_factory=dict)
    epochs_in: list[set[str]] = field(default_factory=list)
    ties: dict[str, str] = field(default_factory=dict)
    """Each epoch tied to others by integrations, with the one that stands for its group."""
    groups: dict[str, list[str]] = field(default_factory=dict)
    """The submaps the integrations place together, by the epoch that stands for them (each
    component, split where only known start poses hold it together:
    :mod:`fleetmap.merger.startposes`), in the components' order."""

    @classmethod
    def of(cls, result: MergeResult | None, last: Placement | None = None) -> Placement:
        """The result indexed. Where the ``last`` placement's result holds the same components and
        edges (a kept solve that only took new versions of submaps), its index is reused, so that
        such a step costs what it adds (issue 49); its result keeps those objects, and so their
        identities, alive."""
        if (
            result is not None
            and last is not None
            and last.result is not None
            and _shape(last.result) == _shape(result)
        ):
            return replace(last, result=result)
        where: dict[str, int] = {}
        epoch_where: dict[str, int] = {}
        epochs_in: list[set[str]] = []
        for i, c in enumerate(result.components if result is not None else []):
            epochs = {epoch_of(k) for k in c.members}
            epochs_in.append(epochs)
            for k in c.members:
                where[k] = i
            for epoch in epochs:
                epoch_where.setdefault(epoch, i)
        ties: dict[str, str] = {}

        def group(epoch: str) -> str:
            while ties.get(epoch, epoch) != epoch:
                epoch = ties[epoch]
            return epoch

        for e in [*result.tree, *result.loops] if result is not None else []:
            if not e.link and e.a in where and e.b in where:
                a, b = group(epoch_of(e.a)), group(epoch_of(e.b))
                if a != b:
                    ties[max(a, b)] = ties[min(a, b)] = min(a, b)
        groups: dict[str, list[str]] = {}
        for c in result.components if result is not None else []:
            for k in c.members:
                groups.setdefault(group(epoch_of(k)), []).append(k)
        return cls(result, where, epoch_where, epochs_in, {epoch: group(epoch) for epoch in ties}, groups)

    def group_of(self, key: str) -> list[str] | None:
        """The submaps the integrations place with a submap (None: not placed)."""
        if key not in self.where:
            return None
        epoch = epoch_of(key)
        return self.groups.get(self.ties.get(epoch, epoch))

    @functools.cached_property
    def global_group(self) -> frozenset[str]:
        """The global map's submaps as its integrations place them: the group of the largest
        component's anchor, when it holds more than one epoch (else none)."""
        if self.result is None or not self.result.components:
            return frozenset()
        group = self.group_of(self.result.components[0].anchor) or []
        return frozenset(group) if len({epoch_of(k) for k in group}) > 1 else frozenset()

    def tied(self, a: str, b: str) -> bool:
        """Whether two submaps are of one epoch, or of epochs the last solve's integrations tie
        (not a robot's start pose alone: :mod:`fleetmap.merger.startposes`)."""
        ea, eb = epoch_of(a), epoch_of(b)
        return ea == eb or (ea in self.ties and self.ties[ea] == self.ties.get(eb))

    def component_of(self, key: str) -> GraphComponent | None:
        index = self.where.get(key)
        return None if index is None or self.result is None else self.result.components[index]

    def placed_epoch(self, epoch_key: str) -> bool:
        """Whether an epoch shares its component with another epoch (the fleet knows where it is)."""
        index = self.epoch_where.get(epoch_key)
        return index is not None and len(self.epochs_in[index]) > 1

    def gives_poses(self, index: int, epoch: int) -> bool:
        """Whether a robot's pose may be given in component ``index`` for its epoch ``epoch``: the
        component merges it with another epoch, or it is a first epoch in the largest component
        (a robot alone, or the first of the fleet)."""
        return len(self.epochs_in[index]) > 1 or (epoch == 0 and index == 0)

    def robot_pose(self, r: Robot) -> tuple[Transform2D | None, int | None]:
        """A robot's pose in its component's frame and the component's index; (None, None) if unknown."""
        if r.at is None or self.result is None:
            return None, None
        key, in_submap = r.at
        index = self.where.get(key)
        if index is None:
            return None, None
        if not self.gives_poses(index, r.epoch):
            return None, None  # a later epoch merged with nothing: the robot is lost, not guessed
        return self.result.components[index].poses[key].compose(in_submap), index

    def pose_frames(self) -> dict[str, tuple[int, Transform2D]]:
        """Per submap a robot's pose may be given in (:meth:`robot_pose`'s rule): its component
        and its pose there (:mod:`fleetmap.merger.follow`)."""
        frames: dict[str, tuple[int, Transform2D]] = {}
        for i, component in enumerate(self.result.components if self.result is not None else []):
            for key in component.members:
                _, epoch, _ = parse_submap_key(key)
                if self.gives_poses(i, epoch):
                    frames[key] = (i, component.poses[key])
        return frames


def global_map_of(
    result: MergeResult, seq: int, stamp: float, made: dict[int, tuple[GraphComponent, Component]] | None = None
) -> GlobalMap:
    """The global map message of a solve. ``made``: the message components of the last call, by
    the solve's component, which a component the solve left as it was reuses (a step costs what
    it changed; the dict is updated to this call's)."""
    held = dict(made) if made is not None else {}
    components = []
    for c in result.components:
        pair = held.get(id(c))
        if pair is None or pair[0] is not c:
            pair = (c, Component(c.anchor, tuple(c.members), dict(c.poses), np.asarray(c.segments)))
        components.append(pair[1])
        if made is not None:
            made[id(c)] = pair
    if made is not None:
        for key in set(made) - {id(c) for c in result.components}:
            del made[key]
    return GlobalMap(seq, stamp, tuple(components))


def robot_pose_messages(
    keys: FleetKeys, robots: dict[str, Robot], submaps: dict[str, LocalMap], placement: Placement, stamp: float
) -> list[Outgoing]:
    """Every robot's pose (a robot with no submap yet says nothing), and a "relocalized" event for
    each later epoch placed for the first time (noted in its :class:`Robot`)."""
    out = []
    for robot in sorted(robots):
        r = robots[robot]
        if r.at is None and not any(k.startswith(f"{robot}/{r.epoch}/") for k in submaps):
            continue  # no submap yet: nothing to say
        pose, index = placement.robot_pose(r)
        out.append(Outgoing(keys.pose(robot), RobotPose(robot, r.epoch, r.stamp, pose, index).to_msgpack()))
        if pose is not None and r.epoch > 0 and r.epoch not in r.relocalized:
            r.relocalized.add(r.epoch)
            detail = json.dumps({"epoch": r.epoch, "component": index})
            out.append(Outgoing(keys.events, FleetEvent("relocalized", robot, stamp, detail).to_msgpack()))
    return out


def scan_poses(
    result: MergeResult | None,
    submaps: dict[str, LocalMap],
    graph: PoseGraph,
    key_scans: dict[str, list[KeyScan]],
    config: FleetmapConfig,
    stats: MergerStats,
) -> dict[tuple[str, int], tuple[int, Transform2D]]:
    """Every scan ``result`` placed, by (robot, index): its component's number and its laser pose in
    that component's frame; with ``SCAN_CONSTRAINTS``, the key scans
    registered on the submaps they revisit and all refined together (:mod:`fleetmap.merger.scangraph`),
    else its submap's pose composed with its pose in the submap. Counts the registrations in ``stats``."""
    out: dict[tuple[str, int], tuple[int, Transform2D]] = {}
    if result is None:
        return out
    tables = {
        k: (m.scan_indices, m.scan_poses)
        for k, m in submaps.items()
        if m.scan_indices is not None and m.scan_poses is not None
    }
    links = {e.b: (e.a, e.transform) for e in graph.links}
    edges = [e for e in (*result.tree, *result.loops) if not e.link]
    stats.scan_registrations = stats.scan_constraints = 0
    for n, c in enumerate(result.components):
        placed = placed_scans(c.poses, tables)
        if SCAN_CONSTRAINTS:
            keys = [k for key in c.members for k in key_scans.get(key, ())]
            walls = {key: np.asarray(submaps[key].segments) for key in c.members if key in submaps}
            integrations = [
                IntegrationEdge(e.a, e.b, e.transform, graph.edge_noise(e, robust=False), graph.edge_noise(e))
                for e in edges
                if e.a in c.poses and e.b in c.poses
            ]
            refined = refine_key_scans(keys, c.poses, c.anchor, walls, links, integrations, config.tracking)
            stats.scan_registrations += refined.registrations
            stats.scan_constraints += refined.constraints
            poses = follow_key_scans(placed, keys, refined.poses, c.poses)
        else:
            poses = {scan: pose for scan, (_, pose) in placed.items()}
        for scan, pose in poses.items():
            out.setdefault(scan, (n, pose))
    return out
