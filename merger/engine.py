"""The merger: submaps in, global maps and robot poses out.

:class:`Merger` is the whole logic as a library (no network, no clock): ``receive`` takes the bytes
of a bus message, ``step`` takes the submaps received since the last step into the pose graph
(:mod:`fleetmap.merger.posegraph`), integrates the pairs of submaps due, solves the graph and returns
the messages to publish. It is deterministic given the same messages in the same order, which is
what lets a recorded session replay to the same map: every step is published as a
:class:`~fleetmap.shared.io.messages.MergerStep` naming the submap versions it took, in order, and how
many pairs it integrated, and a replay follows those steps.

**Bounded work per submap.** A submap is integrated when it is final (it never changes again),
and, while its robot's current epoch is not placed and has no final submap yet (a robot that
just joined, or lost its place), as its active submap grows (each time its version doubles,
``MergeParams.search_growth``). Which pairs:

- *near* (a submap whose predecessor is in the graph): the submaps of its component, its own
  robot's earlier ones included (a loop), whose refined poses lie within reach of where its links
  put the new one (not its neighbours on its own chain), at most
  ``MergeParams.near_candidates``, registered near that prediction
  (:meth:`~fleetmap.merger.posegraph.PoseGraph.align_pair`), as Cartographer's constraint builder
  searches near a trajectory;
- *far*: the submaps of the other components most like it (the cosine of pairwise geometric
  histograms of the walls, the cheap descriptor), at most ``MergeParams.far_candidates``, by the
  paper's pose-free integration; every ``loop_sweep_every``-th final
  submap also tries the most similar submap of its own component beyond its reach (a loop its
  drift hides from the near search);
- *joined*: when a solve joins groups of epochs that were apart, the final submaps of the groups
  whose walls now meet, registered near where the join puts them (at most ``near_candidates``
  a submap): the near search of a submap that arrived before the join only saw its own group.

So integrating n submaps costs O(n) integrations, not n^2 (:attr:`MergerStats.integrations`).

What it publishes after a step:

- ``GlobalMap``: every component of the graph (anchor, member submaps, their poses, fused
  walls), the largest first;
- ``RobotPose`` for every robot: its pose in its component's frame, composed from its newest
  submap's pose and its pose in that submap; *unknown* (None, never a guess) while its current
  epoch is merged with no other epoch (a kidnapped robot not relocalized yet), except a robot's
  first epoch when it is the largest component (it is the global map);
- ``MergeEdge`` for every integration of the step, ``MergerStep``, and ``FleetEvent``
  "relocalized" when a later epoch of a robot is placed for the first time.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from fleetmap.merger.executor import Executor, InlineExecutor, PairJob
from fleetmap.merger.executor import Handle as JobHandle
from fleetmap.merger.graph import Component as GraphComponent
from fleetmap.merger.graph import Edge, MergeResult
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.scangraph import IntegrationEdge, KeyScan, follow_key_scans, is_key, refine_key_scans
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.descriptor import similarity
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.mapgrid import with_viewpoints
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.tracking import REACH_ROTATION, sample_segments
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import ROBOT_KINDS, FleetKeys, parse_submap_key
from fleetmap.shared.io.messages import (
    BadMessage,
    Component,
    FleetEvent,
    GlobalMap,
    LocalMap,
    MergeEdge,
    MergerStep,
    Message,
    RobotPose,
    Scan,
    decode,
)
from fleetmap.shared.io.occupancy import placed_scans

log = logging.getLogger(__name__)

STATE_VERSION = 2
"""The format of the state file a merger saves (:meth:`Merger.save_state`); a file of another is refused."""


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
    foreign: int = 0
    """Messages naming another robot than the robot of their key (a robot speaking for another),
    dropped whatever the router allowed."""
    refused: Counter[str] = field(default_factory=Counter)
    """Messages and pairs refused by a limit (``merge.max_submap_segments``, ``max_robots``,
    ``max_queued_pairs``), per limit."""
    stale: int = 0
    """Submap versions older than (or as old as) the version already held."""
    steps: int = 0
    integrations: int = 0
    """Pairs of submaps integrated (pose-free or near a prediction)."""
    near: int = 0
    """... of which registered near where the graph predicts them ..."""
    idle: int = 0
    """... and pose-free tries for robots apart from the global map, taken when nothing else was due."""
    join_pairs: int = 0
    """Near registrations queued between the groups of submaps a join put in one frame."""
    failed: int = 0
    """Integrations that failed where they ran (a worker that died more often than it is retried,
    a Ray task's error): logged and dropped, the merger goes on."""
    poses_dropped: int = 0
    """Scans the pose thread had no room for (it keeps ``POSE_QUEUE`` waiting)."""
    key_scans: int = 0
    """Scans kept to register on the submaps they revisit (:mod:`fleetmap.merger.scangraph`)."""
    scan_registrations: int = 0
    """Key scans registered on other submaps by the last :meth:`Merger.scan_poses` ..."""
    scan_constraints: int = 0
    """... and the fits kept as edges."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "received": dict(self.received),
            "malformed": self.malformed,
            "malformed_reasons": dict(self.malformed_reasons),
            "ignored": self.ignored,
            "foreign": self.foreign,
            "refused": dict(self.refused),
            "stale": self.stale,
            "steps": self.steps,
            "integrations": self.integrations,
            "near": self.near,
            "idle": self.idle,
            "join_pairs": self.join_pairs,
            "failed": self.failed,
            "poses_dropped": self.poses_dropped,
            "key_scans": self.key_scans,
            "scan_registrations": self.scan_registrations,
            "scan_constraints": self.scan_constraints,
        }


@dataclass
class _Robot:
    epoch: int = 0
    stamp: float = 0.0
    """Stamp of the robot's newest submap that says where it is: when its pose there was true."""
    at: tuple[str, Transform2D] | None = None
    """The robot's newest pose: (submap key, pose in that submap); None when it is lost."""
    relocalized: set[int] = field(default_factory=set)
    present: bool = False


def _epoch_of(key: str) -> str:
    robot, epoch, _ = parse_submap_key(key)
    return f"{robot}/{epoch}"


class Merger:
    """The merger's logic: :meth:`receive` messages, :meth:`step`, publish what it returns."""

    def __init__(
        self,
        keys: FleetKeys,
        config: FleetmapConfig | None = None,
        executor: Executor | None = None,
        keep_key_scans: bool = False,
    ) -> None:
        """``keep_key_scans``: keep the key scans it hears (:meth:`scan_poses` refines with them;
        ``fleetmap map`` asks for it, a live merger that never calls it does not keep them)."""
        self.keys = keys
        self.keep_key_scans = keep_key_scans
        self.config = config or FleetmapConfig()
        self.executor: Executor = executor or InlineExecutor()
        """Where the integrations run (:mod:`fleetmap.merger.executor`); the caller closes it."""
        self.graph = PoseGraph(self.config.integration, self.config.merge, self.config.tracking)
        self.solve_seconds = 0.0
        """How long the last step's solve took (what a step of integrations alone is worth)."""
        self.stats = MergerStats()
        self.seq = 0
        self.stamp = 0.0
        self.submaps: dict[str, LocalMap] = {}
        """The version of every submap in the graph, by submap key."""
        self._pending: dict[str, LocalMap] = {}
        """Submap versions received since the last step, by submap key, in arrival order."""
        self._robots: dict[str, _Robot] = {}
        self._result: MergeResult | None = None
        self._global: GlobalMap | None = None
        self._queue: dict[tuple[str, str], Transform2D | None] = {}
        """Pairs to integrate, oldest first: (a, b) with b's predicted pose in a (near), or None
        (pose-free)."""
        self._scheduled: dict[str, int] = {}
        """The version of each submap its integrations were last scheduled for."""
        self._finals = 0
        """Final submaps of placed robots scheduled so far (every loop_sweep_every-th sweeps)."""
        self._far_tries: dict[str, int] = {}
        """Pose-free integrations queued for each submap with other components' submaps."""
        self._finished_epochs: set[str] = set()
        """Epochs (``robot/epoch``) with a final submap: from then on their final submaps search."""
        self._idle: set[tuple[str, str]] = set()
        """Queued pairs that :meth:`_idle_pairs` chose."""
        self._joined: set[tuple[str, str]] = set()
        """Pairs :meth:`_queue_joined` queued (each once: a pair that did not register stays so)."""
        self._last_out: list[Outgoing] = []
        self._unfused = False
        """Whether the last solve left the global map's walls out (``step(fuse=False)``)."""
        self._where: dict[str, int] = {}
        self._epoch_where: dict[str, int] = {}
        self._epochs_in: list[set[str]] = []
        self._key_scans: dict[str, list[KeyScan]] = {}
        """The key scans of every submap, by submap key (:meth:`_take_scan`)."""

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
        if not self._robots_own(key, message) or not self._room_for(getattr(message, "robot", None)):
            return []
        if isinstance(message, LocalMap):
            if key != self.keys.localmap(message.robot):
                self.stats.ignored += 1
                return []
            self._take_submap(message)
        elif isinstance(message, Scan):
            if key != self.keys.scan(message.robot):
                self.stats.ignored += 1
                return []
            self._robot(message.robot)  # a robot that only scans so far is known, not placed
            self._take_scan(message)
        elif isinstance(message, FleetEvent) and message.kind == "epoch" and message.robot is not None:
            self._robot(message.robot)
        else:
            self.stats.ignored += 1
        return []

    def _robots_own(self, key: str, message: Message) -> bool:
        """Whether a message on a robot's key is that robot's; else it is dropped and counted
        (defence in depth: a router's access control holds a robot to its own keys, but only
        where one is configured)."""
        try:
            parsed = self.keys.parse(key)
        except BadInput:
            return True  # not a fleet key: the kind checks below decide
        robot = getattr(message, "robot", None)
        if parsed.kind not in ROBOT_KINDS or robot == parsed.robot:
            return True
        self.stats.foreign += 1
        if self.stats.foreign <= 20 or self.stats.foreign % 1000 == 0:
            log.warning(
                "dropped a %s naming robot %r on robot %r's key %s (%d so far)",
                message.SCHEMA,
                robot,
                parsed.robot,
                key,
                self.stats.foreign,
            )
        return False

    def _room_for(self, robot: str | None) -> bool:
        """Whether the merger may keep track of ``robot`` (one it knows, or one more under the limit)."""
        if robot is None or robot in self._robots or len(self._robots) < self.config.merge.max_robots:
            return True
        self._refuse("max_robots", f"a message of robot {robot!r}, {len(self._robots)} robots known")
        return False

    def _refuse(self, limit: str, what: str) -> None:
        """Count (and log, the first times) something a limit of ``merge`` refused."""
        self.stats.refused[limit] += 1
        n = self.stats.refused[limit]
        if n <= 10 or n % 1000 == 0:
            flag = "--" + limit.replace("_", "-")
            value = getattr(self.config.merge, limit)
            log.warning("refused %s: more than %s %s allows (%d refused so far)", what, flag, value, n)

    def _enqueue(self, pair: tuple[str, str], predicted: Transform2D | None) -> bool:
        """Queue a pair to integrate (once); False if it was queued already or the queue is full."""
        if pair in self._queue:
            return False
        if len(self._queue) >= self.config.merge.max_queued_pairs:
            self._refuse("max_queued_pairs", f"pair {pair[0]} {pair[1]}, {len(self._queue)} queued")
            return False
        self._queue[pair] = predicted
        return True

    def _robot(self, name: str) -> _Robot:
        return self._robots.setdefault(name, _Robot())

    def _take_submap(self, m: LocalMap) -> None:
        key = m.submap_key
        held = self.submaps.get(key)
        waiting = self._pending.get(key)
        if (held is not None and m.version <= held.version) or (waiting is not None and m.version <= waiting.version):
            self.stats.stale += 1
            return
        if len(m.segments) == 0:
            self.stats.ignored += 1
            return
        if len(m.segments) > self.config.merge.max_submap_segments:
            self._refuse("max_submap_segments", f"submap {key} of {len(m.segments)} segments")
            return
        self._robot(m.robot)  # known from its first map (max_robots counts it)
        self._pending[key] = m

    def _take_scan(self, scan: Scan) -> None:
        """Keep a placed scan that is a key scan of its submap (:func:`fleetmap.merger.scangraph.is_key`)."""
        if (
            not (self.keep_key_scans and self.config.merge.scan_constraints)
            or scan.submap is None
            or scan.pose is None
            or not len(scan.segments)
        ):
            return
        key = f"{scan.robot}/{scan.epoch}/{scan.submap}"
        held = self._key_scans.setdefault(key, [])
        if held and scan.index <= held[-1].index:
            return  # a scan again, or out of order
        if not is_key(held[-1].pose if held else None, scan.pose, self.config.merge):
            return
        samples = sample_segments(np.asarray(scan.segments), self.config.tracking.sample_spacing)
        held.append(KeyScan(scan.robot, scan.epoch, scan.index, key, scan.pose, samples))
        self.stats.key_scans += 1

    def presence(self, robot: str, present: bool, stamp: float) -> list[Outgoing]:
        """A robot's liveliness token appeared or went: a join or leave event. Its maps stay."""
        if not self._room_for(robot):
            return []
        r = self._robot(robot)
        r.present = present
        kind = "join" if present else "leave"
        return [Outgoing(self.keys.events, FleetEvent(kind, robot, max(stamp, 0.0)).to_msgpack())]

    @property
    def pending(self) -> int:
        return len(self._pending)

    @property
    def robots(self) -> list[str]:
        """Every robot the merger knows, by name."""
        return sorted(self._robots)

    def robot_epoch(self, robot: str) -> int:
        """A known robot's current epoch."""
        return self._robots[robot].epoch

    @property
    def waiting(self) -> list[str]:
        """The submaps received that no step has taken into the graph yet."""
        return list(self._pending)

    @property
    def backlog(self) -> int:
        """Submaps received and pairs queued that no step has taken yet."""
        return len(self._pending) + len(self._queue)

    @property
    def has_work(self) -> bool:
        """Whether a step has something to do: submaps pending, pairs to integrate, or robots
        apart from the global map whose submaps have candidates left to try (:meth:`_idle_pairs`)."""
        return bool(self._pending) or bool(self._queue) or self._searching

    @property
    def _searching(self) -> bool:
        if self._result is None or len(self._result.components) < 2:
            return False
        budget = self.config.merge.far_budget
        return any(self._far_tries.get(k, 0) < budget for k in self._idle_candidates())

    @property
    def queued(self) -> int:
        """Pairs of submaps still to integrate."""
        return len(self._queue)

    # -- one step --------------------------------------------------------------------------
    def step(
        self, limit: int | None = None, enough: Callable[[], bool] | None = None, fuse: bool = True
    ) -> list[Outgoing]:
        """Take the submaps received since the last step into the graph, integrate the pairs due
        (all of them, ``limit`` of them as a replay repeats a live step, or until ``enough()`` says
        the step took long enough), solve, and return the messages to publish. With ``fuse``
        False the global map's walls are left out (an offline run fuses them once, at its end: a
        step with ``fuse`` after one without solves again, work or none, to publish them)."""
        refuse = fuse and self._unfused and not self.has_work
        if not self.has_work and not refuse:
            return []
        batch = list(self._pending.values())
        self._pending.clear()
        for m in batch:
            self._enter(m)
        for m in batch:
            self._schedule(m)
        if not self._queue and not refuse:
            self._idle_pairs()
        new_edges: list[Edge] = []
        taken = 0
        running: deque[tuple[PairJob, JobHandle]] = deque()
        while self._queue or running:
            # as many in flight as the executor keeps busy; results taken in the queue's order, so
            # the graph is the same whichever executor ran them (a pair whose two submaps are in
            # flight already waits for that result: whether it is due depends on it)
            while self._queue and len(running) < self.executor.capacity:
                if (limit is not None and taken >= limit) or (
                    limit is None and enough is not None and taken and enough()
                ):
                    break
                pair, predicted = next(iter(self._queue.items()))
                if any({j.a, j.b} == set(pair) for j, _ in running):
                    break
                del self._queue[pair]
                taken += 1
                job = self._job(pair, predicted)
                if job is not None:
                    running.append((job, self.executor.submit(job, self.graph.indexes)))
            if not running:
                break
            job, handle = running.popleft()
            try:
                result = handle.result()
            except Exception as exc:  # a job that failed where it ran: the merger goes on without it
                self.stats.failed += 1
                log.error("integrating %s and %s failed (%s: %s); dropped", job.a, job.b, type(exc).__name__, exc)
                continue
            new_edges.append(self.graph.take(job, result))
        self.seq += 1
        self.stats.steps += 1
        self.stats.integrations += len(new_edges)
        self.stamp = max([self.stamp] + [m.stamp for m in batch])
        out: list[Outgoing] = []
        for e in new_edges:
            t = e.transform
            said = MergeEdge(e.a, e.b, t.x, t.y, t.theta, max(e.value, 0.0), e.valid, self.stamp)
            out.append(Outgoing(self.keys.edges, said.to_msgpack()))
        solving = time.perf_counter()
        apart = {epoch: frozenset(self._epochs_in[i]) for epoch, i in self._epoch_where.items()}
        self._result = self.graph.solve(fuse_maps=fuse)
        self.solve_seconds = time.perf_counter() - solving
        self._unfused = not fuse
        self._index_result()
        self._queue_joined(apart)
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
        byte for byte (nothing before its first step, nothing meant for another fleet).

        A merger killed after saving its state and before publishing that step's messages would
        otherwise never publish them: the robots' republished submaps are the versions it already
        holds, so no step follows. A replay knows the repeated MergerStep for a repeat."""
        return [o for o in self._last_out if o.key.startswith(self.keys.prefix + "/")]

    def _enter(self, m: LocalMap) -> None:
        """Put a submap version into the graph, with its link, and note where its robot is."""
        key = m.submap_key
        r = self._robot(m.robot)
        if m.epoch > r.epoch:
            r.epoch, r.at = m.epoch, None
        if m.epoch == r.epoch and m.pose is not None and m.stamp >= r.stamp:
            r.at, r.stamp = (key, m.pose), m.stamp
        segment_map = SegmentMap(np.array(m.segments), ordered=False, oriented=True)
        if m.viewpoints is not None and len(m.viewpoints):
            segment_map = with_viewpoints(segment_map, m.viewpoints)
        self.graph.put_map(key, segment_map, m.version, keep_edges=True)
        if m.final:
            self._finished_epochs.add(f"{m.robot}/{m.epoch}")
        if m.link is not None:
            previous = f"{m.robot}/{m.epoch}/{m.link.submap}"
            self.graph.put_link(previous, key, m.link.transform, m.link.covariance_matrix)
        self.submaps[key] = m

    # -- which pairs -----------------------------------------------------------------------
    def _component_of(self, key: str) -> GraphComponent | None:
        index = self._where.get(key)
        return None if index is None or self._result is None else self._result.components[index]

    def _placed_epoch(self, epoch_key: str) -> bool:
        """Whether an epoch shares its component with another epoch (the fleet knows where it is)."""
        index = self._epoch_where.get(epoch_key)
        return index is not None and len(self._epochs_in[index]) > 1

    def _index_result(self) -> None:
        """Which component holds each submap and each epoch, and which epochs each holds."""
        self._where, self._epoch_where, self._epochs_in = {}, {}, []
        for i, c in enumerate(self._result.components if self._result is not None else []):
            epochs = {_epoch_of(k) for k in c.members}
            self._epochs_in.append(epochs)
            for k in c.members:
                self._where[k] = i
            for epoch in epochs:
                self._epoch_where.setdefault(epoch, i)

    def _predicted(self, key: str) -> Transform2D | None:
        """Where the graph puts a submap in its component's frame: its refined pose, or its
        predecessor's composed with its link."""
        if self._result is None:
            return None
        pose = self._result.poses.get(key)
        if pose is not None:
            return pose
        link = self.graph.link_to(key)
        if link is not None and self._result.poses.get(link.a) is not None:
            before = self._result.poses[link.a]
            return before.compose(link.transform) if before is not None else None
        return None

    def _schedule(self, m: LocalMap) -> None:
        """Queue the integrations a submap version is due (see the module docstring)."""
        key = m.submap_key
        mp = self.config.merge
        r = self._robots[m.robot]
        current = m.epoch == r.epoch
        placed = self._placed_epoch(f"{m.robot}/{m.epoch}")
        last = self._scheduled.get(key)
        final = m.final and (last is None or last < m.version)
        searching = (
            current
            and not placed
            and f"{m.robot}/{m.epoch}" not in self._finished_epochs
            and (last is None or m.version >= self.config.merge.search_growth * max(last, 1))
        )
        if not (final or searching):
            return
        self._scheduled[key] = m.version
        mine = self._component_members(key)
        if final and self._predicted(key) is not None:
            # its chain is in the graph: the submaps of its component near where the links put it
            # (its own earlier submaps too: a loop), whether or not another robot is there yet
            beyond = []
            for other, predicted in self._near(key, mine)[: mp.near_candidates]:
                # registered near the prediction where the robot's own drift between the two
                # cannot have carried it out of registration's reach; else pose-free (a loop
                # after a long way round: the search window as wide as the uncertainty), the
                # most similar such submap only: the paper's integration costs ten registrations
                if self._within_reach(other, key):
                    self._enqueue((other, key), predicted)
                else:
                    beyond.append(other)
            if beyond:
                h = self.graph.descriptor(key)
                best = max(beyond, key=lambda k: (similarity(self.graph.descriptor(k), h), k))
                self._enqueue(_ordered(best, key), None)
            if m.final:
                self._finals += 1
                if mp.loop_sweep_every > 0 and self._finals % mp.loop_sweep_every == 0:
                    sweep = self._far(key, mine, within=True)[:1]
                    for other in sweep:
                        self._enqueue(_ordered(other, key), None)
        if not self._in_global_map(key):
            # the global map's own submaps are not searched for the others: each of theirs
            # searches it, and one direction is enough
            for other in self._far(key, mine, within=False)[: mp.far_candidates]:
                self._queue_far(key, other)

    def _queue_joined(self, apart: dict[str, frozenset[str]]) -> None:
        """After a solve that joined groups of epochs (``apart``: each epoch's component's epochs
        before it): queue near registrations between the final submaps of the groups now joined
        whose walls meet at their refined poses and that no valid integration relates yet (a pair
        tried pose-free while apart, ambiguous then, may register near the join), each pair once,
        at most ``near_candidates`` a submap, nearest first.

        A final submap searches near its prediction once, when it arrives, among the submaps of its
        component then: two robots' submaps that meet only once a later join puts them in one frame
        would never be registered on each other, and the join would rest on its few integrations
        while the chains around it bend. These are the join's own loop closures, as Cartographer's
        constraint builder finds them for a trajectory it has just placed; bounded by the pairs
        that meet, so the work stays O(n)."""
        if self._result is None:
            return
        limit = self.config.merge.near_candidates
        at = {k: p for k, p in self._result.poses.items() if p is not None}
        queued = 0
        for component in self._result.components:
            groups: dict[frozenset[str], list[str]] = {}
            for key in sorted(component.members):
                if self.submaps[key].final and key in at:
                    epoch = _epoch_of(key)
                    groups.setdefault(apart.get(epoch, frozenset({epoch})), []).append(key)
            if len(groups) < 2:
                continue
            found: list[tuple[float, str, str]] = []
            ordered = sorted(groups.values())
            for n, group_a in enumerate(ordered):
                for group_b in ordered[n + 1 :]:
                    meets = self.graph.meeting(group_a, at, group_b, at)
                    for ia, ib in np.argwhere(meets):
                        a, b = _ordered(group_a[ia], group_b[ib])
                        known = self.graph.edge(a, b)
                        if (a, b) in self._joined or (known is not None and known.valid):
                            continue
                        found.append((math.hypot(at[a].x - at[b].x, at[a].y - at[b].y), a, b))
            count: Counter[str] = Counter()
            for _, a, b in sorted(found):
                if count[a] >= limit or count[b] >= limit:
                    continue
                if self._enqueue((a, b), at[a].inverse().compose(at[b])):
                    self._joined.add((a, b))
                    count[a] += 1
                    count[b] += 1
                    queued += 1
        self.stats.join_pairs += queued

    def _in_global_map(self, key: str) -> bool:
        """Whether a submap (or its predecessor, for a new one) is in the largest component, the
        global map, together with another epoch."""
        link = self.graph.link_to(key)
        index = self._where.get(key, self._where.get(link.a) if link is not None else None)
        return index == 0 and len(self._epochs_in[0]) > 1

    def _queue_far(self, key: str, other: str) -> None:
        if self._enqueue(_ordered(other, key), None):
            self._far_tries[key] = self._far_tries.get(key, 0) + 1

    def _idle_pairs(self) -> int:
        """With nothing else to do: one more pose-free pair for a submap of each component apart
        from the global map (:meth:`_idle_candidates`: robots not in it yet), its next most
        similar submap of another component not tried yet, up to ``far_budget`` tries a submap;
        how many were queued. Every submap's candidates are tried in turn: in a building where
        most views look alike (racks), the descriptor ranks the right partner anywhere."""
        if self._result is None or len(self._result.components) < 2:
            return 0
        budget = self.config.merge.far_budget
        queued = 0
        by_component: dict[int, list[str]] = {}
        for key in self._idle_candidates():
            by_component.setdefault(self._where[key], []).append(key)
        for i, candidates in sorted(by_component.items()):
            mine = set(self._result.components[i].members)
            for key in sorted(candidates, key=lambda k: (self._far_tries.get(k, 0), k)):
                if self._far_tries.get(key, 0) >= budget:
                    continue
                others = self._far(key, mine, within=False)
                if others:
                    self._queue_far(key, others[0])
                    self._idle.add(_ordered(others[0], key))
                    queued += 1
                    break
                self._far_tries[key] = budget  # none left
        return queued

    def _idle_candidates(self) -> list[str]:
        """The submaps the idle search tries (:meth:`_idle_pairs`), whose tries :attr:`_searching`
        counts (they must be the same, or a step with nothing to queue would have work for ever):
        of each component but the global map, its final submaps, or all of them if none is final
        yet. Robots placed among themselves and not in the global map search on: two robots that
        joined each other are still apart from the fleet."""
        if self._result is None:
            return []
        out: list[str] = []
        for i, component in enumerate(self._result.components):
            if i == 0 and len(self._epochs_in[i]) > 1:
                continue
            finals = [k for k in component.members if self.submaps[k].final]
            out += finals or list(component.members)
        return out

    def _component_members(self, key: str) -> set[str]:
        """The submaps in ``key``'s component, by the last solve and its links."""
        members = {key}
        link = self.graph.link_to(key)
        anchor = link.a if link is not None else key
        component = self._component_of(anchor)
        if component is not None:
            members.update(component.members)
        return members

    def _near(self, key: str, mine: set[str]) -> list[tuple[str, Transform2D]]:
        """Submaps of ``key``'s component within reach of where the graph puts it, nearest first,
        with the predicted pose of ``key`` in each; not its neighbours on its own chain."""
        here = self._predicted(key)
        if here is None or self._result is None:
            return []
        radius = self._radius(key)
        out = []
        for other in sorted(mine):
            if other == key or self._neighbours(key, other):
                continue
            there = self._result.poses.get(other)
            if there is None:
                continue
            distance = math.hypot(here.x - there.x, here.y - there.y)
            if distance <= radius + self._radius(other):
                out.append((distance, other, there.inverse().compose(here)))
        out.sort(key=lambda x: (x[0], x[1]))
        return [(other, predicted) for _, other, predicted in out]

    def _within_reach(self, a: str, b: str) -> bool:
        """Whether registration from the predicted pose can find b on a: the drift the links
        between two submaps of one robot's chain allow (three standard deviations of their
        covariances, :meth:`~fleetmap.merger.joins.JoinJudge.chain_drift`) is within the
        tracking's correspondence distance and 5 degrees; always for two robots' submaps (their
        prediction comes through integrations)."""
        drift = self.graph.chain_drift(a, b)
        if drift is None:
            return True
        return drift[0] <= self.config.tracking.max_correspondence and drift[1] <= REACH_ROTATION

    def _neighbours(self, a: str, b: str) -> bool:
        """Whether two submaps are within two of each other on one robot's chain (they share
        scans, or their links already say how they lie)."""
        ra, ea, sa = parse_submap_key(a)
        rb, eb, sb = parse_submap_key(b)
        return ra == rb and ea == eb and sa is not None and sb is not None and abs(sa - sb) <= 2

    def _radius(self, key: str) -> float:
        """How far a submap's walls reach from its frame (m)."""
        seg = self.graph.map_of(key).segments
        if len(seg) == 0:
            return 0.0
        return float(np.hypot(seg[:, 0::2], seg[:, 1::2]).max())

    def _far(self, key: str, mine: set[str], within: bool) -> list[str]:
        """Submaps most like ``key`` (pairwise geometric histograms), of the other components, or of its
        own beyond its reach (``within``), most similar first."""
        h = self.graph.descriptor(key)
        here = self._predicted(key)
        candidates = []
        for other in self.graph.keys:
            if other == key or (other in mine) != within or self._neighbours(key, other):
                continue
            if within and here is not None and self._result is not None:
                there = self._result.poses.get(other)
                if there is not None and math.hypot(here.x - there.x, here.y - there.y) <= self._radius(
                    key
                ) + self._radius(other):
                    continue  # within reach: the near search's
            if not self.graph.seen_enough(key, other) or self.graph.is_current(*_ordered(other, key)):
                continue
            candidates.append((-similarity(self.graph.descriptor(other), h), other))
        candidates.sort()
        return [other for _, other in candidates]

    def _job(self, pair: tuple[str, str], predicted: Transform2D | None) -> PairJob | None:
        """The integration a queued pair is due: near its prediction, or pose-free (once per
        pair of versions); None if a map has gone or the pair's edge is current."""
        a, b = pair
        if a not in self.graph or b not in self.graph:
            return None
        if pair in self._idle:
            self._idle.discard(pair)
            self.stats.idle += 1
        if predicted is not None:
            self.stats.near += 1
            return self.graph.pair_job(a, b, predicted)
        return self.graph.job_once(a, b)

    # -- outputs ---------------------------------------------------------------------------
    def _global_map(self, result: MergeResult) -> GlobalMap:
        components = tuple(
            Component(c.anchor, tuple(c.members), dict(c.poses), np.asarray(c.segments)) for c in result.components
        )
        return GlobalMap(self.seq, self.stamp, components)

    def robot_pose(self, robot: str) -> tuple[Transform2D | None, int | None]:
        """A robot's pose in its component's frame and the component's index; (None, None) if unknown."""
        r = self._robots.get(robot)
        if r is None or r.at is None or self._result is None or self._global is None:
            return None, None
        key, in_submap = r.at
        index = self._where.get(key)
        if index is None:
            return None, None
        if not self._gives_poses(index, r.epoch):
            return None, None  # a later epoch merged with nothing: the robot is lost, not guessed
        return self._result.components[index].poses[key].compose(in_submap), index

    def _gives_poses(self, index: int, epoch: int) -> bool:
        """Whether a robot's pose may be given in component ``index`` for its epoch ``epoch``: the
        component merges it with another epoch, or it is a first epoch in the largest component
        (a robot alone, or the first of the fleet)."""
        return len(self._epochs_in[index]) > 1 or (epoch == 0 and index == 0)

    def pose_frames(self) -> dict[str, tuple[int, Transform2D]]:
        """Per submap a robot's pose may be given in (:meth:`robot_pose`'s rule): its component
        and its pose there, as the last step placed it (:mod:`fleetmap.merger.follow`)."""
        frames: dict[str, tuple[int, Transform2D]] = {}
        for i, component in enumerate(self._result.components if self._result is not None else []):
            for key in component.members:
                _, epoch, _ = parse_submap_key(key)
                if self._gives_poses(i, epoch):
                    frames[key] = (i, component.poses[key])
        return frames

    def _robot_poses(self) -> list[Outgoing]:
        out = []
        for robot in sorted(self._robots):
            r = self._robots[robot]
            if r.at is None and not any(k.startswith(f"{robot}/{r.epoch}/") for k in self.submaps):
                continue  # no submap yet: nothing to say
            pose, index = self.robot_pose(robot)
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

    def scan_poses(self) -> dict[tuple[str, int], tuple[int, Transform2D]]:
        """Every scan the last solve placed, by (robot, index): its component's number and its laser
        pose in that component's frame; with ``merge.scan_constraints``, the key scans registered on
        the submaps they revisit and all refined together (:mod:`fleetmap.merger.scangraph`; a merger
        made with ``keep_key_scans``), else its submap's pose composed with its pose in the submap."""
        out: dict[tuple[str, int], tuple[int, Transform2D]] = {}
        if self._result is None:
            return out
        tables = {
            k: (m.scan_indices, m.scan_poses)
            for k, m in self.submaps.items()
            if m.scan_indices is not None and m.scan_poses is not None
        }
        links = {e.b: (e.a, e.transform) for e in self.graph.links}
        edges = [e for e in (*self._result.tree, *self._result.loops) if not e.link]
        self.stats.scan_registrations = self.stats.scan_constraints = 0
        for n, c in enumerate(self._result.components):
            placed = placed_scans(c.poses, tables)
            if self.config.merge.scan_constraints:
                keys = [k for key in c.members for k in self._key_scans.get(key, ())]
                walls = {key: np.asarray(self.submaps[key].segments) for key in c.members if key in self.submaps}
                integrations = [
                    IntegrationEdge(
                        e.a, e.b, e.transform, self.graph.edge_noise(e, robust=False), self.graph.edge_noise(e)
                    )
                    for e in edges
                    if e.a in c.poses and e.b in c.poses
                ]
                refined = refine_key_scans(
                    keys, c.poses, c.anchor, walls, links, integrations, self.config.merge, self.config.tracking
                )
                self.stats.scan_registrations += refined.registrations
                self.stats.scan_constraints += refined.constraints
                poses = follow_key_scans(placed, keys, refined.poses, c.poses)
            else:
                poses = {scan: pose for scan, (_, pose) in placed.items()}
            for scan, pose in poses.items():
                out.setdefault(scan, (n, pose))
        return out

    # -- state file ------------------------------------------------------------------------
    def save_state(self, path: str | Path) -> None:
        """Everything needed to resume: the submaps (as received, in the order they entered the
        graph), the integrations, the robots, the queue, the submaps received and not yet taken in,
        the last step's messages.

        Written to a temporary file and renamed, so a merger killed while saving leaves the
        previous state whole."""
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
                "rivals": [[t.x, t.y, t.theta] for t in e.rivals],
            }
            for e in self.graph.edges
            if not e.link  # links come back with their submaps
        ]
        robots = {
            name: {
                "epoch": r.epoch,
                "stamp": r.stamp,
                "at": None if r.at is None else [r.at[0], r.at[1].x, r.at[1].y, r.at[1].theta],
                "relocalized": sorted(r.relocalized),
            }
            for name, r in self._robots.items()
        }
        state = {
            "v": STATE_VERSION,
            "seq": self.seq,
            "stamp": self.stamp,
            "submaps": [self.submaps[k].to_msgpack() for k in self.graph.keys],
            "edges": edges,
            "robots": robots,
            "queue": [[a, b, None if t is None else [t.x, t.y, t.theta]] for (a, b), t in self._queue.items()],
            "pending": [m.to_msgpack() for m in self._pending.values()],
            "scheduled": self._scheduled,
            "finals": self._finals,
            "far_tries": self._far_tries,
            "last_out": [[o.key, o.payload] for o in self._last_out],
        }
        p = Path(path)
        tmp = p.with_name(p.name + ".tmp")
        try:
            with open(tmp, "wb") as fh:
                fh.write(msgpack.packb(state, use_bin_type=True))
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, p)
        except OSError:
            tmp.unlink(missing_ok=True)  # a half-written state would only take the space a retry needs
            raise

    def load_state(self, path: str | Path) -> None:
        """Restore a state written by :meth:`save_state` (the graph is rebuilt from its submaps and
        integrations, not recomputed)."""
        source = str(path)
        fresh = Merger(self.keys, self.config)
        try:
            state = msgpack.unpackb(Path(path).read_bytes(), raw=False)
            if not isinstance(state, dict) or state.get("v") != STATE_VERSION:
                raise BadInput(source, f"not a fleetmap merger state file (version {STATE_VERSION})")
            for payload in state["submaps"]:
                m = decode(bytes(payload))
                if not isinstance(m, LocalMap):
                    raise ValueError(f"a saved submap is a {m.SCHEMA}")
                fresh._enter(m)
            for e in state["edges"]:
                fresh.graph.add_edge(
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
                        rivals=tuple(Transform2D(*t) for t in e.get("rivals", [])),
                    )
                )
            robots = {}
            for name, r in state["robots"].items():
                at = r.get("at")
                robots[name] = _Robot(
                    epoch=int(r["epoch"]),
                    stamp=float(r["stamp"]),
                    at=None if at is None else (str(at[0]), Transform2D(float(at[1]), float(at[2]), float(at[3]))),
                    relocalized={int(x) for x in r["relocalized"]},
                )
            pairs: dict[tuple[str, str], Transform2D | None] = {}
            for a, b, t in state.get("queue", []):
                if a in fresh.graph and b in fresh.graph:
                    pairs[(str(a), str(b))] = None if t is None else Transform2D(*t)
            pending = [decode(bytes(payload)) for payload in state.get("pending", [])]
            if not all(isinstance(m, LocalMap) for m in pending):
                raise ValueError("a saved pending submap is not a LocalMap")
            scheduled = {str(k): int(v) for k, v in state.get("scheduled", {}).items()}
            far_tries = {str(k): int(v) for k, v in state.get("far_tries", {}).items()}
            last_out = [Outgoing(str(key), bytes(payload)) for key, payload in state.get("last_out", [])]
            seq, stamp, finals = int(state["seq"]), float(state["stamp"]), int(state.get("finals", 0))
        except (OSError, ValueError, KeyError, TypeError, IndexError, msgpack.UnpackException, BadMessage) as exc:
            raise BadInput(source, f"cannot load the merger state: {exc}") from None
        self.graph, self.submaps, self._robots = fresh.graph, fresh.submaps, robots
        self._finished_epochs = fresh._finished_epochs
        self.seq, self.stamp, self._finals = seq, stamp, finals
        self._queue, self._scheduled, self._last_out = pairs, scheduled, last_out
        self._far_tries = far_tries
        self._pending = {m.submap_key: m for m in pending if isinstance(m, LocalMap)}
        if len(self.graph):
            self._result = self.graph.solve()
            self._index_result()
            self._global = self._global_map(self._result)


def _ordered(a: str, b: str) -> tuple[str, str]:
    """A pose-free pair, always one way (INTEGRATE(a, b) is not exactly the inverse of INTEGRATE(b,
    a): whatever order the submaps arrived in, the same edge)."""
    return (a, b) if a < b else (b, a)


def _information(value: object) -> tuple[float, ...] | None:
    """An edge's saved :attr:`~fleetmap.merger.graph.Edge.information` (None: not saved)."""
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
