"""``fleetmap merger``: the merger service on the bus."""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.executor_args import add_executor_arguments, executor_from_args
from fleetmap.merger.engine import Merger
from fleetmap.merger.service import MergerService
from fleetmap.ros2_outputs import NODE_NAME, Ros2Outputs
from fleetmap.shared.config import MergeParams
from fleetmap.shared.core.warmup import warm
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io import ros2_wire
from fleetmap.shared.io.outputs import output_file
from fleetmap.shared.io.ros2_node import Ros2Node, ros2_options
from fleetmap.shared.io.startposes import read_start_poses
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import OPEN_FLEET, is_open, zenoh_config
from fleetmap.zenoh_args import add_zenoh_arguments, stop_on_signals, zenoh_options_from_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "merger",
        help="run the merger service",
        description="Subscribe to the submaps of every robot, keep the pose graph, and publish the global "
        "map(s) and every robot's pose in the global frame whenever they change. With --state it keeps its "
        "graph in a file and resumes from it when restarted.",
    )
    p.add_argument("--state", metavar="FILE", help="state file: written after every step, loaded at start")
    p.add_argument(
        "--start-poses",
        metavar="FILE",
        help="robot,x,y,theta lines: robots' laser poses when they start, in one frame (a header line allowed): each "
        "is placed from its first submap, and corrected where its map meets the others'",
    )
    ros2 = p.add_argument_group("ROS 2 outputs (rmw_zenoh)")
    ros2.add_argument(
        "--ros2",
        action="store_true",
        help="also publish the largest map as nav_msgs/OccupancyGrid on /map (transient local), map -> <robot>/odom "
        "on /tf and each robot's pose on /<robot>/fleetmap/pose, over Zenoh as rmw_zenoh does; the session is then a "
        "client of the robots' router unless --mode says otherwise (--connect tcp/HOST:7447)",
    )
    ros2.add_argument("--domain", type=int, default=0, metavar="N", help="ROS_DOMAIN_ID (default 0)")
    add_zenoh_arguments(p)
    add_executor_arguments(p)
    add_config_arguments(p, ["integration", "merge", "tracking"], "live")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    start_poses = read_start_poses(args.start_poses) if args.start_poses else None
    options = zenoh_options_from_args(args)
    if args.ros2:
        options = ros2_options(options)  # a client of the robots' router by default
    if args.state:
        output_file(args.state, "--state")
    if args.ros2:
        ros2_wire.data_key(args.domain, "/map", ros2_wire.OCCUPANCY_GRID)  # checks the domain
    elif args.domain != 0:
        raise BadInput("--domain", "applies to --ros2 only")
    executor = executor_from_args(args)
    warm()  # the compiled loops loaded now, not in the first step (Numba's import alone: 0.3 s)
    try:
        merger = Merger(options.keys, config, executor, start_poses=start_poses)
        if start_poses:
            log.info("start poses of %s from %s", ", ".join(sorted(start_poses)), args.start_poses)
        if args.state and Path(args.state).exists():
            merger.load_state(args.state)
            log.warning("resumed from %s: %d maps, step %d", args.state, len(merger.graph), merger.seq)
        with stop_on_signals() as stop, ZenohBus.open(options) as bus:
            if is_open(zenoh_config(options)):
                log.warning("%s", OPEN_FLEET)
            service = MergerService(bus, merger, state_file=args.state)
            node = Ros2Node(bus.session, NODE_NAME, domain=args.domain) if args.ros2 else None
            ros2 = Ros2Outputs(bus, options.keys, node) if node is not None else None
            if ros2 is not None:
                ros2.start()  # before the service, which asks every robot for its maps at start
            service.start()
            try:
                service.run(stop)
            finally:
                service.close()
                if ros2 is not None and node is not None:
                    ros2.close()
                    node.close()
    finally:
        executor.close()
    s = merger.stats
    limits = {f.name for f in dataclasses.fields(MergeParams)}
    refused = ", ".join(
        f"{n} by --{reason.replace('_', '-')}" if reason in limits else f"{n} ({reason.replace('_', ' ')})"
        for reason, n in sorted(s.refused.items())
    )
    log.warning(
        "merger stopped: %d steps, %d integrations (%d near a prediction), %d submaps; %d malformed messages "
        "dropped, %d naming another robot than their key's%s",
        s.steps,
        s.integrations,
        s.near,
        len(merger.graph),
        s.malformed,
        s.foreign,
        f"; refused {refused}" if refused else "",
    )
    return 0
