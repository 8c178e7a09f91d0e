"""The merger service: local maps in, global maps and robot poses out.

:class:`Merger` is the whole logic as a library (no network, no clock): ``receive`` takes the bytes
of a bus message, ``step`` integrates what arrived since the last step into the map graph
(:mod:`fleetmap.merger.graph`) and returns the messages to publish. It is deterministic given the
same messages in the same order, which is what lets a recorded session replay to the same map:
every step is published as a :class:`~fleetmap.shared.messages.MergerStep` naming the local map
versions it took, in order, and how many pairs of maps it integrated, and a replay follows those
steps. New versions enter the graph at once; their integrations with the other maps wait in a
queue, lost robots' first, and the live service gives each step a time budget (a step that
integrated every new version with every map took seconds in a warehouse, while a kidnapped
robot's next map waited).

What it publishes after a step:

- ``GlobalMap``: every component of the graph (anchor, members, poses, fused segments), the
  largest first;
- ``RobotPose`` for every robot: its pose in its component's frame, composed from the pose of its
  current local map and its pose in that map. A robot whose current epoch is merged with nothing
  (a kidnapped robot that has not been relocalized yet) is reported *unknown*: pose None, never a
  guess. A robot's first epoch, before anything merges, is placed only if it is the largest
  component (it is the global map);
- ``MergeEdge`` for every integration computed in the step, ``MergerStep``, and ``FleetEvent``
  "relocalized" when a later epoch of a robot is placed for the first time.

:class:`MergerService` wraps it for a bus: subscriptions, a queryable with the current global map
(a late viewer or a rejoining robot gets it at once), presence from liveliness tokens, and an
optional state file that a restarted merger loads (:meth:`Merger.save_state`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from fleetmap.merger.epochs import EpochMaps
from fleetmap.merger.graph import Edge, MapGraph, MergeResult
from fleetmap.shared.bus import Bus, Handle
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.errors import BadInput
from fleetmap.shared.geometry import Transform2D
from fleetmap.shared.integration import max_map_violation
from fleetmap.shared.keys import FleetKeys
from fleetmap.shared.mapfile import SegmentMap
from fleetmap.shared.mapgrid import viewpoints_of, with_viewpoints
from fleetmap.shared.messages import (
    BadMessage,
    Component,
    FleetEvent,
    GlobalMap,
    LocalMap,
    MergeEdge,
    MergerStep,
    RobotPose,
    Scan,
    decode,
)

log = logging.getLogger(__name__)

STATE_VERSION = 1

STALE_VERSIONS = 2
"""A lost robot's pair integrated this many versions of its map ago is worth another try (a robot
that starts an epoch publishes its map after every scan: two more scans)."""

URGENT_RUN = 2
"""Lost robots' promising pairs a merger integrates for one of the others' (when both wait)."""

CARRIED_STEPS = 4
"""How many of its longest steps a robot may drive between its previous epoch's last placed scan and
its new epoch's first before an integration of the two says it was carried (:meth:`Merger._carried`):
two scans to the break, and two for the last placed scans of an epoch about to break, the least
sure (in the warehouse, r1's last scan of epoch 2 had slid 2.4 m along its lane; r3's epoch 2,
merged two racks back, put its first scan 5.8 m from epoch 1's last, four steps 4.8 m)."""

STEP_SECONDS = 0.25
"""The live service's time budget for one step's integrations: a step ends after the first
integration that finds this much time gone. A lost robot's newest map waits for the step under
way to end, then goes first in the next (its promising pairs do); shorter steps give lost robots
their turns more often, for a little more per-step work (solve, global map, state file). Half a
second cost the live warehouse kidnap a scan or two in about half the runs (README, "Kidnapped
robots")."""


@dataclass(frozen=True)
class Outgoing:
    key: str
    payload: bytes


@dataclass
class MergerStats:
    received: Counter[str] = field(default_factory=Counter)
    """Messages received, per schema."""
    malformed: int = 0
    malformed_reasons: Counter[str] = field(default_factory=Counter)
    """Malformed messages per 'schema field' (what was wrong)."""
    ignored: int = 0
    """Well-formed messages not meant for the merger on the key they came on."""
    stale: int = 0
    """Local maps older than (or as old as) the version already held."""
    steps: int = 0
    lost_first: int = 0
    """Steps that began with a lost robot's pair while other pairs waited behind it."""
    carried_refused: int = 0
    """Integrations of a robot's consecutive epochs taken as invalid: they said the robot was
    carried, on too little evidence (``MergeParams.carried_max_ambiguity``)."""
    integrations: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {
            "received": dict(self.received),
            "malformed": self.malformed,
            "malformed_reasons": dict(self.malformed_reasons),
            "ignored": self.ignored,
            "stale": self.stale,
            "steps": self.steps,
            "lost_first": self.lost_first,
            "integrations": self.integrations,
        }


@dataclass
class _Robot:
    epoch: int = 0
    stamp: float = 0.0
    """Stamp of the robot's latest local map: when its pose in that map was true."""
    pose_in_map: dict[int, Transform2D | None] = field(default_factory=dict)
    relocalized: set[int] = field(default_factory=set)
    present: bool = False


class Merger:
    """The merger's logic: :meth:`receive` messages, :meth:`step`, publish what it returns."""

    def __init__(self, keys: FleetKeys, config: FleetmapConfig | None = None) -> None:
        self.keys = keys
        self.config = config or FleetmapConfig()
        self.graph = MapGraph(self.config.integration, self.config.merge, anchor="first")
        self.stats = MergerStats()
        self.seq = 0
        self.stamp = 0.0
        self.links: dict[str, str] = {}
        """New epoch's map key -> the previous epoch's (the graph links the epochs of a robot)."""
        self._pending: dict[str, LocalMap] = {}
        """Submap versions received since the last step, by submap key, in arrival order."""
        self.epochs = EpochMaps()
        """Every robot's submaps, chained into one map per epoch (the map graph's nodes)."""
        self._robots: dict[str, _Robot] = {}
        self._result: MergeResult | None = None
        self._global: GlobalMap | None = None
        self._queue: dict[tuple[str, str], None] = {}
        """Pairs of maps to integrate (an ordered set: the oldest first), each as (S1, S2)."""
        self._urgent_run = 0
        """Promising pairs of lost robots taken since the last of the rest (see :meth:`_work_lists`)."""
        self._last_out: list[Outgoing] = []
        """The last step's messages as published (kept in the state: see :meth:`where_it_stands`)."""

    # -- input -----------------------------------------------------------------------------
    def receive(self, key: str, payload: bytes) -> list[Outgoing]:
        """Take one message off the bus; a malformed one is dropped, logged and counted."""
        try:
            message = decode(payload)
        except BadMessage as exc:
            self.stats.malformed += 1
            self.stats.malformed_reasons[f"{exc.schema} {exc.field}"] += 1
            if self.stats.malformed <= 20 or self.stats.malformed % 1000 == 0:
                log.warning("dropped a malformed message on %s: %s (%d so far)", key, exc, self.stats.malformed)
            return []
        self.stats.received[message.SCHEMA] += 1
        if isinstance(message, LocalMap):
            if key != self.keys.localmap(message.robot):
                self.stats.ignored += 1
                return []
            self._take_local_map(message)
        elif isinstance(message, Scan):
            self._robot(message.robot)  # a robot that only scans so far is known, not placed
        elif isinstance(message, FleetEvent) and message.kind == "epoch" and message.robot is not None:
            self._robot(message.robot)
        else:
            self.stats.ignored += 1
        return []

    def _robot(self, name: str) -> _Robot:
        return self._robots.setdefault(name, _Robot())

    def _take_local_map(self, m: LocalMap) -> None:
        key = m.submap_key
        held = self.epochs.held(m)
        waiting = self._pending.get(key)
        if (held is not None and m.version <= held.version) or (waiting is not None and m.version <= waiting.version):
            self.stats.stale += 1
            return
        if len(m.segments) == 0:
            self.stats.ignored += 1
            return
        # Arrival order of the first version decides the order of a step; later versions replace it.
        self._pending[key] = m

    def presence(self, robot: str, present: bool, stamp: float) -> list[Outgoing]:
        """A robot's liveliness token appeared or went: a join or leave event. Its maps stay."""
        r = self._robot(robot)
        r.present = present
        kind = "join" if present else "leave"
        return [Outgoing(self.keys.events, FleetEvent(kind, robot, max(stamp, 0.0)).to_msgpack())]

    @property
    def pending(self) -> int:
        return len(self._pending)

    # -- one step --------------------------------------------------------------------------
    @property
    def has_work(self) -> bool:
        """Whether a step has something to do: local maps pending, or pairs still to integrate."""
        return bool(self._pending) or bool(self._queue)

    @property
    def queued(self) -> int:
        """Pairs of maps still to integrate."""
        return len(self._queue)

    def step(self, limit: int | None = None, enough: Callable[[], bool] | None = None) -> list[Outgoing]:
        """Take the local maps received since the last step into the graph, integrate queued pairs,
        and return the messages to publish.

        Every new map version enters the graph at once (its old version's integrations stand
        until replaced) and queues its pairs with the other maps, most similar first. The step
        then integrates queued pairs in the order of :meth:`_work_lists` (lost robots' first):
        all of them, or ``limit`` of them (a replay repeats the live steps), or until ``enough()``
        says the step has taken long enough (the live service's time budget: a step that integrated every new
        version with every map took seconds in a warehouse, while a kidnapped robot's next map
        version waited). The step's MergerStep says how many pairs it took, and how many wait.
        """
        if not self.has_work:
            return []
        batch = list(self._pending.values())
        self._pending.clear()
        changed: dict[tuple[str, int], LocalMap] = {}
        for m in batch:
            if self.epochs.put(m):
                changed.setdefault((m.robot, m.epoch), m)
        for (robot, epoch), first in changed.items():
            self._enter(robot, epoch, first)
        urgent, rest = self._work_lists()
        self.stats.lost_first += bool(urgent) and bool(rest) and self._urgent_run < URGENT_RUN
        new_edges: list[Edge] = []
        taken = 0
        while urgent or rest:
            if (limit is not None and taken >= limit) or (limit is None and enough is not None and taken and enough()):
                break
            if urgent and (self._urgent_run < URGENT_RUN or not rest):
                pair = urgent.pop(0)
                self._urgent_run += 1
            else:
                pair = rest.pop(0)
                self._urgent_run = 0
            del self._queue[pair]
            taken += 1
            computed = self.graph.integrate_pair_once(*pair)
            if computed is not None:
                if (
                    computed.valid
                    and self._carried(computed)
                    and computed.ambiguity > self.config.merge.carried_max_ambiguity
                ):
                    computed = replace(computed, valid=False)
                    self.graph.add_edge(computed)
                    self.stats.carried_refused += 1
                new_edges.append(computed)
        self.seq += 1
        self.stats.steps += 1
        self.stats.integrations += len(new_edges)
        self.stamp = max([self.stamp] + [m.stamp for m in batch])
        out: list[Outgoing] = []
        for e in new_edges:
            t = e.transform
            edge = MergeEdge(e.a, e.b, t.x, t.y, t.theta, max(e.value, 0.0), e.valid, self.stamp)
            out.append(Outgoing(self.keys.edges, edge.to_msgpack()))
        self._result = self.graph.solve()
        self._global = self._global_map(self._result)
        out.append(Outgoing(self.keys.globalmap, self._global.to_msgpack()))
        out += self._robot_poses()
        # Last: whoever sees the step has seen everything it produced (fleetmap run waits on it).
        step = MergerStep(
            self.seq,
            self.stamp,
            tuple(m.submap_key for m in batch),
            tuple(m.version for m in batch),
            integrations=taken,
            queued=len(self._queue),
        )
        out.append(Outgoing(self.keys.steps, step.to_msgpack()))
        self._last_out = out
        return out

    def where_it_stands(self) -> list[Outgoing]:
        """What a merger restored from its state publishes first: its last step's messages again,
        byte for byte (its edges, global map, the robots' poses and events, the MergerStep last;
        nothing before its first step, nothing meant for another fleet).

        A merger killed after saving its state and before publishing that step's messages would
        otherwise never publish them: the robots' republished maps are the versions it already
        holds, so no step follows; whoever waits for those maps to be integrated (``fleetmap
        run``) would wait for ever, and a robot relocalized in that step would never hear it. A
        replay knows the repeated MergerStep for a repeat (:func:`fleetmap.replay.replay`).
        """
        return [o for o in self._last_out if o.key.startswith(self.keys.prefix + "/")]

    def _work_lists(self) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
        """The queued pairs a step integrates: lost robots' promising pairs, best first, and the
        rest, oldest first. The step takes ``URGENT_RUN`` promising pairs for one of the rest,
        counted across steps (a robot lost for long cannot starve the others).

        A robot is lost while its current epoch (after the first) is merged with nothing: its
        pose is unknown. Its promising pairs are those whose last integration was nearly valid
        (only ambiguous: a few more scans may be all it lacks), least ambiguous first, in turn
        with those never integrated and then those last integrated with a version of its map
        ``STALE_VERSIONS`` or more older, the oldest first (in a warehouse, r1's map after its
        kidnap matched r4's from 5 to 7 scans ambiguously, 0.86-0.95 as well elsewhere; at 8
        scans 0.78; at 10 it was valid). The issue asks for the best candidates first; the last versions'
        integrations are the best guide there is. A pair tried with the last version or the one
        before and far from valid waits its turn with the rest: a robot exploring where no one
        has been keeps publishing, and its pairs must not crowd out the fleet's. A robot whose
        previous epoch was placed (the fleet knew where it was: a kidnap) goes before those never
        placed, which take turns (in the warehouse, three robots whose epochs broke at corners
        were lost along with the kidnapped one: median 11 scans to relocalize it live, 10 with it
        first). The lists depend only on the queue and the graph, so a replay of the recorded
        steps repeats them.
        """
        lost_maps = {k for k in self.graph.keys if self._is_lost(k)}
        urgent: list[tuple[tuple[int, float], tuple[str, str]]] = []
        rest: list[tuple[str, str]] = []
        for pair in self._queue:
            promise = self._promise(pair, lost_maps) if pair[0] in lost_maps or pair[1] in lost_maps else None
            if promise is not None and promise[0] < 2:
                urgent.append((promise, pair))
            else:
                rest.append(pair)
        urgent.sort(key=lambda x: x[0])  # stable: the oldest first among equals
        # Within one robot's, a nearly valid pair and an untried one in turn: racks that repeat
        # leave many pairs nearly valid, and the one that becomes valid may not be among them yet.
        by_map: dict[str, tuple[list[tuple[str, str]], list[tuple[str, str]]]] = {}
        for promise, pair in urgent:
            near, untried = by_map.setdefault(pair[0] if pair[0] in lost_maps else pair[1], ([], []))
            (near if promise[0] == 0 else untried).append(pair)
        # Robots whose previous epoch was placed first: the fleet knew where they were (a kidnap).
        # The others after them, in turn, each one's best first (one robot's pair that stays
        # nearly valid version after version must not hold back another's).
        known = [k for k in by_map if k in self.links and self._placed(self.links[k])]
        first = [pair for k in known for pair in _alternate(*by_map[k])]
        turns = [_alternate(*own) for k, own in by_map.items() if k not in known]
        return first + [own[k] for k in range(max(map(len, turns), default=0)) for own in turns if k < len(own)], rest

    def _placed(self, key: str) -> bool:
        """Whether the last solve placed map ``key`` (merged it with another)."""
        return self._result is not None and self._result.poses.get(key) is not None

    def _promise(self, pair: tuple[str, str], lost_maps: set[str]) -> tuple[int, float]:
        """How promising a lost robot's pair is (see :meth:`_work_lists`): (0, ambiguity) if its
        last integration was nearly valid; (1, -age) if it was never integrated, or only with a
        version of the lost map STALE_VERSIONS or more older (the map has grown since); (2, 0)
        otherwise."""
        e = self.graph.edge(*pair)
        if e is None:
            return (1, -math.inf)
        p = self.config.integration
        if e.limited_violation <= max_map_violation(e.value, p) * e.value and e.ambiguity <= p.valid_max_ambiguity:
            return (0, e.ambiguity)
        ends = zip((e.a, e.b), e.versions, strict=True)
        age = max(self.graph.version_of(k) - version for k, version in ends if k in lost_maps)
        return (1, -float(age)) if age >= STALE_VERSIONS else (2, 0.0)

    def _carried(self, e: Edge) -> bool:
        """Whether ``e`` links a robot's previous epoch to the next one (the agent's link) and puts
        the new epoch's first scan farther from the previous epoch's last placed scan than the
        robot can drive in ``CARRIED_STEPS`` of its longest steps in that epoch, plus
        ``witness_translation``: the agent starts an epoch two scans after its last placed one,
        the robot may have driven on at its full speed (a robot that had stopped may start
        again), and that last scan may have slid a little. The maps carry their scans' poses in
        order, not their times. Such an edge says the robot was carried; see
        ``MergeParams.carried_max_ambiguity``."""
        if self.links.get(e.b) == e.a:
            previous, pose = e.a, e.transform
        elif self.links.get(e.a) == e.b:
            previous, pose = e.b, e.transform.inverse()
        else:
            return False
        views = viewpoints_of(self.graph.map_of(previous))[:, 0:2]
        if len(views) < 2:
            return False
        step = float(np.max(np.hypot(*np.diff(views, axis=0).T)))
        reach = CARRIED_STEPS * step + self.config.integration.witness_translation
        return math.hypot(pose.x - views[-1, 0], pose.y - views[-1, 1]) > reach

    def _is_lost(self, key: str) -> bool:
        """Whether ``key`` is the current epoch (after the first) of a robot whose pose is unknown."""
        robot, epoch = key.rsplit("/", 1)
        r = self._robots.get(robot)
        current = r is None or int(epoch) >= r.epoch
        return current and int(epoch) > 0 and not self._placed(key)

    def _enter(self, robot: str, epoch: int, m: LocalMap) -> None:
        """Put an epoch's map, chained from its submaps, into the graph as a new version, and queue
        its pairs (``m``: one of its submaps that changed, for the epoch's link to the previous one)."""
        built = self.epochs.epoch(robot, epoch)
        if built is None or len(built.segments) == 0:
            return
        key = f"{robot}/{epoch}"
        version = self.graph.version_of(key) + 1 if key in self.graph else 0
        r = self._robot(robot)
        if epoch >= r.epoch:
            r.epoch, r.stamp = epoch, built.stamp
        r.pose_in_map[epoch] = built.pose
        if m.previous_epoch_link is not None:
            self.links[key] = f"{robot}/{m.previous_epoch_link.epoch}"
        segment_map = SegmentMap(np.array(built.segments), ordered=False, oriented=True)
        if len(built.viewpoints):
            segment_map = with_viewpoints(segment_map, built.viewpoints)
        if not self.graph.put_map(key, segment_map, version, keep_edges=True):
            return
        for other in self.graph.pairs_for(key):
            pair = (other, key) if other < key else (key, other)
            if pair not in self._queue and not self.graph.is_current(*pair):
                self._queue[pair] = None

    def _global_map(self, result: MergeResult) -> GlobalMap:
        components = tuple(
            Component(c.anchor, tuple(c.members), dict(c.poses), np.asarray(c.segments)) for c in result.components
        )
        return GlobalMap(self.seq, self.stamp, components)

    def robot_pose(self, robot: str) -> tuple[Transform2D | None, int | None]:
        """A robot's pose in its component's frame and the component's index; (None, None) if unknown."""
        r = self._robots.get(robot)
        if r is None or self._result is None or self._global is None:
            return None, None
        key = f"{robot}/{r.epoch}"
        in_map = r.pose_in_map.get(r.epoch)
        index = self._global.component_of(key)
        if in_map is None or index is None:
            return None, None
        component = self._result.components[index]
        merged = len(component.members) > 1
        if not merged and not (r.epoch == 0 and index == 0):
            return None, None  # a later epoch merged with nothing: the robot is lost, not guessed
        return component.poses[key].compose(in_map), index

    def _robot_poses(self) -> list[Outgoing]:
        out = []
        for robot in sorted(self._robots):
            r = self._robots[robot]
            pose, index = self.robot_pose(robot)
            if r.pose_in_map.get(r.epoch, None) is None and f"{robot}/{r.epoch}" not in self.graph:
                continue  # no local map yet: nothing to say
            out.append(Outgoing(self.keys.pose(robot), RobotPose(robot, r.epoch, r.stamp, pose, index).to_msgpack()))
            if pose is not None and r.epoch > 0 and r.epoch not in r.relocalized:
                r.relocalized.add(r.epoch)
                detail = json.dumps({"epoch": r.epoch, "component": index})
                out.append(
                    Outgoing(self.keys.events, FleetEvent("relocalized", robot, self.stamp, detail).to_msgpack())
                )
        return out

    @property
    def global_map(self) -> GlobalMap:
        """The current global map (empty before the first step)."""
        return self._global if self._global is not None else GlobalMap(self.seq, self.stamp, ())

    @property
    def result(self) -> MergeResult | None:
        return self._result

    # -- state file ------------------------------------------------------------------------
    def save_state(self, path: str | Path) -> None:
        """Everything needed to resume: maps (with versions, in insertion order), edges, robots.

        Written to a temporary file and renamed, so a merger killed while saving leaves the
        previous state whole.
        """
        nodes = [
            {
                "key": k,
                "version": self.graph.version_of(k),
                "segments": np.ascontiguousarray(self.graph.map_of(k).segments, dtype="<f8").tobytes(),
                "viewpoints": np.ascontiguousarray(viewpoints_of(self.graph.map_of(k)), dtype="<f8").tobytes(),
            }
            for k in self.graph.keys
        ]
        edges = [
            {
                "a": e.a,
                "b": e.b,
                "t": [e.transform.x, e.transform.y, e.transform.theta],
                "value": e.value,
                "valid": e.valid,
                "runner_up": e.runner_up,
                "seconds": e.seconds,
                "versions": list(e.versions),
                "violation": e.violation,
                "solid_violation": e.solid_violation,
                "information": None if e.information is None else list(e.information),
            }
            for e in self.graph.edges
        ]
        robots = {
            name: {
                "epoch": r.epoch,
                "stamp": r.stamp,
                "pose_in_map": {str(ep): None if p is None else [p.x, p.y, p.theta] for ep, p in r.pose_in_map.items()},
                "relocalized": sorted(r.relocalized),
            }
            for name, r in self._robots.items()
        }
        state = {
            "v": STATE_VERSION,
            "seq": self.seq,
            "stamp": self.stamp,
            "nodes": nodes,
            "edges": edges,
            "robots": robots,
            "links": self.links,
            "submaps": [m.to_msgpack() for m in self.epochs.messages()],
            "queue": [list(pair) for pair in self._queue],
            "urgent_run": self._urgent_run,
            "last_out": [[o.key, o.payload] for o in self._last_out],
        }
        p = Path(path)
        tmp = p.with_name(p.name + ".tmp")
        with open(tmp, "wb") as fh:
            fh.write(msgpack.packb(state, use_bin_type=True))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)

    def load_state(self, path: str | Path) -> None:
        """Restore a state written by :meth:`save_state` (the graph is not recomputed)."""
        source = str(path)
        try:
            state = msgpack.unpackb(Path(path).read_bytes(), raw=False)
            if not isinstance(state, dict) or state.get("v") != STATE_VERSION:
                raise BadInput(source, f"not a fleetmap merger state file (version {STATE_VERSION})")
            graph = MapGraph(self.config.integration, self.config.merge, anchor="first")
            for n in state["nodes"]:
                seg = np.frombuffer(n["segments"], dtype="<f8").reshape(-1, 4).copy()
                vp = np.frombuffer(n.get("viewpoints", b""), dtype="<f8").reshape(-1, 5)
                restored = SegmentMap(seg, ordered=False, oriented=True)
                graph.put_map(n["key"], with_viewpoints(restored, vp) if len(vp) else restored, int(n["version"]))
            for e in state["edges"]:
                graph.add_edge(
                    Edge(
                        e["a"],
                        e["b"],
                        Transform2D(*e["t"]),
                        float(e["value"]),
                        bool(e["valid"]),
                        float(e["runner_up"]),
                        float(e["seconds"]),
                        (int(e["versions"][0]), int(e["versions"][1])),
                        float(e.get("violation", 0.0)),
                        None if e.get("solid_violation") is None else float(e["solid_violation"]),
                        _information(e.get("information")),
                    )
                )
            robots = {}
            for name, r in state["robots"].items():
                robot = _Robot(epoch=int(r["epoch"]), stamp=float(r["stamp"]), relocalized=set(r["relocalized"]))
                robot.pose_in_map = {
                    int(ep): None if p is None else Transform2D(*p) for ep, p in r["pose_in_map"].items()
                }
                robots[name] = robot
            pairs = {(str(a), str(b)): None for a, b in state.get("queue", []) if a in graph and b in graph}
            urgent_run = int(state.get("urgent_run", 0))
            last_out = [Outgoing(str(key), bytes(payload)) for key, payload in state.get("last_out", [])]
            epochs = EpochMaps()
            for payload in state.get("submaps", []):
                held = decode(bytes(payload))
                if not isinstance(held, LocalMap):
                    raise ValueError(f"a saved submap is a {held.SCHEMA}")
                epochs.put(held)
        except (OSError, ValueError, KeyError, TypeError, IndexError, msgpack.UnpackException, BadMessage) as exc:
            raise BadInput(source, f"cannot load the merger state: {exc}") from None
        # A state written before edges carried their information: fit them as this merger would.
        refitted = graph.fit_edges() if any("information" not in e for e in state["edges"]) else 0
        if refitted:
            log.info("%s: fitted %d edges saved without how firmly their walls fix them", source, refitted)
        self.graph, self._robots = graph, robots
        self.seq, self.stamp, self.links = int(state["seq"]), float(state["stamp"]), dict(state["links"])
        self._queue, self._urgent_run, self._last_out = pairs, urgent_run, last_out
        self.epochs = epochs
        if len(self.graph):
            self._result = self.graph.solve()
            self._global = self._global_map(self._result)


def _information(value: object) -> tuple[float, ...] | None:
    """An edge's saved :attr:`~fleetmap.merger.graph.Edge.information` (None: not saved, as in a
    state written before edges carried it; the restored graph fits it, :meth:`MapGraph.fit_edges`)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 9:
        raise ValueError(f"an edge's information must be a list of 9 numbers, got {value!r}")
    h = np.array([float(v) for v in value]).reshape(3, 3)
    scale = float(np.abs(h).max()) if np.isfinite(h).all() else math.inf
    if not math.isfinite(scale) or not np.allclose(h, h.T, rtol=1e-9, atol=1e-12 * scale):
        raise ValueError(f"an edge's information must be a finite symmetric matrix, got {value!r}")
    if np.linalg.eigvalsh(h).min() < -1e-9 * scale:
        raise ValueError(f"an edge's information must be positive semidefinite, got {value!r}")
    return tuple(h.ravel().tolist())


def _alternate(a: list[tuple[str, str]], b: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """a[0], b[0], a[1], b[1], ... and the rest of the longer."""
    return [x for k in range(max(len(a), len(b))) for x in (a[k : k + 1] + b[k : k + 1])]


class MergerService:
    """:class:`Merger` on a bus: the live service (``fleetmap merger``).

    Bus callbacks only queue what arrives (a callback that blocked would stall the whole zenoh
    session); one thread, :meth:`run`, takes the queue in order, steps the merger and publishes.
    The queryable answers from the last published global map without waiting for a step.
    """

    def __init__(
        self,
        bus: Bus,
        merger: Merger,
        *,
        state_file: str | Path | None = None,
        tick: float = 0.05,
        clock: Callable[[], float] = time.time,
        step_seconds: float = STEP_SECONDS,
    ) -> None:
        if not step_seconds >= 0 or math.isinf(step_seconds):
            raise BadInput("step_seconds", f"must be 0 (no budget) or a positive number, got {step_seconds}")
        self.bus = bus
        self.merger = merger
        self.keys = merger.keys
        self.state_file = Path(state_file) if state_file else None
        self.tick = tick
        self.step_seconds = step_seconds
        self.clock = clock
        self._inbox: queue.SimpleQueue[tuple[str, bytes | bool]] = queue.SimpleQueue()
        self._handles: list[Handle] = []
        self._snapshot = merger.global_map.to_msgpack()

    def start(self) -> None:
        keys = self.keys
        self._handles.append(self.bus.subscribe(keys.all_localmaps, self._on_message))
        self._handles.append(self.bus.subscribe(keys.all_scans, self._on_message))
        self._handles.append(self.bus.subscribe(keys.events, self._on_message))
        self._handles.append(self.bus.declare_queryable(keys.state, self._on_query))
        self._handles.append(
            self.bus.subscribe_liveliness(
                keys.all_alive,
                lambda k: self._inbox.put((k, True)),
                lambda k: self._inbox.put((k, False)),
                history=True,
            )
        )
        self._handles.append(self.bus.declare_liveliness(keys.service("merger")))
        now = self.clock()
        self.bus.publish(keys.events, FleetEvent("merger_start", None, now).to_msgpack())
        # A (re)started merger says where it stands, and asks every robot for its latest local
        # map of every epoch.
        self._publish(self.merger.where_it_stands())
        self.bus.publish(keys.events, FleetEvent("republish_request", None, now).to_msgpack())

    def _on_message(self, key: str, payload: bytes) -> None:
        self._inbox.put((key, payload))

    def _on_query(self, selector: str) -> bytes:
        return self._snapshot

    def _publish(self, out: list[Outgoing]) -> None:
        for o in out:
            self.bus.publish(o.key, o.payload)

    def _drain(self) -> None:
        while True:
            try:
                key, item = self._inbox.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, bool):
                robot = key.rsplit("/", 1)[-1]
                log.info("robot %s %s", robot, "joined" if item else "left")
                self._publish(self.merger.presence(robot, item, self.clock()))
            else:
                self._publish(self.merger.receive(key, item))

    def run_once(self) -> bool:
        """Take what arrived and step if there is work (a local map pending, or pairs of maps to
        integrate), for about ``step_seconds`` at most (one integration at least); True if it
        stepped."""
        self._drain()
        return self._step()

    def _step(self) -> bool:
        if not self.merger.has_work:
            return False
        deadline = time.monotonic() + self.step_seconds

        def past_deadline() -> bool:
            return time.monotonic() >= deadline

        out = self.merger.step(enough=past_deadline if self.step_seconds > 0 else None)
        if self.state_file is not None:
            self.merger.save_state(self.state_file)
        self._snapshot = self.merger.global_map.to_msgpack()
        self._publish(out)
        return True

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            if not self.run_once():
                stop.wait(self.tick)
        # At the stop: what arrived, then every pair still queued (what arrives from now on is
        # not taken, so this ends): nothing is left unintegrated.
        self._drain()
        while self._step():
            pass

    def close(self) -> None:
        try:
            self.bus.publish(self.keys.events, FleetEvent("merger_stop", None, self.clock()).to_msgpack())
            self.bus.flush()
        finally:
            for h in self._handles:
                h.close()
            self._handles.clear()
