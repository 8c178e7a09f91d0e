"""The agent on the bus: paces a source's scans, publishes what the Agent says, answers republish requests.

:func:`run_agent` is the I/O edge around :class:`~fleetmap.agents.agent.Agent`:

1. declare the robot's liveliness token (``fleet/<fleet>/alive/<robot>``: the robot is up);
2. listen on the fleet's events for ``republish_request`` (robot None or this robot), and answer
   with the latest LocalMap of every epoch, so a merger that (re)started loses nothing; and for
   ``relocalized`` (this robot), which tells the agent its new epoch is placed
   (:meth:`~fleetmap.agents.agent.Agent.relocalized`: it stops publishing after every scan);
3. feed the scans to the agent at their stamps' pace (divided by ``speed``; 0: as fast as
   possible; the first scan at once) and publish each message on its key as it comes;
4. when the source ends or ``stop`` is set: the final LocalMap, flush the bus, undeclare.

Requests arrive on the bus's threads; they only set a flag, and the loop's thread answers them,
between scans or while waiting for the next one. A payload on the events key that is not a valid
FleetEvent is counted and ignored.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from fleetmap.agents.agent import Agent
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.bus import Bus, Handle
from fleetmap.shared.io.keys import FleetKeys, parse_submap_key
from fleetmap.shared.io.messages import BadMessage, FleetEvent, GlobalMap, LocalMap, Message, Scan, decode
from fleetmap.shared.io.sources import SourceScan

log = logging.getLogger(__name__)

POLL = 0.05
"""Longest wait (s) before the loop looks again at stop and republish requests."""
STATUS_SECONDS = 5.0
"""An agent says how far it is at INFO this often (s)."""


@dataclass(frozen=True)
class AgentSummary:
    """What one run of an agent did."""

    robot: str
    scans: int
    placed: int
    epochs: int
    published: int
    """Messages published (republished ones included)."""
    republished: int
    """Republish requests answered."""
    bad_events: int
    """Payloads on the events key that were not FleetEvents."""
    stopped: bool
    """True when ``stop`` ended the run before the source did."""
    seconds: float

    def line(self) -> str:
        ended = "stopped" if self.stopped else "done"
        return (
            f"agent {self.robot} {ended}: {self.scans} scans, {self.placed} placed, {self.epochs} epochs, "
            f"{self.published} messages published, {self.republished} republish requests, "
            f"{self.bad_events} bad events, {self.seconds:.1f} s"
        )


class _FleetEvents:
    """What the fleet's events ask of one robot (republish requests, and the epochs the merger
    relocalized), from the bus's threads to the agent's loop."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.pending = threading.Event()
        self._lock = threading.Lock()
        self.bad = 0
        self.relocalized: list[int] = []
        """Epochs of this robot the merger said it placed, not yet told to the agent."""

    def on_event(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload)
        except BadMessage as exc:
            self._count_bad(f"{key}: {exc}")
            return
        if not isinstance(message, FleetEvent):
            self._count_bad(f"{key}: a {message.SCHEMA} is not a fleet event")
        elif message.kind == "republish_request" and message.robot in (None, self.robot):
            self.pending.set()
        elif message.kind == "relocalized" and message.robot == self.robot:
            try:
                epoch = int(json.loads(message.detail)["epoch"])
            except (ValueError, TypeError, KeyError) as exc:
                self._count_bad(f"{key}: a relocalized event without an epoch ({exc!r})")
                return
            with self._lock:
                self.relocalized.append(epoch)

    def _count_bad(self, why: str) -> None:
        with self._lock:
            self.bad += 1
            n = self.bad
        log.warning("ignored on the events key (%d so far): %s", n, why)

    def take_relocalized(self) -> list[int]:
        """The epochs relocalized since the last call."""
        with self._lock:
            epochs, self.relocalized = self.relocalized, []
        return epochs

    def take(self) -> bool:
        """Whether a request came since the last call."""
        if self.pending.is_set():
            self.pending.clear()
            return True
        return False


def message_key(keys: FleetKeys, message: Message) -> str:
    """Where an agent publishes a message: its scan, local map or events key."""
    if isinstance(message, Scan):
        return keys.scan(message.robot)
    if isinstance(message, LocalMap):
        return keys.localmap(message.robot)
    if isinstance(message, FleetEvent) and message.robot is not None:
        return keys.robot_events(message.robot)
    raise TypeError(f"an agent does not publish {type(message).__name__}")


FIRST_EPOCH_WAIT = 2.0
"""Seconds a starting agent waits for the merger to say which epochs of its robot it holds."""


def first_epoch(bus: Bus, keys: FleetKeys, robot: str) -> int:
    """The first epoch of this run of ``robot``: after every epoch of it in the merger's global map
    (its state queryable), so a robot restarted under its id, or a second one started by mistake,
    never publishes a submap the merger holds already; 0 when the merger holds none of it or none
    answers (a merger that starts later refuses a run that reuses epoch numbers)."""
    newest = -1
    for payload in bus.query(keys.state, timeout=FIRST_EPOCH_WAIT):
        try:
            global_map = GlobalMap.from_msgpack(payload)
        except BadMessage as exc:
            log.warning("%s: the merger's state is not a global map (%s); starting at epoch 0", robot, exc)
            return 0
        for component in global_map.components:
            for member in component.members:
                owner, epoch, _ = parse_submap_key(member)
                if owner == robot:
                    newest = max(newest, epoch)
    return newest + 1


def _start_after_known(bus: Bus, keys: FleetKeys, agent: Agent) -> None:
    epoch = first_epoch(bus, keys, agent.robot)
    if epoch:
        log.info("%s: the merger holds its epochs up to %d: this run starts at epoch %d", agent.robot, epoch - 1, epoch)
        agent.start_at(epoch)


def run_agent(
    source: Iterable[SourceScan],
    agent: Agent,
    bus: Bus,
    keys: FleetKeys,
    speed: float,
    stop: threading.Event,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], object] | None = None,
    wait_for_listener: float = 0.0,
    start_after_known: bool = True,
    source_ends_at_stop: bool = False,
) -> AgentSummary:
    """Run ``agent`` on ``source`` over ``bus`` until the source ends or ``stop`` is set.

    ``sleep(seconds)`` waits between scans (default: ``stop.wait``, so a stop cuts the wait
    short); ``clock`` and ``sleep`` are injectable so a test can step the pacing. With
    ``wait_for_listener`` > 0 the first scan waits up to that many seconds for something to
    subscribe to the robot's local maps (a merger or recorder starting at the same time). With
    ``start_after_known`` the run's first epoch follows the robot's epochs the merger holds
    (:func:`first_epoch`). A source that ends itself when ``stop`` is set, giving back first the
    scans it holds (``source_ends_at_stop``: a live robot's, :class:`~fleetmap.agents.ros2_source.Ros2LiveSource`),
    has every scan it gives tracked, so a SIGTERM loses none the robot sent before it; any other
    is cut at ``stop``.
    """
    if not speed >= 0:
        raise BadInput("speed", f"must be 0 (as fast as possible) or positive, got {speed}")
    wait = sleep if sleep is not None else stop.wait
    requests = _FleetEvents(agent.robot)
    started = said = clock()
    out = _Outbox(bus, keys, agent, requests)
    handles: list[Handle] = [bus.declare_liveliness(keys.alive(agent.robot))]
    stopped = False
    try:
        if start_after_known:
            _start_after_known(bus, keys, agent)
        handles.append(bus.subscribe(keys.events, requests.on_event))
        if wait_for_listener > 0 and not bus.wait_for_subscribers(keys.localmap(agent.robot), wait_for_listener):
            log.warning("%s: nobody listens to %s yet; going on", agent.robot, keys.localmap(agent.robot))
        stopped = _feed_scans(source, agent, out, speed, stop, clock, wait, said, source_ends_at_stop)
        stopped = stopped or stop.is_set()  # a live source ends when stop is set
        out.publish(agent.finish())
        out.answer_requests()
        bus.flush()
    finally:
        for handle in reversed(handles):
            handle.close()
    counts = agent.counts
    summary = AgentSummary(
        agent.robot, counts.scans, counts.placed, counts.epochs, out.published, out.republished, requests.bad,
        stopped, clock() - started,
    )  # fmt: skip
    log.info("%s", summary.line())
    return summary


class _Outbox:
    """What a run publishes, counted, and the republish requests it answers, on the loop's thread."""

    def __init__(self, bus: Bus, keys: FleetKeys, agent: Agent, requests: _FleetEvents) -> None:
        self.bus = bus
        self.keys = keys
        self.agent = agent
        self.requests = requests
        self.published = 0
        """Messages published (republished ones included)."""
        self.republished = 0
        """Republish requests answered."""

    def publish(self, messages: list[Message]) -> None:
        for message in messages:
            self.bus.publish(message_key(self.keys, message), message.to_msgpack())
        self.published += len(messages)

    def answer_requests(self) -> None:
        if self.requests.take():
            self.republished += 1
            latest = self.agent.republish()
            log.info("%s: republishing %d local maps", self.agent.robot, len(latest))
            self.publish(latest)


def _feed_scans(
    source: Iterable[SourceScan],
    agent: Agent,
    out: _Outbox,
    speed: float,
    stop: threading.Event,
    clock: Callable[[], float],
    wait: Callable[[float], object],
    said: float,
    ends_at_stop: bool,
) -> bool:
    """Step 3 of the module docstring: the scans to the agent at their stamps' pace, what it says
    published, requests answered between scans; whether ``stop`` ended the run before the source
    did. ``said``: when the last status line was logged (the clock's time); ``ends_at_stop``: the
    source ends itself at ``stop`` (:func:`run_agent`)."""
    first: tuple[float, float] | None = None  # (stamp, clock) of the first scan
    for item in source:
        stamp = item.stamp
        if first is None:
            first = (stamp, clock())
        elif speed > 0:
            due = first[1] + (stamp - first[0]) / speed
            while not stop.is_set() and (left := due - clock()) > 0:
                out.answer_requests()
                wait(min(left, POLL))
        out.answer_requests()
        if stop.is_set() and not ends_at_stop:
            return True
        for epoch in out.requests.take_relocalized():
            agent.relocalized(epoch)
        out.publish(agent.add_scan(item.index, stamp, item.scan, item.odometry))
        if clock() - said >= STATUS_SECONDS:
            said = clock()
            _log_status(agent, out.published)
    return False


def _log_status(agent: Agent, published: int) -> None:
    """The periodic line of a running agent."""
    c = agent.counts
    log.info(
        "%s: %d scans, %d placed, %d epochs, %d local maps, %d messages published",
        agent.robot, c.scans, c.placed, c.epochs, c.local_maps, published,
    )  # fmt: skip
