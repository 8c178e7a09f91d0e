"""The merger's intake: what it takes off the bus, and which robots it keeps track of.

A message is decoded within its budget and dropped and counted if malformed
(:mod:`fleetmap.shared.io.messages`); one on a robot's key must be that robot's; a live merger
listens only to robots that hold their liveliness token, up to ``max_robots``; a stamp far ahead of
the receiver's clock is refused (:mod:`fleetmap.merger.clocks`); a final submap never changes; a
second live agent under one robot's id is refused, and the first keeps its maps; new submaps are
taken at the robot's budget (:mod:`fleetmap.merger.budget`). A robot that left with none of its
submaps placed is forgotten once nothing of it is left to try. :class:`~fleetmap.merger.engine.Merger`
is this and its steps.
"""

from __future__ import annotations

import json
import logging

import numpy as np
from fleetmap.merger.budget import SubmapBudget
from fleetmap.merger.clocks import from_the_future
from fleetmap.merger.outputs import Outgoing, Placement, Robot
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.scangraph import SCAN_CONSTRAINTS, KeyScan, is_key
from fleetmap.merger.schedule import FAR_BUDGET, PairSchedule
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.tracking import SAMPLE_SPACING, sample_segments
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import ROBOT_KINDS, FleetKeys, parse_map_key, parse_submap_key
from fleetmap.shared.io.messages import (
    BadMessage,
    FleetEvent,
    LocalMap,
    Message,
    Scan,
    decode,
)

log = logging.getLogger(__name__)

MAX_SUBMAP_SEGMENTS = 5000
"""The merger refuses a submap of more segments than this (dropped, logged and counted): one
integration's time grows with its segments, an agent's submaps hold tens to hundreds
(docs/decisions/003-a-fleet-that-lets-in-only-its-own.md)."""

_NO_ROBOT = Robot()
"""Who a robot the merger does not know is (refused nothing)."""


class Intake:
    """What the merger takes in, and the robots it keeps track of (the state is
    :class:`~fleetmap.merger.engine.Merger`'s, set up by it)."""

    keys: FleetKeys
    keep_key_scans: bool
    require_presence: bool
    stats: MergerStats
    stamp: float
    graph: PoseGraph
    schedule: PairSchedule
    placement: Placement
    budget: SubmapBudget | None
    submaps: dict[str, LocalMap]
    _config: FleetmapConfig
    _pending: dict[str, LocalMap]
    _held: dict[str, dict[str, LocalMap]]
    _robots: dict[str, Robot]
    _key_scans: dict[str, list[KeyScan]]
    _said_refused: set[tuple[str, int]]
    _left: set[str]
    _forgotten: bool

    @property
    def config(self) -> FleetmapConfig:
        """The parameters. A new one set here holds from the next message and step on (its pair
        schedule's too; the pose graph keeps the parameters it was made with)."""
        return self._config

    @config.setter
    def config(self, config: FleetmapConfig) -> None:
        self._config = config
        self.schedule.config = config

    # -- input -----------------------------------------------------------------------------
    def receive(self, key: str, payload: bytes, now: float | None = None, recalled: bool = False) -> list[Outgoing]:
        """Take one message off the bus; a malformed one is dropped, logged and counted. ``now``:
        the receiver's clock (s since 1970), against which a stamp too far ahead is refused
        (:mod:`fleetmap.merger.clocks`); ``recalled``: a submap the recorder kept (its robot may
        have left long ago)."""
        try:
            message = decode(payload)
        except BadMessage as exc:
            self.stats.malformed += 1
            self.stats.malformed_reasons[f"{exc.schema} {exc.field}"] += 1
            if self.stats.malformed <= 20 or self.stats.malformed % 1000 == 0:
                log.warning("dropped a malformed message on %s: %s (%d so far)", key, exc, self.stats.malformed)
            return []
        return self._take(key, message, now, recalled)

    def take(self, message: Message, now: float | None = None, recalled: bool = False) -> list[Outgoing]:
        """Take one typed message from an in-process caller (``fleetmap map``, replays,
        benchmarks), as :meth:`receive` takes it off the bus: on its robot's own key, with the
        same checks (a message is validated when it is made, so nothing is decoded here). A
        robot's event counts on its robot's events key; a message the merger does not take
        (another service's output) is counted as ignored."""
        robot = getattr(message, "robot", None)
        if isinstance(message, LocalMap):
            key = self.keys.localmap(message.robot)
        elif isinstance(message, Scan):
            key = self.keys.scan(message.robot)
        elif isinstance(message, FleetEvent) and robot is not None:
            key = self.keys.robot_events(robot)
        else:
            key = self.keys.events
        return self._take(key, message, now, recalled)

    def _take(self, key: str, message: Message, now: float | None, recalled: bool) -> list[Outgoing]:
        """What :meth:`receive` and :meth:`take` share: a valid message's checks and intake."""
        self.stats.received[message.SCHEMA] += 1
        robot = getattr(message, "robot", None)
        if not self._robots_own(key, message) or not self._admitted(robot, recalled) or not self._room_for(robot):
            return []
        if robot is not None and from_the_future(message.stamp, now):
            self._drop(
                "future_stamp", f"a {message.SCHEMA} of {robot} stamped {message.stamp - (now or 0):.0f} s ahead"
            )
            return []
        epoch = getattr(message, "epoch", None)
        if robot is not None and epoch in self._robots.get(robot, _NO_ROBOT).refused:
            self._drop("second_agent", f"a {message.SCHEMA} of {robot}'s epoch {epoch}, a second agent's")
            return []
        if isinstance(message, LocalMap):
            if key != self.keys.localmap(message.robot):
                self.stats.ignored += 1
                return []
            return self._take_submap(message, now, recalled)
        elif isinstance(message, Scan):
            if key != self.keys.scan(message.robot):
                self.stats.ignored += 1
                return []
            r = self._robot(message.robot)  # a robot that only scans so far is known, not placed
            # heard: a scan of an epoch taken (a restarted agent's scans of its new epoch come
            # before that epoch's first submap, and would make it look like a second agent)
            r.live = r.live or message.epoch in r.epochs
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

    def _admitted(self, robot: str | None, recalled: bool) -> bool:
        """Whether a live merger listens to ``robot``: one it knows (its maps stay after it left),
        or one that holds its liveliness token; else the message is dropped and counted."""
        if not self.require_presence or robot is None or recalled or robot in self._robots:
            return True
        self._drop("absent", f"a message of robot {robot!r}, which holds no liveliness token")
        return False

    def _room_for(self, robot: str | None) -> bool:
        """Whether the merger may keep track of ``robot`` (one it counts already, or one more under
        the limit). A live merger counts the robots that hold their token and were heard since."""
        r = self._robots.get(robot) if robot is not None else None
        if robot is None or (r is not None and (r.live or not self.require_presence)):
            return True
        if self.require_presence:
            counted = sum(1 for x in self._robots.values() if x.present and x.live)
        else:
            counted = len(self._robots)
        if counted < self.config.merge.max_robots:
            return True
        self._refuse(
            "max_robots", self.config.merge.max_robots, f"a message of robot {robot!r}, {counted} robots counted"
        )
        return False

    def _drop(self, reason: str, what: str) -> None:
        """Count (and log, the first times) a message refused for ``reason``."""
        self.stats.refused[reason] += 1
        n = self.stats.refused[reason]
        if n <= 10 or n % 1000 == 0:
            log.warning("dropped %s (%s: %d so far)", what, reason.replace("_", " "), n)

    def _refuse(self, limit: str, value: int, what: str) -> None:
        """Count (and log, the first times) something the merger's ``limit`` (at ``value``) refused."""
        self.stats.refused[limit] += 1
        n = self.stats.refused[limit]
        if n <= 10 or n % 1000 == 0:
            log.warning("refused %s: more than %s %s allows (%d refused so far)", what, limit, value, n)

    def _robot(self, name: str) -> Robot:
        return self._robots.setdefault(name, Robot())

    def _take_submap(self, m: LocalMap, now: float | None = None, recalled: bool = False) -> list[Outgoing]:
        key = m.submap_key
        held = self.submaps.get(key)
        waiting = self._pending.get(key, self._held.get(m.robot, {}).get(key))
        if (held is not None and m.version <= held.version) or (waiting is not None and m.version <= waiting.version):
            self.stats.stale += 1
            return []
        if (held is not None and held.final) or (waiting is not None and waiting.final):
            self._drop("final_submap", f"version {m.version} of submap {key}, final at an earlier version")
            return []
        if not self._same_agent(m):
            return [self._refused_event(m.robot, m.epoch)] if (m.robot, m.epoch) not in self._said_refused else []
        if len(m.segments) == 0:
            self.stats.ignored += 1
            return []
        if len(m.segments) > MAX_SUBMAP_SEGMENTS:
            self._refuse("max_submap_segments", MAX_SUBMAP_SEGMENTS, f"submap {key} of {len(m.segments)} segments")
            return []
        r = self._robot(m.robot)  # known from its first map (max_robots counts it)
        r.live = True
        r.epochs.add(m.epoch)
        budget = self.budget
        if budget is not None and now is not None and not recalled and held is None and key not in self._pending:
            self._hold(m, now, budget)
        else:
            self._pending[key] = m
        return []

    def _hold(self, m: LocalMap, now: float, budget: SubmapBudget) -> None:
        """A new submap under the budget (:mod:`fleetmap.merger.budget`): taken if its robot may
        start one now and holds none back; else held back behind them, up to the budget's burst;
        else refused and counted."""
        held = self._held.setdefault(m.robot, {})
        key = m.submap_key
        if key in held or (not held and budget.admit(m.robot, now)):
            (held if key in held else self._pending)[key] = m
        elif len(held) < budget.burst:
            held[key] = m
        else:
            self._drop("submap_budget", f"submap {key}: {m.robot} started more than {budget.burst:.0f} in a window")
        if not held:
            del self._held[m.robot]

    def release(self, now: float) -> None:
        """Take the submaps the budget held back that their robots may start by ``now``."""
        if self.budget is None:
            return
        for robot in list(self._held):
            held = self._held[robot]
            while held and self.budget.admit(robot, now):
                key = next(iter(held))
                self._pending[key] = held.pop(key)
            if not held:
                del self._held[robot]

    def _same_agent(self, m: LocalMap) -> bool:
        """Whether a submap of an epoch new to the merger comes from the agent it hears already:
        a new epoch without a link to an earlier one (an agent's first) newer than every epoch of a
        robot whose token is held and that was heard since is a second agent under its id, started
        by mistake; it and the epochs that descend from it are refused, and the first agent keeps
        its maps. After the robot left, such an epoch is its restarted agent, taken."""
        r = self._robots.get(m.robot)
        if r is None or m.epoch in r.epochs:
            return True
        link = m.previous_epoch_link
        second = link is None and r.present and r.live and bool(r.epochs) and m.epoch > max(r.epochs)
        if not second and (link is None or link.epoch not in r.refused):
            return True
        r.refused.add(m.epoch)
        self._drop("second_agent", f"epoch {m.epoch} of {m.robot} from a second live agent under its id")
        return False

    def _refused_event(self, robot: str, epoch: int) -> Outgoing:
        """The event that says an epoch of ``robot`` is refused (once an epoch), so that whoever
        waits for its maps to be merged (``fleetmap run``) knows they never will be."""
        self._said_refused.add((robot, epoch))
        detail = json.dumps({"epoch": epoch, "why": "a second live agent under its id"})
        return Outgoing(self.keys.events, FleetEvent("refused", robot, self.stamp, detail).to_msgpack())

    def follows(self, robot: str, epoch: int) -> bool:
        """Whether the pose of ``robot``'s epoch may follow its scans: an epoch the merger took."""
        r = self._robots.get(robot)
        return r is not None and epoch in r.epochs

    def _take_scan(self, scan: Scan) -> None:
        """Keep a placed scan that is a key scan of its submap (:func:`fleetmap.merger.scangraph.is_key`)."""
        if (
            not (self.keep_key_scans and SCAN_CONSTRAINTS)
            or scan.submap is None
            or scan.pose is None
            or not len(scan.segments)
        ):
            return
        key = f"{scan.robot}/{scan.epoch}/{scan.submap}"
        held = self._key_scans.setdefault(key, [])
        if held and scan.index <= held[-1].index:
            return  # a scan again, or out of order
        if not is_key(held[-1].pose if held else None, scan.pose):
            return
        samples = sample_segments(np.asarray(scan.segments), SAMPLE_SPACING)
        held.append(KeyScan(scan.robot, scan.epoch, scan.index, key, scan.pose, samples))
        self.stats.key_scans += 1

    def presence(self, robot: str, present: bool, stamp: float) -> list[Outgoing]:
        """A robot's liveliness token appeared or went: a join or leave event. Its maps stay,
        unless none of them is placed once the merger has tried them all: a robot that left and
        was merged with nothing is forgotten, its submaps and all (it takes no room, in memory or
        in the state file; :meth:`_forget_the_unplaced`)."""
        if not self.require_presence and not self._room_for(robot):
            return []
        r = self._robot(robot)
        r.present, r.live = present, False
        if present:
            self._left.discard(robot)
        else:
            self._left.add(robot)
            self._forget_the_unplaced()
        kind = "join" if present else "leave"
        return [Outgoing(self.keys.events, FleetEvent(kind, robot, max(stamp, 0.0)).to_msgpack())]

    def _placed_robot(self, robot: str) -> bool:
        """Whether a submap of ``robot`` is in a component its pose is given in (merged with
        another epoch, or its first epoch in the largest component)."""
        for key, index in self.placement.where.items():
            owner, epoch, _ = parse_submap_key(key)
            if owner == robot and self.placement.gives_poses(index, epoch):
                return True
        return False

    def _forget_the_unplaced(self) -> None:
        """Forget the robots that left, none of whose submaps is placed, once nothing of theirs is
        left to try (no submap waiting, no pair queued, no search budget left): a busy merger does
        not forget a robot it has not got to yet."""
        for robot in sorted(self._left):
            if self._placed_robot(robot):
                self._left.discard(robot)
            elif not self._work_for(robot):
                self._left.discard(robot)
                self._forget(robot)

    def _work_for(self, robot: str) -> bool:
        def mine(key: str) -> bool:
            return key.split("/", 1)[0] == robot

        s = self.schedule
        budget = FAR_BUDGET
        return (
            any(mine(k) for k in self._pending)
            or robot in self._held
            or any(mine(a) or mine(b) for a, b in s.queue)
            or any(mine(k) and s.far_tries.get(k, 0) < budget for k in s.idle_candidates(self.placement))
        )

    def _forget(self, robot: str) -> None:
        mine = [k for k in [*self.submaps, *self._pending] if parse_submap_key(k)[0] == robot]
        s = self.schedule
        for key in mine:
            self.graph.remove_map(key)
            self.submaps.pop(key, None)
            self._pending.pop(key, None)
            s.scheduled.pop(key, None)
            s.far_tries.pop(key, None)
            s.far_rank.forget(key)
            self._key_scans.pop(key, None)
        self._held.pop(robot, None)
        if self.budget is not None:
            self.budget.forget(robot)
        gone = set(mine)
        s.queue = {pair: t for pair, t in s.queue.items() if gone.isdisjoint(pair)}
        s.windows = {pair: w for pair, w in s.windows.items() if gone.isdisjoint(pair)}
        s.finished_epochs = {e for e in s.finished_epochs if parse_map_key(e)[0] != robot}
        self._forgotten = bool(mine) or self._forgotten
        if gone & self.placement.where.keys():  # the last solve's components name them: solve without
            self.placement = Placement.of(self.graph.solve(fuse_maps=False) if len(self.graph) else None)
        del self._robots[robot]
        log.info("forgot robot %s: it left before any of its %d submaps was placed", robot, len(mine))
