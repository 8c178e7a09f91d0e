"""Zenoh key expressions of a fleet, and the names that go into them.

Everything a fleet says lives under one prefix, ``fleet/<fleet>`` (``docs/formats.md``, bus keys)::

    fleet/<fleet>/robots/<robot>/scan        Scan
    fleet/<fleet>/robots/<robot>/localmap    LocalMap
    fleet/<fleet>/robots/<robot>/pose        RobotPose
    fleet/<fleet>/robots/<robot>/events      FleetEvent said by the robot (a new epoch)
    fleet/<fleet>/merger/globalmap           GlobalMap
    fleet/<fleet>/merger/edges               MergeEdge
    fleet/<fleet>/merger/steps               MergerStep (the versions the merger took in, and the pairs it integrated)
    fleet/<fleet>/merger/state               queryable: the current global state
    fleet/<fleet>/events                     FleetEvent said by the merger (join, leave, requests)
    fleet/<fleet>/recorder/stats             queryable: what the recorder has recorded so far
    fleet/<fleet>/recorder/maps              queryable: the newest version of every submap recorded
    fleet/<fleet>/alive/<robot>              liveliness token: the robot is up
    fleet/<fleet>/services/<service>         liveliness token: a service (merger, recorder) is up

Robot ids and fleet names have one format, ``^[a-z][a-z0-9_-]{0,31}$``: short, lower case, safe
in a key expression (no ``/``, ``*``, ``$`` or ``?``) and in a file name. A robot writes only
under its own ``robots/<robot>/`` and ``alive/<robot>`` keys, so a router's access control can hold
it to them (:mod:`fleetmap.shared.io.security`). A robot's epoch is named by
its *map key* ``<robot>/<epoch>``, and each submap of it by ``<robot>/<epoch>/<submap>``, the node
name of the merger's pose graph.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal, get_args

from fleetmap.shared.errors import BadInput

NAME_PATTERN = re.compile(r"[a-z][a-z0-9_-]{0,31}")
"""Robot ids, fleet names and service names (matched whole)."""

MAP_KEY_PATTERN = re.compile(r"([a-z][a-z0-9_-]{0,31})/(0|[1-9][0-9]{0,17})(?:/(0|[1-9][0-9]{0,17}))?")
"""``<robot>/<epoch>``: a robot's local map of one epoch (the frame of its first scan), or
``<robot>/<epoch>/<submap>``: one submap of it; the numbers are non-negative integers without
leading zeros."""

DEFAULT_FLEET = "default"

KeyKind = Literal[
    "scan",
    "localmap",
    "pose",
    "robot_events",
    "globalmap",
    "edges",
    "steps",
    "state",
    "events",
    "alive",
    "services",
    "recorder_stats",
    "recorder_maps",
]
KEY_KINDS: tuple[str, ...] = get_args(KeyKind)
ROBOT_LEAVES: dict[str, KeyKind] = {"scan": "scan", "localmap": "localmap", "pose": "pose", "events": "robot_events"}
"""The last part of a robot's key ``fleet/<fleet>/robots/<robot>/<leaf>``, and the kind it names."""
ROBOT_KINDS: tuple[KeyKind, ...] = tuple(ROBOT_LEAVES.values())
"""Kinds whose key names a robot; a message on such a key must be that robot's."""


def check_name(value: object, what: str) -> str:
    """``value`` if it is a valid robot id / fleet name, else BadInput naming ``what``."""
    if not isinstance(value, str):
        raise BadInput(what, f"expected a string, got {type(value).__name__}")
    if NAME_PATTERN.fullmatch(value) is None:
        raise BadInput(what, f"{value[:64]!r} is not a valid name (^[a-z][a-z0-9_-]{{0,31}}$)")
    return value


def map_key(robot: str, epoch: int) -> str:
    """The name of a robot's local map of one epoch: ``<robot>/<epoch>``."""
    check_name(robot, "robot")
    if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
        raise BadInput("epoch", f"expected a non-negative integer, got {epoch!r}")
    return f"{robot}/{epoch}"


def parse_map_key(key: str) -> tuple[str, int]:
    """``(robot, epoch)`` of a map key ``<robot>/<epoch>`` or ``<robot>/<epoch>/<submap>``."""
    robot, epoch, _ = parse_submap_key(key)
    return robot, epoch


def submap_key(robot: str, epoch: int, submap: int) -> str:
    """The name of one submap of a robot's epoch: ``<robot>/<epoch>/<submap>``."""
    if isinstance(submap, bool) or not isinstance(submap, int) or submap < 0:
        raise BadInput("submap", f"expected a non-negative integer, got {submap!r}")
    return f"{map_key(robot, epoch)}/{submap}"


def parse_submap_key(key: str) -> tuple[str, int, int | None]:
    """``(robot, epoch, submap)`` of a map key; submap None for a whole epoch's ``<robot>/<epoch>``."""
    match = MAP_KEY_PATTERN.fullmatch(key) if isinstance(key, str) else None
    if match is None:
        raise BadInput("map key", f"{str(key)[:64]!r} is not <robot>/<epoch> or <robot>/<epoch>/<submap>")
    submap = match.group(3)
    return match.group(1), int(match.group(2)), None if submap is None else int(submap)


@dataclass(frozen=True)
class ParsedKey:
    """What a key of the fleet is: its kind and, for robot and presence keys, the name in it."""

    kind: KeyKind
    robot: str | None = None
    """The robot of a robots/<robot>/... or alive/<robot> key; the service of a services/<name> key."""


@dataclass(frozen=True)
class FleetKeys:
    """The key expressions of one fleet."""

    fleet: str = DEFAULT_FLEET

    def __post_init__(self) -> None:
        check_name(self.fleet, "fleet")

    @property
    def prefix(self) -> str:
        return f"fleet/{self.fleet}"

    @property
    def everything(self) -> str:
        """Every key of the fleet (what the recorder subscribes to)."""
        return f"{self.prefix}/**"

    def scan(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_name(robot, 'robot')}/scan"

    def localmap(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_name(robot, 'robot')}/localmap"

    def pose(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_name(robot, 'robot')}/pose"

    def robot_events(self, robot: str) -> str:
        """Where a robot says things about itself (a new epoch): its own key, not the fleet's."""
        return f"{self.prefix}/robots/{check_name(robot, 'robot')}/events"

    @property
    def all_robot_events(self) -> str:
        return f"{self.prefix}/robots/*/events"

    @property
    def all_scans(self) -> str:
        return f"{self.prefix}/robots/*/scan"

    @property
    def all_localmaps(self) -> str:
        return f"{self.prefix}/robots/*/localmap"

    @property
    def all_poses(self) -> str:
        return f"{self.prefix}/robots/*/pose"

    @property
    def globalmap(self) -> str:
        return f"{self.prefix}/merger/globalmap"

    @property
    def edges(self) -> str:
        return f"{self.prefix}/merger/edges"

    @property
    def steps(self) -> str:
        """MergerStep: the local map versions the merger took in, in its order, and how many pairs it
        integrated (what replay follows)."""
        return f"{self.prefix}/merger/steps"

    @property
    def state(self) -> str:
        """The merger's queryable: a query returns the current global state."""
        return f"{self.prefix}/merger/state"

    @property
    def events(self) -> str:
        """The merger's events (join, leave, relocalized, requests to the robots); a recording may
        hold robots' own events here too."""
        return f"{self.prefix}/events"

    @property
    def recorder_stats(self) -> str:
        """The recorder's queryable: messages recorded so far, per topic."""
        return f"{self.prefix}/recorder/stats"

    @property
    def recorder_maps(self) -> str:
        """The recorder's queryable: the newest version of every submap it recorded, one reply each
        (what a restarted merger recalls of robots that finished while it was down)."""
        return f"{self.prefix}/recorder/maps"

    def alive(self, robot: str) -> str:
        """The liveliness token a robot holds while it is up."""
        return f"{self.prefix}/alive/{check_name(robot, 'robot')}"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/alive/*"

    def service(self, name: str) -> str:
        """The liveliness token a service (``merger``, ``recorder``) holds while it is up."""
        return f"{self.prefix}/services/{check_name(name, 'service')}"

    @property
    def all_services(self) -> str:
        return f"{self.prefix}/services/*"

    def parse(self, key: str) -> ParsedKey:
        """The kind (and robot) of a concrete key of this fleet; BadInput for any other key."""
        head = self.prefix + "/"
        if not isinstance(key, str) or not key.startswith(head):
            raise BadInput("key", f"{str(key)[:128]!r} is not under {head}")
        parts = key[len(head) :].split("/")
        match parts:
            case ["robots", robot, leaf] if leaf in ROBOT_LEAVES and NAME_PATTERN.fullmatch(robot):
                return ParsedKey(ROBOT_LEAVES[leaf], robot)
            case ["merger", "globalmap"]:
                return ParsedKey("globalmap")
            case ["merger", "edges"]:
                return ParsedKey("edges")
            case ["merger", "steps"]:
                return ParsedKey("steps")
            case ["merger", "state"]:
                return ParsedKey("state")
            case ["events"]:
                return ParsedKey("events")
            case ["recorder", "stats"]:
                return ParsedKey("recorder_stats")
            case ["recorder", "maps"]:
                return ParsedKey("recorder_maps")
            case ["alive", robot] if NAME_PATTERN.fullmatch(robot):
                return ParsedKey("alive", robot)
            case ["services", name] if NAME_PATTERN.fullmatch(name):
                return ParsedKey("services", name)
        raise BadInput("key", f"{key[:128]!r} is not a fleetmap key")
