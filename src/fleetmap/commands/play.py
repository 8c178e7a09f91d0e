"""``fleetmap play BAG --ros2``: a bag's robot on rmw_zenoh topics, as ``ros2 bag play`` would put it.

The bag's sensor_msgs/LaserScan, nav_msgs/Odometry and tf2_msgs/TFMessage topics are published at
the pace of their log times (``--speed``), each on its rmw_zenoh key under ``--namespace``
(``/scan`` -> ``/<ns>/scan``; ``/tf`` and ``/tf_static`` too), with the rmw_zenoh attachment and a
publisher token each, as one node: a robot for ``fleetmap agent --ros2`` (or any ROS 2 node) with
no robot. ``/tf_static`` is transient local (a subscriber that starts later still gets the
mounting): every static transform of the bag so far is published together, as tf2's static
broadcaster does, so its cache of one holds them all.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from fleetmap.shared.errors import BadInput
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.ros2_node import Ros2Node, Ros2Publisher, ros2_options
from fleetmap.shared.io.sources import LASER_SCAN_SCHEMAS, ODOMETRY_SCHEMAS, TF_SCHEMAS, Ros2BagSource
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.zenoh_args import add_zenoh_arguments, stop_on_signals, zenoh_options_from_args

log = logging.getLogger(__name__)

NODE_NAME = "fleetmap_play"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "play",
        help="play a ROS bag's laser scans, odometry and tf on ROS 2 topics (rmw_zenoh), as ros2 bag play would",
        description="Publish a bag's sensor_msgs/LaserScan, nav_msgs/Odometry and tf2_msgs/TFMessage (/tf, "
        "/tf_static) topics over Zenoh exactly as rmw_zenoh does (keys with the Jazzy type hashes, CDR, the "
        "attachment, liveliness tokens), at the pace of the bag's log times: a robot for `fleetmap agent --ros2` "
        "or any ROS 2 node, without a robot or a ROS install. /tf_static is transient local. The session is a "
        "client of the router (rmw_zenohd; --connect tcp/HOST:7447) unless --mode says otherwise.",
    )
    p.add_argument("bag", metavar="BAG", help="a rosbag2 directory, its .mcap or .db3 file, or a ROS 1 .bag")
    p.add_argument("--ros2", action="store_true", required=True, help="publish on ROS 2 topics over rmw_zenoh")
    p.add_argument("--namespace", default="", metavar="NS", help="put the bag's topics under NS (default: as they are)")
    p.add_argument(
        "--speed", type=float, default=1.0, metavar="X", help="X times the bag's pace; 0: as fast as possible"
    )
    p.add_argument("--domain", type=int, default=0, metavar="N", help="ROS_DOMAIN_ID (default 0)")
    add_zenoh_arguments(p, fleet=False)
    p.set_defaults(func=run)


@dataclass(frozen=True)
class PlaySummary:
    published: dict[str, int]
    """Messages published, by topic (as published, under the namespace)."""
    stopped: bool
    seconds: float

    def line(self) -> str:
        topics = ", ".join(f"{n} on {t}" for t, n in sorted(self.published.items())) or "nothing"
        return f"play {'stopped' if self.stopped else 'done'}: {topics}, {self.seconds:.1f} s"


def wire_type(bag_type: str) -> str | None:
    """The ROS 2 type a bag's topic is published as (None: not played)."""
    for schemas, typename in (
        (LASER_SCAN_SCHEMAS, wire.LASER_SCAN),
        (ODOMETRY_SCHEMAS, wire.ODOMETRY),
        (TF_SCHEMAS, wire.TF_MESSAGE),
    ):
        if bag_type in schemas:
            return typename
    return None


def play_bag(
    bag: Ros2BagSource,
    node: Ros2Node,
    namespace: str,
    speed: float,
    stop: threading.Event,
    clock: Callable[[], float] = time.monotonic,
) -> PlaySummary:
    """Publish ``bag``'s played topics on ``node`` at ``speed`` times their log times' pace."""
    if not speed >= 0 or math.isinf(speed):
        raise BadInput("--speed", f"must be 0 (as fast as possible) or a positive number, got {speed}")
    played = {t: ty for t, name in bag.topic_types.items() if (ty := wire_type(name)) is not None}
    publishers: dict[str, Ros2Publisher] = {}
    for topic, typename in sorted(played.items()):
        name = wire.fully_qualified(namespace, topic.lstrip("/"))
        qos = wire.TF_STATIC if topic.endswith("tf_static") else wire.TF if typename == wire.TF_MESSAGE else wire.Qos()
        publishers[topic] = node.publisher(name, typename, qos)
    static: dict[str, Any] = {}  # child frame -> its transform: tf_static carries them all at once
    started = clock()
    first: tuple[int, float] | None = None
    stopped = False
    for topic, log_time, message in bag.messages(sorted(played)):
        if first is None:
            first = (log_time, clock())
        elif speed > 0:
            due = first[1] + (log_time - first[0]) * 1e-9 / speed
            if (left := due - clock()) > 0 and stop.wait(left):
                stopped = True
                break
        if stop.is_set():
            stopped = True
            break
        if topic.endswith("tf_static"):
            static.update({str(t.child_frame_id): t for t in message.transforms})
            message = wire.typestore().types[wire.TF_MESSAGE](list(static.values()))
        publishers[topic].publish(message)
    published = {p.topic: p.published for p in publishers.values()}
    return PlaySummary(published, stopped, clock() - started)


def run(args: argparse.Namespace) -> int:
    bag = Ros2BagSource(args.bag)  # a bag without a LaserScan topic is refused here
    wire.data_key(args.domain, "/scan", wire.LASER_SCAN)  # checks the domain
    options = ros2_options(zenoh_options_from_args(args))  # a client of the router by default
    with stop_on_signals() as stop, ZenohBus.open(options) as bus:
        namespace = wire.fully_qualified("", args.namespace) if args.namespace.strip("/") else ""
        with Ros2Node(bus.session, NODE_NAME, namespace, args.domain) as node:
            print(f"play {args.bag} on ROS 2 domain {args.domain} (Ctrl-C or SIGTERM to stop)", file=sys.stderr)
            summary = play_bag(bag, node, args.namespace, args.speed, stop)
            bus.flush()  # what is still queued reaches the router before the session closes
    print(summary.line())
    return 0
