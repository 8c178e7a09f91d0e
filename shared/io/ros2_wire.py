"""The rmw_zenoh wire, as ROS 2 (Jazzy and later) puts every topic on Zenoh: pure helpers, no session.

What a ROS 2 node over rmw_zenoh sends and expects (ros2/rmw_zenoh ``docs/design.md``; the facts
and their sources are collected in the project's ROS 2 notes):

- **data key** ``<domain>/<fully qualified name, outer slashes stripped>/<DDS type>/<RIHS01 hash>``,
  e.g. ``0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1...d828``
  (:func:`data_key`); a subscriber puts ``*`` in the hash chunk to take any distro's (Humble's is
  ``TypeHashNotSupported``), a publisher must give the exact hash (:func:`type_hash`, computed by
  ``rosbags`` from the Jazzy type store, REP-2011);
- **payload**: CDR, little endian, with its 4-byte encapsulation header ``00 01 00 00``
  (:func:`encode`, :func:`decode`: ``rosbags``' ``serialize_cdr``/``deserialize_cdr``);
- **attachment** on every sample, 33 bytes: int64 sequence number, int64 source timestamp (ns since
  the epoch), both little endian, one byte 16, then the publisher's 16-byte GID
  (:class:`Attachment`); rmw_zenoh drops a sample without it;
- **liveliness tokens** ``@ros2_lv/...`` for a node (``NN``), a publisher (``MP``) and a
  subscription (``MS``), with the QoS written as rmw_zenoh does, each field left empty where it is
  rmw_zenoh's default (:func:`node_token`, :func:`endpoint_token`, :class:`Qos`): they make an
  endpoint visible to ``ros2 node list`` / ``ros2 topic list``; data flows without them.
"""

from __future__ import annotations

import struct
import sys
from dataclasses import dataclass
from functools import cache
from typing import Any

import xxhash
from fleetmap.shared.errors import BadInput
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore
from rosbags.typesys.store import Typestore

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"

STORE = Stores.ROS2_JAZZY
"""The distro whose message definitions give the type hashes published (Jazzy, Kilted and Rolling
share them for the messages fleetmap uses; Humble puts no hash on the wire and cannot talk to them)."""
ANY_HASH = "*"
"""The hash chunk of a subscription that takes any distro's."""
ENCAPSULATION = b"\x00\x01\x00\x00"
"""CDR little endian, the header every rmw_zenoh payload starts with."""
ATTACHMENT = struct.Struct("<qqB16s")
"""Sequence number, source timestamp (ns), GID length, GID: 33 bytes."""
GID_SIZE = 16
LIVELINESS_PREFIX = "@ros2_lv"


class Ros2WireError(BadInput):
    """A sample that is not what rmw_zenoh sends: a payload that does not decode, a bad attachment."""


@cache
def typestore() -> Typestore:
    return get_typestore(STORE)


def type_hash(typename: str) -> str:
    """The RIHS01 hash of a message type (``RIHS01_`` and 64 hex digits), as rmw_zenoh puts it in keys."""
    try:
        return str(typestore().hash_rihs01(typename))
    except (KeyError, TypesysError) as exc:
        raise BadInput(typename, f"not a message type of ROS 2 {STORE.name}: {exc}") from None


def dds_type_name(typename: str) -> str:
    """``pkg/msg/Name`` as DDS and rmw_zenoh name it: ``pkg::msg::dds_::Name_``."""
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        raise BadInput(typename, "not a ROS 2 type name (package/msg/Name)")
    package, kind, name = parts
    return f"{package}::{kind}::dds_::{name}_"


def fully_qualified(namespace: str, topic: str) -> str:
    """A topic's fully qualified name: ``topic`` if absolute, else under ``namespace`` (``/robot1`` +
    ``scan`` -> ``/robot1/scan``); an empty namespace is the root."""
    name = topic if topic.startswith("/") else "/".join(p for p in (namespace.strip("/"), topic) if p)
    name = "/" + name.strip("/")
    if name == "/" or "//" in name:
        raise BadInput(f"topic {topic!r}", f"is not a valid ROS 2 topic name (namespace {namespace!r})")
    return name


def data_key(domain: int, name: str, typename: str, hash_chunk: str | None = None) -> str:
    """The key expression rmw_zenoh publishes topic ``name`` of ``typename`` on in ``domain``; with
    ``hash_chunk`` (:data:`ANY_HASH` to subscribe to any distro's) instead of the type's own hash."""
    if not 0 <= domain <= 232:  # ROS 2's domain ids (REP-2003's DDS port arithmetic caps it at 232)
        raise BadInput("--domain", f"must be a ROS domain id, 0 to 232, got {domain}")
    chunk = type_hash(typename) if hash_chunk is None else hash_chunk
    return f"{domain}/{name.strip('/')}/{dds_type_name(typename)}/{chunk}"


def encode(message: Any, typename: str) -> bytes:
    """The CDR payload of ``message`` (a ``rosbags`` message object), header included."""
    return bytes(typestore().serialize_cdr(message, typename, little_endian=True))


def decode(payload: bytes, typename: str, where: str = "payload") -> Any:
    """The message in a CDR payload; :class:`Ros2WireError` naming ``where`` if it does not decode."""
    if len(payload) < len(ENCAPSULATION) + 1 or payload[0] != 0 or payload[1] not in (0, 1):
        raise Ros2WireError(where, f"not a CDR payload ({len(payload)} bytes starting {payload[:4].hex()})")
    try:
        return typestore().deserialize_cdr(payload, typename)
    except (SerdeError, TypesysError, struct.error, ValueError, KeyError, IndexError, TypeError) as exc:
        raise Ros2WireError(where, f"not a {typename} ({type(exc).__name__}: {exc})"[:300]) from None


@dataclass(frozen=True)
class Attachment:
    """The rmw_zenoh attachment of a sample."""

    sequence: int
    """The publisher's count of its samples, from 1."""
    stamp_ns: int
    """When the sample was published (ns since the UNIX epoch)."""
    gid: bytes
    """The publisher's 16-byte id."""

    def pack(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a publisher GID is {GID_SIZE} bytes, got {len(self.gid)}")
        return ATTACHMENT.pack(self.sequence, self.stamp_ns, GID_SIZE, self.gid)

    @classmethod
    def unpack(cls, data: bytes | None, where: str = "attachment") -> Attachment:
        """The attachment in ``data``; :class:`Ros2WireError` if there is none or it is not 33 bytes
        with a 16-byte GID (what rmw_zenoh's subscriber drops too)."""
        if data is None:
            raise Ros2WireError(where, "no rmw_zenoh attachment (sequence number, timestamp, GID)")
        if len(data) != ATTACHMENT.size:
            raise Ros2WireError(where, f"an rmw_zenoh attachment is {ATTACHMENT.size} bytes, got {len(data)}")
        sequence, stamp_ns, size, gid = ATTACHMENT.unpack(data)
        if size != GID_SIZE:
            raise Ros2WireError(where, f"attachment's GID length is {size}, not {GID_SIZE}")
        return cls(sequence, stamp_ns, gid)


def gid_of(token: str) -> bytes:
    """The 16-byte GID of the endpoint whose liveliness token is ``token``, as rmw_zenoh makes it:
    XXH3-128 of the token's exact bytes, its low and then its high 64 bits copied in the machine's
    byte order (rmw_zenoh ``liveliness_utils.cpp`` with ``simplified_xxhash3.cpp``, a portable copy
    of xxHash's XXH3-128: a ``memcpy`` of ``low64``, then ``high64``).
    A ROS 2 node that matches a sample's GID to the publisher it discovered (message info,
    ``ros2 topic info -v``) then finds fleetmap's."""
    digest = xxhash.xxh3_128(token.encode()).intdigest()
    low, high = digest & 0xFFFF_FFFF_FFFF_FFFF, digest >> 64
    return low.to_bytes(8, sys.byteorder) + high.to_bytes(8, sys.byteorder)


RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
"""rmw's QoS enum values (rmw/types.h), as the liveliness tokens write them."""


@dataclass(frozen=True)
class Qos:
    """The QoS an endpoint declares; the defaults are rmw_zenoh's (``qos.cpp``). Deadline, lifespan
    and liveliness are rmw_zenoh's defaults (it does not implement the first two)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42

    def keyexpr(self) -> str:
        """``rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:liv,lease_s,lease_ns``, each field empty where it
        is the default (rmw_zenoh ``liveliness_utils.cpp`` ``qos_to_keyexpr``)."""
        default = Qos()

        def field(value: int, base: int) -> str:
            return "" if value == base else str(value)

        return (
            f"{field(self.reliability, default.reliability)}:{field(self.durability, default.durability)}:"
            f"{field(self.history, default.history)},{field(self.depth, default.depth)}:,:,:,,"
        )


SENSOR_DATA = Qos(reliability=BEST_EFFORT, depth=5)
"""rclcpp's SensorDataQoS: what laser drivers publish scans with."""
MAP = Qos(durability=TRANSIENT_LOCAL, depth=1)
"""REP-2003's map QoS: reliable, transient local, the last map."""
TF = Qos(depth=100)
"""tf2_ros's DynamicBroadcasterQoS on /tf."""
TF_STATIC = Qos(durability=TRANSIENT_LOCAL, depth=1)
"""tf2_ros's StaticBroadcasterQoS on /tf_static."""


def mangle(name: str) -> str:
    """A name as a single key chunk: ``/`` -> ``%``; empty -> ``%``."""
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as the graph sees it: ``session_id`` is the Zenoh session's id (its hex zid)."""

    domain: int
    session_id: str
    node_id: int
    name: str
    namespace: str = ""
    enclave: str = ""

    def token(self) -> str:
        """The node's ``NN`` liveliness token."""
        return (
            f"{LIVELINESS_PREFIX}/{self.domain}/{self.session_id}/{self.node_id}/{self.node_id}/NN/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}"
        )

    def endpoint_token(
        self, entity_id: int, kind: str, name: str, typename: str, qos: Qos, hash_chunk: str = ""
    ) -> str:
        """The ``MP`` (publisher) or ``MS`` (subscription) token of topic ``name`` (fully qualified)."""
        if kind not in ("MP", "MS"):
            raise ValueError(f"an endpoint token is MP or MS, not {kind!r}")
        return (
            f"{LIVELINESS_PREFIX}/{self.domain}/{self.session_id}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}/{mangle(name)}/"
            f"{dds_type_name(typename)}/{hash_chunk or type_hash(typename)}/{qos.keyexpr()}"
        )
