"""The merger service: :class:`~fleetmap.merger.engine.Merger` on a bus (``fleetmap merger``).

:class:`MergerService` wraps it for a bus: subscriptions, a queryable with the current global map,
presence from liveliness tokens, and an optional state file that a restarted merger loads
(:meth:`Merger.save_state`).
"""

from __future__ import annotations

import logging
import math
import queue
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from fleetmap.merger.budget import SubmapBudget
from fleetmap.merger.clocks import CLOCK_SKEW, from_the_future
from fleetmap.merger.engine import Merger, Outgoing
from fleetmap.merger.follow import PoseFollower
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.bus import Bus, BusError, Handle
from fleetmap.shared.io.keys import parse_submap_key
from fleetmap.shared.io.messages import (
    BadMessage,
    FleetEvent,
    LocalMap,
    RobotPose,
    Scan,
)

log = logging.getLogger(__name__)

RECALL_SECONDS = 5.0
"""How long a starting merger waits for the recorder's maps (no recorder: no wait)."""
STATE_ERROR_EVERY = 10.0
"""Seconds between the ERROR lines of a merger that cannot save its state."""
POSE_QUEUE = 10_000
"""Scans the pose thread keeps waiting at most (more are dropped and counted: a flood)."""
STATUS_SECONDS = 5.0
"""Seconds between the live merger's status lines (INFO)."""
STATUS_WINDOW = 60.0
"""The status line's latency covers the submaps merged in this many last seconds."""
ANOTHER_MERGER = (
    "another merger (%s) is on this fleet: two mergers publish two global maps under one key, and a shared "
    "--state file is written by both; stop one"
)


class _Recalled(bytes):
    """A submap the recorder kept, recalled at start (its robot may have left long ago)."""


class _RecalledAtLeave(_Recalled):
    """A submap of a robot that just left, as the recorder kept it (:meth:`MergerService._recall`)."""


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
        step_seconds: float | None = None,
    ) -> None:
        if step_seconds is None:
            step_seconds = merger.config.merge.step_seconds  # the live preset's (fleetmap/examples/live.toml)
        if not step_seconds >= 0 or math.isinf(step_seconds):
            raise BadInput("step_seconds", f"must be 0 (no budget) or a positive number, got {step_seconds}")
        self.bus = bus
        self.merger = merger
        merger.require_presence = True  # a live fleet's robots hold liveliness tokens
        merger.budget = SubmapBudget.of(merger.config)  # and take the graph at a robot's pace
        self.keys = merger.keys
        self.state_file = Path(state_file) if state_file else None
        self.tick = tick
        self.step_seconds = step_seconds
        self._arrived: dict[str, float] = {}
        """When each submap waiting to be taken in first arrived (monotonic s)."""
        self._latencies: deque[tuple[float, float]] = deque()
        """(when, seconds from arrival to the global map) of the submaps taken in the last minute."""
        self._placed: dict[str, tuple[int | None, int]] = {}
        """Per robot: its component after the last step (None: not placed) and its epoch."""
        self._ever_placed: set[tuple[str, int]] = set()
        """(robot, epoch) placed at some step."""
        self._components = 0
        self.state_errors = 0
        """Failed writes of the state file (disk full)."""
        self._state_error_said = -math.inf
        self.clock = clock
        self._inbox: queue.SimpleQueue[tuple[str, bytes | bool]] = queue.SimpleQueue()
        self._handles: list[Handle] = []
        self._snapshot = merger.global_map.to_msgpack()
        self._maps_arrived = 0
        """Local maps that arrived so far (a long step ends early when one does)."""
        self.follower = PoseFollower(
            lambda pose: self.bus.publish(self.keys.pose(pose.robot), pose.to_msgpack()), merger.config.merge.max_robots
        )
        """Robot poses between steps, from their placed scans (:mod:`fleetmap.merger.follow`)."""
        self._scans: queue.Queue[tuple[str, bytes]] = queue.Queue(POSE_QUEUE)
        self._follow_errors = 0
        self.future_scans = 0
        """Scans the pose thread dropped: stamped further ahead than :data:`CLOCK_SKEW`."""
        self._stop_following = threading.Event()
        self._following = threading.Thread(target=self._follow, name="merger-poses", daemon=True)
        self._to_recall: set[str] = set()
        """Robots that left, whose maps the recall thread is to ask the recorder for (:meth:`_recall_left`)."""
        self._recalling: threading.Thread | None = None
        self._recall_lock = threading.Lock()
        self.recalled_at_leave = 0
        """Submap versions this merger had not heard, recalled from the recorder when their robot left."""
        self.instance = f"merger {secrets.token_hex(6)}"
        """This service's name in its ``merger_start`` event, to tell another merger's start from its own."""
        self.other_mergers: set[str] = set()
        """Other mergers seen on the fleet: answering the state query at start, or starting later."""

    def start(self) -> None:
        keys = self.keys
        # Another merger answers the state query (before this one declares its own): one fleet, two
        # mergers, two global maps. Said, not refused: an operator decides which one to stop.
        if self.bus.query(keys.state, timeout=RECALL_SECONDS):
            self._another_merger("answers the merger's state query")
        self._handles.append(self.bus.subscribe(keys.all_localmaps, self._on_message))
        self._handles.append(self.bus.subscribe(keys.all_scans, self._on_scan))
        self._handles.append(self.bus.subscribe(keys.all_robot_events, self._on_message))
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
        self._following.start()
        now = self.clock()
        self.bus.publish(keys.events, FleetEvent("merger_start", None, now, self.instance).to_msgpack())
        # A (re)started merger says where it stands, and asks every robot for its latest local
        # map of every epoch.
        self._publish(self.merger.where_it_stands())
        self.bus.publish(keys.events, FleetEvent("republish_request", None, now).to_msgpack())
        # ... and the recorder for the newest version of every submap it recorded: robots that
        # finished while the merger was down cannot answer (versions it holds are stale, dropped)
        recalled = self._recall(None)
        if recalled:
            log.info("recalled %d submaps from the recorder", recalled)

    def _recall(self, robots: set[str] | None) -> int:
        """Ask the recorder for the newest version of every submap it recorded (of ``robots``
        only, if given) and queue them; how many. A robot that left sends nothing more: a version
        of its the bus did not bring here (a live 16-robot session once ended with a robot's last
        version of a submap recorded and never integrated, the runner waiting for it; decision
        record 073) would be missing from the map for good. So the robots that leave have their
        maps recalled (:meth:`_recall_left`); versions already held are stale, dropped."""
        keys, marker = self.keys, _Recalled if robots is None else _RecalledAtLeave
        queued = 0
        try:
            answers = self.bus.query(keys.recorder_maps, timeout=RECALL_SECONDS)
        except BusError as exc:  # the session closed meanwhile (the service stopping)
            log.debug("no recall of the maps of %s: %s", robots, exc)
            return 0
        for payload in answers:
            try:
                owner = LocalMap.from_msgpack(payload).robot
            except BadMessage:
                self.merger.stats.malformed += 1  # (an int: one more or less from two threads)
                continue
            if robots is None or owner in robots:
                self._inbox.put((keys.localmap(owner), marker(payload)))
                queued += 1
        return queued

    def _on_message(self, key: str, payload: bytes) -> None:
        if key.endswith("/localmap"):
            self._maps_arrived += 1
        self._inbox.put((key, payload))

    def _on_scan(self, key: str, payload: bytes) -> None:
        self._inbox.put((key, payload))
        try:
            self._scans.put_nowait((key, payload))
        except queue.Full:
            self.merger.stats.poses_dropped += 1

    def _follow(self) -> None:
        """The pose thread: each placed scan moves its robot's global pose (:mod:`.follow`) while
        the merger steps; the inbox's copy of the scan counts what is wrong with it. Nothing ends
        it but :meth:`close`: an error is logged and the next scan taken."""
        while not self._stop_following.is_set():
            try:
                key, payload = self._scans.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                scan = Scan.from_msgpack(payload)
                if from_the_future(scan.stamp, self.clock()):
                    self.future_scans += 1
                    if self.future_scans <= 10 or self.future_scans % 1000 == 0:
                        log.warning(
                            "dropped a scan of %s stamped %.0f s ahead of this clock (more than %.0f s; %d so far)",
                            scan.robot,
                            scan.stamp - self.clock(),
                            CLOCK_SKEW,
                            self.future_scans,
                        )
                elif key == self.keys.scan(scan.robot) and self.merger.follows(scan.robot, scan.epoch):
                    self.follower.scan(scan)
            except BadMessage:
                continue
            except Exception:
                self._follow_errors += 1
                if self._follow_errors <= 10 or self._follow_errors % 1000 == 0:
                    log.exception("the pose thread failed on a scan on %s (%d so far)", key, self._follow_errors)

    def _on_query(self, selector: str) -> bytes:
        return self._snapshot

    def _publish_step(self, out: list[Outgoing]) -> None:
        """A step's messages in order, its robot poses through the pose follower (each the newest
        placed scan's under the step's frames where that is newer; never one older than a pose
        already published)."""
        self.follower.merged(self.merger.pose_frames())
        for o in out:
            if self.keys.parse(o.key).kind == "pose":
                self.follower.step(RobotPose.from_msgpack(o.payload))
            else:
                self.bus.publish(o.key, o.payload)

    def _publish(self, out: list[Outgoing]) -> None:
        for o in out:
            self.bus.publish(o.key, o.payload)

    def _drain(self) -> None:
        while True:
            try:
                key, item = self._inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, bool):
                robot = self._token_robot(key)
                if robot is not None:
                    log.info("robot %s %s", robot, "joined" if item else "left")
                    self._publish(self.merger.presence(robot, item, self.clock()))
                    if not item:
                        self._recall_left(robot)
            else:
                if key == self.keys.events:
                    self._note_merger_start(item)
                stale = self.merger.stats.stale
                self._publish(self.merger.receive(key, item, self.clock(), recalled=isinstance(item, _Recalled)))
                m = LocalMap.from_msgpack(item) if isinstance(item, _RecalledAtLeave) else None
                if m is not None and self.merger.stats.stale == stale and m.submap_key in self.merger.waiting:
                    self.recalled_at_leave += 1
                    log.warning(
                        "took submap %s version %d from the recorder after %s left: this merger had not heard it",
                        m.submap_key,
                        m.version,
                        m.robot,
                    )
        self.merger.release(self.clock())
        now = time.monotonic()
        for waiting in self.merger.waiting:
            self._arrived.setdefault(waiting, now)

    def _recall_left(self, robot: str) -> None:
        """Recall the maps of ``robot``, which just left (:meth:`_recall`), if it sent any, off the
        merging thread: one recall thread at a time, which takes every robot that left meanwhile
        in one query (tokens that come and go cost one query at a time, not one each)."""
        if not any(parse_submap_key(k)[0] == robot for k in (*self.merger.submaps, *self.merger.waiting)):
            return
        with self._recall_lock:
            self._to_recall.add(robot)
            if self._recalling is None:
                self._recalling = threading.Thread(target=self._recall_loop, name="merger-recall", daemon=True)
                self._recalling.start()

    def _recall_loop(self) -> None:
        while True:
            with self._recall_lock:
                robots, self._to_recall = self._to_recall, set()
                if not robots:
                    self._recalling = None
                    return
            self._recall(robots)

    def _note_merger_start(self, payload: bytes) -> None:
        """Warn of a ``merger_start`` event that is not this service's own: a second merger started."""
        try:
            event = FleetEvent.from_msgpack(payload)
        except BadMessage:
            return  # the engine counts it
        if event.kind == "merger_start" and event.detail != self.instance:
            self._another_merger(f"started: {event.detail or 'an older version'}")

    def _another_merger(self, what: str) -> None:
        self.other_mergers.add(what)
        log.warning(ANOTHER_MERGER, what)

    def _token_robot(self, key: str) -> str | None:
        """The robot a liveliness token under ``alive/`` names; None, counted and logged, for a
        token whose name is no robot id (anyone on an open fleet may declare one)."""
        try:
            parsed = self.keys.parse(key)
        except BadInput:
            parsed = None
        if parsed is not None and parsed.kind == "alive":
            return parsed.robot
        stats = self.merger.stats
        stats.malformed += 1
        stats.malformed_reasons["liveliness token"] += 1
        n = stats.malformed_reasons["liveliness token"]
        if n <= 10 or n % 1000 == 0:
            log.warning("ignored the liveliness token %r: not a robot id (%d such tokens so far)", key[:128], n)
        return None

    def run_once(self) -> bool:
        """Take what arrived and step if there is work (a local map pending, or pairs of maps to
        integrate), for about ``step_seconds`` at most when it takes new local maps in (one
        integration at least), else as long as the last solve took; True if it stepped."""
        self._drain()
        return self._step()

    def _step(self) -> bool:
        if not self.merger.has_work:
            return False
        # A step that takes new submaps in integrates for step_seconds, so they reach the global
        # map soon; one with only queued pairs integrates as long as a solve takes (at least half
        # of the merger's time goes to the backlog), unless a local map arrives meanwhile.
        start, arrived = time.monotonic(), self._maps_arrived
        short = start + self.step_seconds
        long = short if self.merger.pending else start + max(self.step_seconds, self.merger.solve_seconds)

        def past_deadline() -> bool:
            now = time.monotonic()
            return now >= long or (now >= short and self._maps_arrived != arrived)

        out = self.merger.step(enough=past_deadline if self.step_seconds > 0 else None, now=self.clock())
        self._save()
        self._snapshot = self.merger.global_map.to_msgpack()
        self._publish_step(out)
        self._note_step()
        return True

    def _note_step(self) -> None:
        """After a step: how long the submaps it took had waited (received -> in the global map),
        and, at INFO, robots placed, lost or relocalized and components merged."""
        now = time.monotonic()
        waiting = set(self.merger.waiting)
        for key in [k for k in self._arrived if k not in waiting]:
            self._latencies.append((now, now - self._arrived.pop(key)))
        while self._latencies and now - self._latencies[0][0] > STATUS_WINDOW:
            self._latencies.popleft()
        for robot in self.merger.robots:
            pose, component = self.merger.robot_pose(robot)
            epoch = self.merger.robot_epoch(robot)
            was = self._placed.get(robot)
            if was is not None and epoch > was[1]:
                log.info("robot %s lost its place (epoch %d): searching", robot, epoch)
            if pose is not None and (robot, epoch) not in self._ever_placed:
                self._ever_placed.add((robot, epoch))
                log.info("robot %s %s in component %d", robot, "relocalized" if epoch else "placed", component)
            self._placed[robot] = (component, epoch)
        components = len(self.merger.global_map.components)
        if components < self._components:
            log.info("maps merged: %d components now", components)
        self._components = components

    def status(self) -> str:
        """One line: robots, submaps, components, work waiting, and the latency of the last minute."""
        placed = sum(1 for c, _ in self._placed.values() if c is not None)
        lat = sorted(d for _, d in self._latencies)
        latency = (
            f"latency median {lat[len(lat) // 2]:.1f} s, p95 {lat[min(len(lat) - 1, int(0.95 * len(lat)))]:.1f} s"
            if lat
            else "no submap merged in the last minute"
        )
        return (
            f"{len(self.merger.robots)} robots ({placed} placed), {len(self.merger.graph)} submaps, "
            f"{len(self.merger.global_map.components)} components, {self.merger.queued} pairs queued, "
            f"{self.merger.pending} submaps waiting; {latency}"
        )

    def _save(self) -> bool:
        """Save the state file, if any; a failed write (disk full) is said loudly and the merger goes
        on serving from memory (the previous state file stays whole); whether it was saved."""
        if self.state_file is None:
            return False
        try:
            self.merger.save_state(self.state_file)
        except OSError as exc:
            self.state_errors += 1
            if self.state_errors == 1 or time.monotonic() - self._state_error_said >= STATE_ERROR_EVERY:
                self._state_error_said = time.monotonic()
                log.error(
                    "cannot save the state to %s: %s (%d failed saves); merging goes on, a restart would resume "
                    "from the last saved state",
                    self.state_file,
                    exc.strerror or exc,
                    self.state_errors,
                )
            return False
        return True

    def run(self, stop: threading.Event) -> None:
        said = time.monotonic()
        while not stop.is_set():
            if not self.run_once():
                stop.wait(self.tick)
            if time.monotonic() - said >= STATUS_SECONDS:
                said = time.monotonic()
                log.info("status: %s", self.status())
        # At the stop (SIGTERM), whatever the queue: what arrived is taken off the bus and saved with
        # the queue, not integrated, so the service ends within a step. It waits in the state file
        # for the next start; without one it is lost, and said so.
        self._drain()
        saved = self._save()
        left = self.merger.backlog
        if left:
            kept = f"kept in {self.state_file} for the next start" if saved else "lost (no --state, or it failed)"
            log.warning("stopping with %d integrations or maps not yet taken in: %s", left, kept)

    def close(self) -> None:
        self._stop_following.set()
        if self._following.is_alive():
            self._following.join(timeout=5.0)
        with self._recall_lock:
            recalling = self._recalling
        if recalling is not None:
            recalling.join(timeout=RECALL_SECONDS + 1.0)
        try:
            self.bus.publish(self.keys.events, FleetEvent("merger_stop", None, self.clock()).to_msgpack())
            self.bus.flush()
        finally:
            for h in self._handles:
                h.close()
            self._handles.clear()
