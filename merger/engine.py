"""The merger: submaps in, global maps and robot poses out.

:class:`Merger` is the whole logic as a library (no network, no clock): ``receive`` takes the bytes
of a bus message, ``step`` takes the submaps received since the last step into the pose graph
(:mod:`fleetmap.merger.posegraph`), integrates the pairs of submaps due, solves the graph and returns
the messages to publish. It is deterministic given the same messages in the same order, which is
what lets a recorded session replay to the same map: every step is published as a
:class:`~fleetmap.shared.io.messages.MergerStep` naming the submap versions it took, in order, and how
many pairs it integrated, and a replay follows those steps.

Its parts, one file each: which pairs a submap is due and in what order
(:mod:`fleetmap.merger.schedule`: O(n) integrations for n submaps, not n^2); what a step publishes,
from where the solve placed every submap (:mod:`fleetmap.merger.outputs`: the global map, every
robot's pose, ``MergeEdge`` for every integration of the step, ``MergerStep``, relocalization
events); the state file a merger resumes from (:mod:`fleetmap.merger.state`); what it counts
(:mod:`fleetmap.merger.stats`).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
from fleetmap.merger.budget import SubmapBudget
from fleetmap.merger.executor import Executor, InlineExecutor, PairJob, pair_result
from fleetmap.merger.executor import Handle as JobHandle
from fleetmap.merger.graph import Component as GraphComponent
from fleetmap.merger.graph import Edge, MergeResult
from fleetmap.merger.intake import Intake
from fleetmap.merger.outputs import (
    Outgoing,
    Placement,
    Robot,
    global_map_of,
    robot_pose_messages,
)
from fleetmap.merger.outputs import scan_poses as placed_scan_poses
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.scangraph import KeyScan
from fleetmap.merger.schedule import PairSchedule
from fleetmap.merger.startposes import StartFrame
from fleetmap.merger.state import MergerState, read_state, write_state
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.mapgrid import with_viewpoints
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys, parse_submap_key
from fleetmap.shared.io.messages import (
    Component,
    GlobalMap,
    LocalMap,
    MergeEdge,
    MergerStep,
)

__all__ = ["Merger", "MergerStats", "Outgoing"]

log = logging.getLogger(__name__)


class Merger(Intake):
    """The merger's logic: :meth:`receive` messages, :meth:`step`, publish what it returns."""

    def __init__(
        self,
        keys: FleetKeys,
        config: FleetmapConfig | None = None,
        executor: Executor | None = None,
        keep_key_scans: bool = False,
        start_poses: dict[str, Transform2D] | None = None,
    ) -> None:
        """``keep_key_scans``: keep the key scans it hears (:meth:`scan_poses` refines with them;
        ``fleetmap map`` asks for it, a live merger that never calls it does not keep them).
        ``start_poses``: robots' known start poses in one shared frame, by robot id
        (:mod:`fleetmap.merger.startposes`)."""
        self.keys = keys
        self.keep_key_scans = keep_key_scans
        self._config = config or FleetmapConfig()
        self.executor: Executor = executor or InlineExecutor()
        """Where the integrations run (:mod:`fleetmap.merger.executor`); the caller closes it."""
        self.graph = PoseGraph(self.config.integration, self.config.merge, self.config.tracking)
        self.start = StartFrame(start_poses, self.config.merge) if start_poses else None
        """The known start poses, linked into the graph as the robots' first submaps arrive."""
        self.solve_seconds = 0.0
        """How long the last step's solve took (what a step of integrations alone is worth)."""
        self.stats = MergerStats()
        self.seq = 0
        self.stamp = 0.0
        self.submaps: dict[str, LocalMap] = {}
        """The version of every submap in the graph, by submap key."""
        self.schedule = PairSchedule(self.graph, self.submaps, self.config, self.stats, self._refuse, self.executor)
        """Which pairs to integrate (:mod:`fleetmap.merger.schedule`)."""
        self.placement = Placement()
        """Where the last solve put every submap and epoch."""
        self._pending: dict[str, LocalMap] = {}
        """Submap versions received since the last step, by submap key, in arrival order."""
        self.budget: SubmapBudget | None = None
        """A live merger's budget of new submaps per robot (:mod:`fleetmap.merger.budget`); None: none."""
        self._held: dict[str, dict[str, LocalMap]] = {}
        """Per robot, its new submaps the budget holds back, by submap key, in arrival order."""
        self._robots: dict[str, Robot] = {}
        self._global: GlobalMap | None = None
        self._last_out: list[Outgoing] = []
        self._made: dict[int, tuple[GraphComponent, Component]] = {}
        """The global map's message components, by the solve's component (:func:`global_map_of`)."""
        self._unfused = False
        """Whether the last solve left the global map's walls out (``step(fuse=False)``)."""
        self._key_scans: dict[str, list[KeyScan]] = {}
        """The key scans of every submap, by submap key (:meth:`_take_scan`)."""
        self.require_presence = False
        """A live merger's robots hold liveliness tokens (:meth:`presence`): a message of a robot it
        does not know and that holds none is dropped, and ``max_robots`` counts the robots that hold
        one and were heard since. Offline (a log, a replay) every robot counts from its first map."""
        self._forgotten = False
        """Robots were forgotten since the last solve (:meth:`presence`): solve again."""
        self._said_refused: set[tuple[str, int]] = set()
        self._left: set[str] = set()
        """Robots that left with none of their submaps placed (yet)."""

    @property
    def _result(self) -> MergeResult | None:
        return self.placement.result

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
        """The submaps received that no step has taken into the graph yet (the budget's held back included)."""
        return [*self._pending, *(k for held in self._held.values() for k in held)]

    @property
    def backlog(self) -> int:
        """Submaps received and pairs queued that no step has taken yet."""
        return len(self.waiting) + len(self.schedule.queue)

    @property
    def has_work(self) -> bool:
        """Whether a step has something to do: submaps pending, pairs to integrate, or robots
        apart from the global map whose submaps have candidates left to try
        (:meth:`~fleetmap.merger.schedule.PairSchedule.idle_pairs`)."""
        return (
            bool(self._pending)
            or bool(self.schedule.queue)
            or self.schedule.searching(self.placement)
            or self._forgotten
        )

    @property
    def queued(self) -> int:
        """Pairs of submaps still to integrate."""
        return len(self.schedule.queue)

    # -- one step --------------------------------------------------------------------------
    def step(
        self,
        limit: int | None = None,
        enough: Callable[[], bool] | None = None,
        fuse: bool = True,
        now: float | None = None,
    ) -> list[Outgoing]:
        """Take the submaps received since the last step into the graph, integrate the pairs due
        (all of them, ``limit`` of them as a replay repeats a live step, or until ``enough()`` says
        the step took long enough), solve, and return the messages to publish. With ``fuse``
        False the global map's walls are left out (an offline run fuses them once, at its end: a
        step with ``fuse`` after one without solves again, work or none, to publish them). ``now``
        (the merger's clock) stamps the step; without it (offline) the newest submap's stamp does."""
        refuse = fuse and self._unfused and not self.has_work
        if not self.has_work and not refuse:
            return []
        batch = list(self._pending.values())
        self._pending.clear()
        self._forgotten = False
        for m in batch:
            self._enter(m)
        queue = self.schedule.queue
        for m in batch:
            self.schedule.submap(m, m.epoch == self._robots[m.robot].epoch, self.placement)
        if not queue and not refuse:
            self.schedule.idle_pairs(self.placement)
        new_edges, taken = self._integrate(limit, enough)
        self.schedule.behind = bool(queue)  # (before the solve queues the joins' pairs: new work)
        self.seq += 1
        self.stats.steps += 1
        self.stats.integrations += len(new_edges)
        self.stamp = now if now is not None else max([self.stamp] + [m.stamp for m in batch])
        out: list[Outgoing] = []
        for e in new_edges:
            t = e.transform
            said = MergeEdge(e.a, e.b, t.x, t.y, t.theta, max(e.value, 0.0), e.valid, self.stamp)
            out.append(Outgoing(self.keys.edges, said.to_msgpack()))
        solving = time.perf_counter()
        placed = self.placement
        apart = {epoch: frozenset(placed.epochs_in[i]) for epoch, i in placed.epoch_where.items()}
        solved = self.graph.solve(fuse_maps=fuse)
        self.solve_seconds = time.perf_counter() - solving
        self._unfused = not fuse
        self.placement = Placement.of(solved, self.placement)
        self.schedule.queue_joined(self.placement, apart)
        self.schedule.placed(self.placement)
        self._global = global_map_of(solved, self.seq, self.stamp, self._made)
        out.append(Outgoing(self.keys.globalmap, self._global.to_msgpack()))
        out += robot_pose_messages(self.keys, self._robots, self.submaps, self.placement, self.stamp)
        # Last: whoever sees the step has seen everything it produced (fleetmap run waits on it).
        step = MergerStep(
            self.seq,
            self.stamp,
            tuple(m.submap_key for m in batch),
            tuple(m.version for m in batch),
            integrations=taken,
            queued=len(queue),
        )
        out.append(Outgoing(self.keys.steps, step.to_msgpack()))
        self._last_out = out
        self._forget_the_unplaced()
        return out

    def _integrate(self, limit: int | None, enough: Callable[[], bool] | None) -> tuple[list[Edge], int]:
        """Integrate the queued pairs (all, ``limit`` of them, or until ``enough()``) on the executor
        and take their edges into the graph; the edges and how many pairs were taken off the queue."""
        queue = self.schedule.queue
        new_edges: list[Edge] = []
        taken = 0
        running: deque[tuple[PairJob, JobHandle]] = deque()
        while queue or running:
            # as many in flight as the executor keeps busy; results taken in the queue's order, so
            # the graph is the same whichever executor ran them (a pair whose two submaps are in
            # flight already waits for that result: whether it is due depends on it)
            # a step with no bound keeps a second job queued for each worker: one that ends before
            # the oldest in flight starts the next at once (a near registration takes a tenth of a
            # pose-free integration); a bounded step keeps one each, so it stops soon after its time
            depth = self.executor.capacity * (2 if limit is None and enough is None else 1)
            while queue and len(running) < depth:
                if (limit is not None and taken >= limit) or (
                    limit is None and enough is not None and taken and enough()
                ):
                    break
                pair, predicted = self.schedule.next_pair()
                if any({j.a, j.b} == set(pair) for j, _ in running):
                    break
                self.schedule.take(pair)
                taken += 1
                job = self.schedule.job(pair, predicted)
                if job is not None:
                    running.append((job, self.executor.submit(job, self.graph.indexes)))
            if not running:
                break
            job, handle = running.popleft()
            try:
                result = pair_result(handle)
            except Exception as exc:  # a job that failed where it ran: the merger goes on without it
                self.stats.failed += 1
                log.error("integrating %s and %s failed (%s: %s); dropped", job.a, job.b, type(exc).__name__, exc)
                continue
            if result.integration.exhausted:
                self.stats.exhausted += 1
                log.warning(
                    "%s and %s: the integration stopped at the work budget (merge.max_integration_work %d), not "
                    "valid (%d stopped so far)",
                    job.a,
                    job.b,
                    job.merge.max_integration_work,
                    self.stats.exhausted,
                )
            edge = self.graph.take(job, result)
            self.schedule.registered((job.a, job.b), edge.valid)
            new_edges.append(edge)
        return new_edges, taken

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
        # the newest by the robot's own count (submap, version), not by its stamps (a clock that
        # stepped back, or one far-future stamp, would keep an old pose for good)
        held = self.submaps.get(r.at[0]) if r.at is not None else None
        newer = held is None or (m.submap, m.version) >= (held.submap, held.version)
        if m.epoch == r.epoch and m.pose is not None and newer:
            r.at, r.stamp = (key, m.pose), m.stamp
        r.epochs.add(m.epoch)
        segment_map = SegmentMap(np.array(m.segments), ordered=False, oriented=True)
        if m.viewpoints is not None and len(m.viewpoints):
            segment_map = with_viewpoints(segment_map, m.viewpoints)
        self.graph.put_map(key, segment_map, m.version, keep_edges=True)
        if m.final:
            self.schedule.finished_epochs.add(f"{m.robot}/{m.epoch}")
        if m.link is not None:
            previous = f"{m.robot}/{m.epoch}/{m.link.submap}"
            self.graph.put_link(previous, key, m.link.transform, m.link.covariance_matrix)
        if self.start is not None:
            self.start.enter(self.graph, key)
        self.submaps[key] = m

    # -- outputs ---------------------------------------------------------------------------
    def robot_pose(self, robot: str) -> tuple[Transform2D | None, int | None]:
        """A robot's pose in its component's frame and the component's index; (None, None) if unknown."""
        r = self._robots.get(robot)
        if r is None or self._global is None:
            return None, None
        return self.placement.robot_pose(r)

    def pose_frames(self) -> dict[str, tuple[int, Transform2D]]:
        """Per submap a robot's pose may be given in (:meth:`robot_pose`'s rule): its component
        and its pose there, as the last step placed it (:mod:`fleetmap.merger.follow`)."""
        return self.placement.pose_frames()

    @property
    def global_map(self) -> GlobalMap:
        """The current global map (empty before the first step)."""
        return self._global if self._global is not None else GlobalMap(self.seq, self.stamp, ())

    @property
    def result(self) -> MergeResult | None:
        return self._result

    @property
    def key_scans(self) -> dict[str, list[KeyScan]]:
        """The key scans kept, by the submap that placed them (a merger made with ``keep_key_scans``)."""
        return self._key_scans

    def scan_poses(self) -> dict[tuple[str, int], tuple[int, Transform2D]]:
        """Every scan the last solve placed, by (robot, index): its component's number and its laser
        pose in that component's frame (:func:`fleetmap.merger.outputs.scan_poses`; the key scans
        refined only by a merger made with ``keep_key_scans``)."""
        return placed_scan_poses(self._result, self.submaps, self.graph, self._key_scans, self.config, self.stats)

    # -- state file ------------------------------------------------------------------------
    def save_state(self, path: str | Path) -> None:
        """Everything needed to resume (:mod:`fleetmap.merger.state`), written so that a merger
        killed while saving leaves the previous state whole."""
        s = self.schedule
        state = MergerState(
            seq=self.seq,
            stamp=self.stamp,
            submaps=[self.submaps[k] for k in self.graph.keys],
            edges=[e for e in self.graph.edges if not e.link],  # links come back with their submaps
            robots=self._robots,
            queue=s.queue,
            pending=[*self._pending.values(), *(m for held in self._held.values() for m in held.values())],
            scheduled=s.scheduled,
            finals=s.finals,
            far_tries=s.far_tries,
            last_out=self._last_out,
            behind=s.behind,
            windows=s.windows,
        )
        write_state(path, state)

    def load_state(self, path: str | Path) -> None:
        """Restore a state written by :meth:`save_state` (the graph is rebuilt from its submaps and
        integrations, not recomputed)."""
        state = read_state(path)
        fresh = Merger(self.keys, self.config, start_poses=self.start.poses if self.start is not None else None)
        try:
            for m in state.submaps:
                fresh._enter(m)
            for e in state.edges:
                fresh.graph.add_edge(e)
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise BadInput(str(path), f"cannot load the merger state: {exc}") from None
        self.graph, self.submaps, self._robots, self.start = fresh.graph, fresh.submaps, state.robots, fresh.start
        for name, r in self._robots.items():
            r.epochs = {parse_submap_key(k)[1] for k in self.submaps if parse_submap_key(k)[0] == name}
        self.seq, self.stamp, self._last_out = state.seq, state.stamp, state.last_out
        s = PairSchedule(self.graph, self.submaps, self.config, self.stats, self._refuse, self.executor)
        s.finished_epochs = fresh.schedule.finished_epochs
        s.queue = {(a, b): t for (a, b), t in state.queue.items() if a in self.graph and b in self.graph}
        s.scheduled, s.finals, s.far_tries, s.behind = state.scheduled, state.finals, state.far_tries, state.behind
        s.windows = {pair: w for pair, w in state.windows.items() if pair in s.queue}
        self.schedule = s
        self._pending = {m.submap_key: m for m in state.pending}
        if len(self.graph):
            solved = self.graph.solve()
            self.placement = Placement.of(solved)
            self._global = global_map_of(solved, self.seq, self.stamp, self._made)
