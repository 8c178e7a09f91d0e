"""``fleetmap agent``: one robot on the bus, from a simulated robot, a CARMEN log, a ROS 2 bag or a
live ROS 2 robot on rmw_zenoh."""

from __future__ import annotations

import argparse
import logging
import math
import sys

from fleetmap.agents.agent import LOST_SCANS, Agent
from fleetmap.agents.process import run_agent
from fleetmap.agents.ros2_source import Ros2LiveSource, Ros2Topics
from fleetmap.commands import add_no_return_reading
from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.scenarios.stream import ScenarioSource
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.warmup import warm
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import check_name
from fleetmap.shared.io.ros2_node import ros2_options
from fleetmap.shared.io.sources import CarmenSource, Ros2BagSource, ScanSource
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.zenoh_args import add_zenoh_arguments, stop_on_signals, zenoh_options_from_args

log = logging.getLogger(__name__)

WAIT_FOR_LISTENER = 5.0
"""Seconds the first scan waits for a merger or recorder to listen (they may be starting too)."""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "agent",
        help="run one robot: extract segments, track its scans into submaps, publish scans and submaps",
        description="One robot agent on the fleet's bus. For each scan of its source it extracts segments "
        "(paper III-D), predicts the scan's pose from odometry (--odometry auto|on|off) or constant velocity, "
        "registers it on the active submap and checks the fit; a scan that does not fit is re-acquired by the "
        "paper's pose-free integration, and after --kidnap-after scans in a row that fit nowhere the robot "
        "starts a new epoch (it lost its place) and says so on the events key. It publishes every scan, and "
        "each submap every --publish-every inserted scans and once more when finished (after every inserted "
        "scan for the first --lost-scans of a later epoch). --front-end pivot runs the paper's pivot method "
        "instead (IV-C, Algorithm 6). It holds the liveliness token fleet/<fleet>/alive/<robot> while it runs, "
        "republishes its latest submaps when a merger asks, and stops cleanly on SIGINT or SIGTERM (final "
        "submaps, then leave).",
    )
    p.add_argument("--robot", required=True, metavar="ID", help="the robot id (^[a-z][a-z0-9_-]{0,31}$)")
    source = p.add_argument_group("scan source (exactly one)")
    given = source.add_mutually_exclusive_group(required=True)
    given.add_argument("--scenario", metavar="NAME_OR_FILE", help="a bundled scenario name or a scenario .toml")
    given.add_argument("--carmen", metavar="FILE", help="a CARMEN log (plain or .gz)")
    given.add_argument(
        "--ros2-bag",
        metavar="BAG",
        help="a ROS bag with sensor_msgs/LaserScan: a rosbag2 directory, its .mcap or .db3 file, or a ROS 1 .bag",
    )
    given.add_argument(
        "--ros2",
        action="store_true",
        help="a live ROS 2 robot over rmw_zenoh: its LaserScan, Odometry (or tf odom -> base_link) and /tf_static, "
        "heard on this agent's zenoh session, a client of the robot's router unless --mode says otherwise "
        "(--connect tcp/ROBOT:7447); runs until stopped",
    )
    source.add_argument("--start", type=int, default=0, metavar="N", help="CARMEN: first scan (default 0)")
    source.add_argument("--stop", type=int, default=None, metavar="M", help="CARMEN: stop before scan M (default: end)")
    source.add_argument("--step", type=int, default=1, metavar="K", help="CARMEN: every K-th scan (default 1)")
    add_no_return_reading(source)
    source.add_argument(
        "--topic",
        default=None,
        help="ROS bag: the sensor_msgs/LaserScan topic (default: the bag's one LaserScan topic, /scan if several)",
    )
    source.add_argument(
        "--odometry-topic",
        default=None,
        metavar="TOPIC",
        help="ROS 2 bag: the nav_msgs/Odometry topic (default: the first one, else tf odom -> base_link)",
    )
    ros2 = p.add_argument_group("live ROS 2 robot (--ros2)")
    ros2.add_argument("--namespace", default="", metavar="NS", help="the robot's ROS namespace (default: none)")
    ros2.add_argument("--scan-topic", default="scan", metavar="TOPIC", help="sensor_msgs/LaserScan (default scan)")
    ros2.add_argument("--odom-topic", default="odom", metavar="TOPIC", help="nav_msgs/Odometry (default odom)")
    ros2.add_argument("--domain", type=int, default=0, metavar="N", help="ROS_DOMAIN_ID (default 0)")
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        metavar="X",
        help="play the scans at X times their stamps' pace; 0: as fast as possible (default 1)",
    )
    p.add_argument(
        "--lost-scans",
        type=int,
        default=LOST_SCANS,
        metavar="N",
        help="in an epoch after the first (the robot is lost until the merger places it), publish the local "
        f"map after each of its first N placed scans (default {LOST_SCANS})",
    )
    p.add_argument(
        "--wait-for-listener",
        type=float,
        default=WAIT_FOR_LISTENER,
        metavar="S",
        help=f"wait up to S seconds for a subscriber before the first scan (default {WAIT_FOR_LISTENER:g})",
    )
    add_zenoh_arguments(p)
    add_config_arguments(p, ["extraction", "integration", "tracking"], "live")
    p.set_defaults(func=run)


def make_source(args: argparse.Namespace) -> ScanSource:
    """The source the flags name (files are checked here, before the agent goes on the bus)."""
    check_source_flags(args)
    if args.scenario is not None:
        return ScenarioSource(args.scenario, args.robot)
    if args.carmen is not None:
        return CarmenSource(args.carmen, args.start, args.stop, args.step, args.no_return_reading)
    return Ros2BagSource(args.ros2_bag, args.topic, args.odometry_topic)


def check_source_flags(args: argparse.Namespace) -> None:
    """Refuse the flags of a source that is not the one given."""
    if args.carmen is None and (args.start, args.stop, args.step, args.no_return_reading) != (0, None, 1, math.inf):
        raise BadInput("--start/--stop/--step/--no-return-reading", "apply to --carmen only")
    if args.ros2_bag is None and (args.topic is not None or args.odometry_topic is not None):
        raise BadInput("--topic/--odometry-topic", "apply to --ros2-bag only")
    if not args.ros2 and (args.namespace, args.scan_topic, args.odom_topic, args.domain) != ("", "scan", "odom", 0):
        raise BadInput("--namespace/--scan-topic/--odom-topic/--domain", "apply to --ros2 only")


def run(args: argparse.Namespace) -> int:
    robot = check_name(args.robot, "--robot")
    if not args.speed >= 0 or math.isinf(args.speed):
        raise BadInput("--speed", f"must be 0 (as fast as possible) or a positive number, got {args.speed}")
    config = config_from_args(args)
    if args.ros2:
        return run_ros2(args, robot, config)
    source = make_source(args)
    if config.tracking.odometry == "on" and not source.has_odometry:
        raise BadInput(source.name, "has no odometry (--odometry on needs it; auto uses it where there is some)")
    agent = Agent(robot, config, odometry=source.has_odometry, lost_scans=args.lost_scans)
    options = zenoh_options_from_args(args)
    warm()  # the compiled loops loaded before the first scan, not while it waits
    with stop_on_signals() as stop, ZenohBus.open(options) as bus:
        print(f"agent {robot}: {source.name} on {options.keys.prefix} (Ctrl-C or SIGTERM to stop)", file=sys.stderr)
        summary = run_agent(
            source, agent, bus, options.keys, args.speed, stop, wait_for_listener=args.wait_for_listener
        )
    print(summary.line())
    return 0


def run_ros2(args: argparse.Namespace, robot: str, config: FleetmapConfig) -> int:
    """The agent of a live ROS 2 robot: its scans as they come, until SIGINT or SIGTERM."""
    check_source_flags(args)
    if args.speed != 1.0:
        raise BadInput("--speed", "does not apply to --ros2: a live robot's scans come at its own pace")
    topics = Ros2Topics.of(args.namespace, args.scan_topic, args.odom_topic, args.domain)
    agent = Agent(robot, config, odometry=Ros2LiveSource.has_odometry, lost_scans=args.lost_scans)
    options = ros2_options(zenoh_options_from_args(args))  # a client of the robot's router by default
    warm()  # the compiled loops loaded before the first scan, not while it waits
    with stop_on_signals() as stop, ZenohBus.open(options) as bus:
        source = Ros2LiveSource(bus.session, topics, stop, robot)
        print(f"agent {robot}: {source.name} on {options.keys.prefix} (Ctrl-C or SIGTERM to stop)", file=sys.stderr)
        # live scans come at the robot's pace: no pacing by their stamps
        # the source ends at stop, giving back the scans it holds: each is tracked
        summary = run_agent(
            source,
            agent,
            bus,
            options.keys,
            0.0,
            stop,
            wait_for_listener=args.wait_for_listener,
            source_ends_at_stop=True,
        )
    print(summary.line())
    dropped = sum(source.dropped.values())
    print(f"agent {robot}: {sum(source.received.values())} ROS 2 samples taken, {dropped} dropped")
    return 0
