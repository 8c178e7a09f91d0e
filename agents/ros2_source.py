"""A live ROS 2 robot as an agent's scan source, over rmw_zenoh: no ROS install, no bridge.

ROS 2 (Jazzy and later) with rmw_zenoh puts every topic on Zenoh (:mod:`fleetmap.shared.io.ros2_wire`),
so the agent's own Zenoh session subscribes to the robot's topics as a ROS 2 node would:

- ``<namespace>/scan``: sensor_msgs/LaserScan, the scans, with the robot's own header stamps;
- ``<namespace>/odom``: nav_msgs/Odometry, the base's odometry, interpolated at each scan's stamp
  (:class:`~fleetmap.shared.io.sources.OdometryTrack`, as for a bag); without it, tf ``odom ->
  base_link`` (or ``base_footprint``) on ``<namespace>/tf``;
- ``<namespace>/tf_static``: the laser's mounting on the base (transient local: an advanced
  subscriber with history gets what the robot published before the agent started).

Subscriptions put ``*`` in the type hash chunk, so any distro's publisher is heard (Humble's has no
hash); the type chunk must be the expected one. The agent declares a node and one subscription
token per topic (``ros2 node list`` / ``ros2 topic info`` see it).

Bad input does not stop the agent: a sample of another type on a topic, a payload that does not
decode, a sample without the rmw_zenoh attachment, a scan with a negative reading or nothing but
NaN, a stamp at or before the previous one on its topic: each is dropped and counted
(:attr:`Ros2LiveSource.dropped`), and logged the first time it happens with the topic named. NaN
readings among good ones are no return (REP 117: an invalid measurement), as in a bag.

A scan waits for the odometry at its stamp (odometry usually comes at a higher rate and a little
later), as tf2's message filter holds a message until its transform comes: until the robot's own
clock says the odometry is late (a later scan stamped :data:`ODOMETRY_WAIT` seconds after it, and
still no reading at its stamp) and no reading has come since the scan did, or the robot has gone
quiet for :data:`QUIET` seconds. Then it goes without, which the tracker handles as for a scan
outside a bag's odometry. The agent's own wall clock does not decide: on a busy machine the
odometry sample can sit behind the scan for longer than the robot took between them, and its
readings still coming, older than the scan, say it is behind, not stopped (a robot played at five
times its pace, on a machine running two other jobs: a scan went without its reading, 0.1 s of the
agent's time behind the scan that came 0.5 s of the robot's after it). And every sample heard is
taken before a scan goes: on a machine running four other jobs the agent found a scan, later
scans and then the scan's odometry all waiting for it, and, taking them one at a time, let the
scan go without it.

The samples wait in zenoh's own FIFO channels, one per topic, which the source drains from the
agent's thread; between turns it waits on ``stop`` itself, never on a queue with a timeout: in
CPython 3.11 and 3.12 a timed ``queue.SimpleQueue.get`` whose deadline passes while it is
interrupted (a signal) or descheduled (a loaded machine) then waits with a negative timeout, which
is forever, until the next item. At the end of a robot's run no item comes: agents flooded on a
machine at load 10-14 sat in that wait, deaf to SIGTERM, until killed (docs/decisions/077). No
Python code runs on zenoh's threads either (no callback per sample, no thread per topic).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
import zenoh.ext
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.logs import OdometryReading
from fleetmap.shared.io.sources import (
    BASE_FRAMES,
    ODOMETRY_FRAMES,
    OdometryTrack,
    SourceScan,
    checked_scan,
    laser_odometry,
    laser_scan,
    planar_pose,
)

log = logging.getLogger(__name__)

POLL = 0.01
"""Longest a sample waits in its channel (s) while the source has nothing to do; how often it looks
at ``stop`` and at scans waiting for odometry."""
CHANNEL_CAPACITY = 4096
"""Samples a topic's channel holds before zenoh waits for the source to take them: 40 s of tf at
100 Hz, a robot's busiest topic (the source takes them all at every turn, a scan's tracking apart)."""
ODOMETRY_WAIT = 0.5
"""How long (s, the robot's clock: later scans' stamps) a scan waits for an odometry reading at or
after its stamp."""
QUIET = 5.0
"""How long (s, wall clock) a scan waits when nothing after it comes (the robot stopped, or has no
odometry and sent one scan)."""
ODOMETRY_KEPT = 400
"""Odometry readings kept to interpolate in (seconds of it at any usual rate)."""
NODE_NAME = "fleetmap_agent"


@dataclass(frozen=True)
class Ros2Topics:
    """Where a robot's topics are: fully qualified names, and the ROS domain."""

    scan: str
    odom: str
    tf: str
    tf_static: str
    domain: int = 0
    namespace: str = ""

    @classmethod
    def of(cls, namespace: str = "", scan: str = "scan", odom: str = "odom", domain: int = 0) -> Ros2Topics:
        """The topics of a robot in ``namespace`` (relative names are under it; tf and tf_static too)."""
        names = [wire.fully_qualified(namespace, t) for t in (scan, odom, "tf", "tf_static")]
        qualified = wire.fully_qualified("", namespace) if namespace.strip("/") else ""
        scan_topic, odom_topic, tf, tf_static = names
        topics = cls(scan_topic, odom_topic, tf, tf_static, domain=domain, namespace=qualified)
        wire.data_key(domain, topics.scan, wire.LASER_SCAN)  # checks the domain
        return topics

    def subscriptions(self) -> list[tuple[str, str, wire.Qos]]:
        """(topic, type, QoS) of every subscription."""
        return [
            (self.scan, wire.LASER_SCAN, wire.SENSOR_DATA),
            (self.odom, wire.ODOMETRY, wire.Qos(depth=10)),
            (self.tf, wire.TF_MESSAGE, wire.TF),
            (self.tf_static, wire.TF_MESSAGE, wire.TF_STATIC),
        ]


def node_name(robot: str) -> str:
    """A ROS node name for the robot's agent (node names take no ``-``)."""
    return f"{NODE_NAME}_{robot.replace('-', '_')}"


class Ros2LiveSource:
    """The scans of a live ROS 2 robot heard on ``session`` until ``stop`` is set (see the module)."""

    has_odometry = True
    """The robot may publish odometry; a scan without any at its stamp goes without."""

    def __init__(
        self,
        session: zenoh.Session,
        topics: Ros2Topics,
        stop: threading.Event,
        robot: str = "robot",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.session = session
        self.topics = topics
        self.stop = stop
        self.robot = robot
        self.clock = clock
        self._odometry_heard = -math.inf
        """When (``clock``) the last odometry reading was heard."""
        self.name = f"ROS 2 {topics.scan} (domain {topics.domain})"
        self.dropped: Counter[tuple[str, str]] = Counter()
        """Samples dropped, by (topic, why)."""
        self.received: Counter[str] = Counter()
        """Samples taken, by topic."""
        self.ready = threading.Event()
        """Set once every subscription and token is declared."""
        self._odometry: deque[OdometryReading] = deque(maxlen=ODOMETRY_KEPT)
        self._tf_odometry: deque[OdometryReading] = deque(maxlen=ODOMETRY_KEPT)
        self._mounting: dict[str, Transform2D] = {}
        self._base: str | None = None
        self._last_stamp: dict[str, float] = {}
        self._pending: deque[tuple[float, SourceScan, Any]] = deque()
        self._index = 0
        self._declared: tuple[list[Any], list[tuple[str, Any]]] | None = None
        """The subscriptions and tokens, and the subscribers to drain, once :meth:`listen` made them."""

    # --- the zenoh side: channels the source drains itself (no Python code on zenoh's threads) ---

    def _declare(self) -> tuple[list[Any], list[tuple[str, Any]]]:
        """The subscriptions and tokens (undeclared at the end), and each topic's subscriber to drain,
        the robot's frames and odometry before its scans."""
        handles: list[Any] = []
        heard: list[tuple[str, Any]] = []
        node = wire.Node(self.topics.domain, str(self.session.zid()), 0, node_name(self.robot), self.topics.namespace)
        for entity, (topic, typename, qos) in enumerate(self.topics.subscriptions(), start=1):
            # any type and any hash: a sample of the wrong type is counted, not unheard
            keyexpr = f"{self.topics.domain}/{topic.strip('/')}/*/*"
            channel: zenoh.handlers.FifoChannel[zenoh.Sample] = zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
            subscriber: Any
            if qos.durability == wire.TRANSIENT_LOCAL:
                subscriber = zenoh.ext.declare_advanced_subscriber(
                    self.session,
                    keyexpr,
                    channel,
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth),
                    subscriber_detection=True,
                )
            else:
                subscriber = self.session.declare_subscriber(keyexpr, channel)
            handles.append(subscriber)
            heard.append((topic, subscriber))
            token = node.endpoint_token(entity, "MS", topic, typename, qos)
            handles.append(self.session.liveliness().declare_token(token))
        handles.append(self.session.liveliness().declare_token(node.token()))
        order = [self.topics.tf_static, self.topics.tf, self.topics.odom, self.topics.scan]
        return handles, sorted(heard, key=lambda h: order.index(h[0]))

    def _take_heard(self, heard: list[tuple[str, Any]]) -> int:
        """Take every sample waiting in the subscribers' channels; how many there were."""
        taken = 0
        for topic, subscriber in heard:
            while (sample := subscriber.try_recv()) is not None:
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                self._take(topic, str(sample.key_expr), sample.payload.to_bytes(), attachment)
                taken += 1
        return taken

    def listen(self) -> None:
        """Subscribe now (iterating does it if not done): samples the robot publishes from here on
        wait in their channels until the source takes them."""
        if self._declared is None:
            self._declared = self._declare()
            self.ready.set()
            log.info("%s: listening on %s", self.robot, ", ".join(t for t, _, _ in self.topics.subscriptions()))

    def __iter__(self) -> Iterator[SourceScan]:
        self.listen()
        assert self._declared is not None
        handles, heard = self._declared
        try:
            while not self.stop.is_set():
                # everything heard is taken before a scan is released: a scan whose odometry came
                # with it or before it (a busy machine) is not taken for one without it
                if not self._take_heard(heard):
                    self.stop.wait(POLL)
                yield from self._released()
            # stopped: what was heard is taken, and every scan held goes (stop releases them all)
            self._take_heard(heard)
            yield from self._released()
        finally:
            self._declared = None
            for handle in reversed(handles):
                handle.undeclare()
            self._say_dropped()

    def feed(self, topic: str, key: str, payload: bytes, attachment: bytes | None) -> list[SourceScan]:
        """Take one sample of ``topic`` heard on ``key`` as the subscription would, without a session;
        the scans it releases (a benchmark or a test steps the source this way)."""
        self._take(topic, key, payload, attachment)
        return list(self._released())

    # --- what the samples say ---

    def _drop(self, topic: str, why: str, detail: str = "") -> None:
        self.dropped[(topic, why)] += 1
        if self.dropped[(topic, why)] == 1:
            log.warning("%s: dropped: %s%s (said once; counted)", topic, why, f" ({detail})" if detail else "")

    def _say_dropped(self) -> None:
        if self.dropped:
            said = ", ".join(f"{n} on {topic}: {why}" for (topic, why), n in sorted(self.dropped.items()))
            log.warning("%s: samples dropped: %s", self.robot, said)

    def _take(self, topic: str, key: str, payload: bytes, attachment: bytes | None) -> None:
        typename = next(t for name, t, _ in self.topics.subscriptions() if name == topic)
        type_chunk = key.rsplit("/", 2)[-2]
        if type_chunk != wire.dds_type_name(typename):
            self._drop(topic, f"not a {typename}", f"a {type_chunk}")
            return
        try:
            wire.Attachment.unpack(attachment, topic)
            message = wire.decode(payload, typename, topic)
        except wire.Ros2WireError as exc:
            self._drop(topic, "no rmw_zenoh attachment" if attachment is None else "undecodable", exc.reason)
            return
        try:
            if topic == self.topics.scan:
                self._on_scan(message)
            elif topic == self.topics.odom:
                self._on_odometry(message)
            else:
                self._on_tf(topic, message)
        except (AttributeError, TypeError, ValueError, OverflowError) as exc:
            self._drop(topic, "unusable", f"{type(exc).__name__}: {exc}"[:200])
            return
        self.received[topic] += 1

    def _newer(self, topic: str, stamp: float) -> bool:
        """Whether ``stamp`` is after the topic's previous one (else the sample is dropped)."""
        last = self._last_stamp.get(topic)
        if last is not None and stamp <= last:
            self._drop(topic, "stamp not after the previous one", f"{stamp:.6f} s after {last:.6f} s")
            return False
        self._last_stamp[topic] = stamp
        return True

    def _on_scan(self, msg: Any) -> None:
        topic = self.topics.scan
        stamp = _stamp(msg.header.stamp)
        ranges = np.asarray(msg.ranges, dtype=np.float64)
        if np.any(ranges < 0):  # -inf is "too close" (REP 117); a negative distance is no reading at all
            self._drop(topic, "negative ranges", f"{int(np.sum(ranges < 0))} of {len(ranges)}")
            return
        if len(ranges) == 0 or np.all(np.isnan(ranges)):
            self._drop(topic, "no reading (every range NaN)")
            return
        if not self._newer(topic, stamp):
            return
        index = self._index
        self._index += 1
        try:
            scan = checked_scan(topic, index, stamp, laser_scan(msg, stamp))
        except BadInput as exc:
            self._drop(topic, "bad scan", exc.reason)
            return
        self._pending.append((self.clock(), scan, str(msg.header.frame_id).lstrip("/")))

    def _on_odometry(self, msg: Any) -> None:
        stamp = _stamp(msg.header.stamp)
        if not self._newer(self.topics.odom, stamp):
            return
        pose = planar_pose(msg.pose.pose.position, msg.pose.pose.orientation)
        if not all(math.isfinite(v) for v in pose):
            self._drop(self.topics.odom, "pose not finite")
            return
        self._base = self._base or str(msg.child_frame_id).lstrip("/")
        self._odometry.append(OdometryReading(len(self._odometry), stamp, pose))
        self._odometry_heard = self.clock()

    def _on_tf(self, topic: str, msg: Any) -> None:
        for t in msg.transforms:
            parent, child = str(t.header.frame_id).lstrip("/"), str(t.child_frame_id).lstrip("/")
            planar = planar_pose(t.transform.translation, t.transform.rotation)
            if topic == self.topics.tf_static:
                self._mounting[f"{parent}>{child}"] = Transform2D(*planar)
            elif parent.rsplit("/", 1)[-1] in ODOMETRY_FRAMES and child.rsplit("/", 1)[-1] in BASE_FRAMES:
                stamp = _stamp(t.header.stamp)
                if self._tf_odometry and stamp <= self._tf_odometry[-1].stamp:
                    continue  # the same transform again (tf is often republished), or older
                self._tf_odometry.append(OdometryReading(len(self._tf_odometry), stamp, planar))
                self._odometry_heard = self.clock()
                if not self._odometry:
                    self._base = child

    # --- scans out, each with the odometry at its stamp ---

    def _track(self, laser_frame: str) -> OdometryTrack | None:
        readings = self._odometry or self._tf_odometry
        if not readings:
            return None
        track = OdometryTrack(list(readings))
        track.mounting = self._mounting.get(f"{self._base}>{laser_frame}") if self._base else None
        return track

    def _released(self) -> Iterator[SourceScan]:
        now = self.clock()
        while self._pending:
            arrived, scan, frame = self._pending[0]
            readings = self._odometry or self._tf_odometry
            caught_up = bool(readings) and readings[-1].stamp >= scan.stamp
            behind = self._odometry_heard > arrived  # readings still coming since the scan: late, not stopped
            waited = self._pending[-1][1].stamp - scan.stamp >= ODOMETRY_WAIT and not behind
            late = waited or now - arrived >= QUIET
            if not caught_up and not late and not self.stop.is_set():
                return
            self._pending.popleft()
            odometry = laser_odometry(self._track(frame), scan.stamp)
            yield SourceScan(scan.index, scan.stamp, scan.scan, odometry)


def _stamp(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9
