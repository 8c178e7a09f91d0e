"""A ROS 2 node's publishers on a Zenoh session, as rmw_zenoh makes them (the wire: :mod:`.ros2_wire`).

:class:`Ros2Node` holds the node's ``NN`` liveliness token and makes :class:`Ros2Publisher` s, each
with its ``MP`` token, its rmw_zenoh key and a 33-byte attachment on every sample. A transient
local topic (``/map``, ``/tf_static``) is published as rmw_zenoh does, through Zenoh's advanced
publisher: a cache of the last ``depth`` samples that a subscriber starting later queries,
publisher detection, and (reliable) a sporadic heartbeat so a subscriber can see it missed the last
sample. A plain put would reach only the subscribers already there.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zenoh
import zenoh.ext
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.zenoh_config import ZenohOptions

log = logging.getLogger(__name__)

HEARTBEAT = 0.5
"""Seconds between the sporadic heartbeats of a reliable transient local publisher (rmw_zenoh's)."""


def ros2_options(options: ZenohOptions) -> ZenohOptions:
    """A session that meets ROS 2 nodes: a client unless ``--mode`` or ``--zenoh-config`` says
    otherwise. rmw_zenoh's router does not forward between peers (``peers_failover_brokering:
    false``; ROS nodes are peers that talk directly), but always to and from its clients."""
    if options.mode is None and options.config_file is None:
        return options.with_mode("client")
    return options


class Ros2Publisher:
    """One topic of a :class:`Ros2Node`: ``publish(message)`` puts it with its attachment."""

    def __init__(self, node: Ros2Node, entity_id: int, topic: str, typename: str, qos: wire.Qos) -> None:
        self.topic = topic
        self.typename = typename
        self.key = wire.data_key(node.info.domain, topic, typename)
        token = node.info.endpoint_token(entity_id, "MP", topic, typename, qos)
        self.gid = wire.gid_of(token)
        self._sequence = 0
        self._lock = threading.Lock()
        session = node.session
        congestion = zenoh.CongestionControl.BLOCK if qos.reliability == wire.RELIABLE else zenoh.CongestionControl.DROP
        reliability = zenoh.Reliability.RELIABLE if qos.reliability == wire.RELIABLE else zenoh.Reliability.BEST_EFFORT
        self._publisher: Any
        reliable = qos.reliability == wire.RELIABLE
        heartbeat = zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT) if reliable else None
        if qos.durability == wire.TRANSIENT_LOCAL:
            self._publisher = zenoh.ext.declare_advanced_publisher(
                session,
                self.key,
                congestion_control=congestion,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(max_samples=qos.depth),
                publisher_detection=True,
                sample_miss_detection=heartbeat,
            )
        else:
            self._publisher = session.declare_publisher(
                self.key, congestion_control=congestion, reliability=reliability
            )
        # the token after the publisher: whoever sees it (the SDK's late subscriber) finds the cache there
        self._token = session.liveliness().declare_token(token)

    def publish(self, message: Any) -> None:
        """Put ``message`` (a ``rosbags`` message object of the topic's type)."""
        self.publish_cdr(wire.encode(message, self.typename))

    def publish_cdr(self, payload: bytes) -> None:
        """Put a CDR payload as it is (a bag's own bytes)."""
        with self._lock:
            self._sequence += 1  # rmw_zenoh's publishers count from 1
            attachment = wire.Attachment(self._sequence, time.time_ns(), self.gid).pack()
        self._publisher.put(payload, attachment=attachment)

    @property
    def published(self) -> int:
        return self._sequence

    def close(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


class Ros2Node:
    """A ROS 2 node named ``name`` in ``namespace`` on ``session`` (domain ``domain``); close when done."""

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "", domain: int = 0) -> None:
        self.session = session
        self.info = wire.Node(domain, str(session.zid()), 0, name, namespace)
        self._token = session.liveliness().declare_token(self.info.token())
        self._publishers: list[Ros2Publisher] = []

    def publisher(self, topic: str, typename: str, qos: wire.Qos) -> Ros2Publisher:
        """A publisher of ``typename`` on topic ``topic`` (fully qualified)."""
        publisher = Ros2Publisher(self, len(self._publishers) + 1, topic, typename, qos)
        self._publishers.append(publisher)
        return publisher

    def close(self) -> None:
        for publisher in self._publishers:
            publisher.close()
        self._token.undeclare()

    def __enter__(self) -> Ros2Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
