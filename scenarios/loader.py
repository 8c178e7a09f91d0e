"""Scenario files (TOML): reading, validation, and the bundled scenarios.

A scenario file::

    name = "department"                 # optional: the file's stem
    description = "three robots on the Section V loop"
    world = "department"                # a bundled world (fleetmap.scenarios.worlds)
    seed = 7                            # seeds the laser noise

    [odometry]                          # optional: the robots' wheel odometry (defaults shown)
    enabled = true
    translation_error = 0.03            # systematic share of the distance driven
    rotation_error_deg_per_m = 1.5      # systematic heading drift
    noise = 0.01                        # random share of each step

    [laser]                             # optional; the defaults are the paper's SICK LMS 200
    fov_deg = 180.0
    resolution_deg = 1.0
    max_range = 8.0                     # m
    noise = 0.01                        # m, standard deviation
    dropout = 0.0                       # probability that a beam returns nothing
    spurious = 0.0                      # probability of a return short of the wall

    [[robots]]
    id = "r1"                           # ^[a-z][a-z0-9_-]{0,31}$
    path = [[3.0, 3.5], [5.0, 5.9], [8.0, 6.0]]   # waypoints, world frame (m)
    spacing = 0.2                       # m of path between scans (at most 2.8, the paper's largest)
    period = 0.2                        # scenario seconds between scans (here 5 Hz at 1 m/s)
    turn_rate = 1.0                     # rad/s on the spot at a waypoint (0: at once, between scans)
    start = 0.0                         # s (or give a join event)

    [[events]]
    t = 6.0
    type = "kidnap"                     # join | leave | crash | kidnap | merger_restart
    robot = "r1"
    pose = [20.0, 6.0, 0.0]             # x, y (m), theta (rad): where the robot is put down
    path = [[21.0, 1.5], [16.5, 1.2]]   # the waypoints it follows from there

    [[events]]
    t = 10.0
    type = "merger_restart"
    down_for = 3.0                      # s

Every error is a :class:`~fleetmap.shared.errors.ConfigError` naming the file, the field
(``robots[1].path[3]``) and what is wrong; unknown keys are errors too. Paths are checked against
the world: every waypoint inside the building and clear of walls and obstacles, no move through a
wall, and no turn between two consecutive scans larger than the paper's largest (1.73 rad).
"""

from __future__ import annotations

import itertools
import logging
import math
import re
import tomllib
from collections.abc import Iterable, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from fleetmap.scenarios.fleet import (
    EVENT_KINDS,
    Crash,
    Event,
    Join,
    Kidnap,
    Leave,
    MergerRestart,
    Point,
    RobotEvent,
    RobotSpec,
    Scenario,
    plan_robot,
    sample_motion,
)
from fleetmap.scenarios.laser import LaserParams
from fleetmap.scenarios.odometry import OdometryParams
from fleetmap.scenarios.worlds import WORLDS, World, get_world
from fleetmap.shared.core.geometry import Transform2D, wrap_angle
from fleetmap.shared.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULT_SCENARIO = "department"
"""What ``fleetmap run`` plays when no scenario is named."""

ROBOT_ID = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")

MAX_SCAN_SPACING = 2.8
"""The paper's largest displacement between consecutive scans (Section V: 0.34 to 2.8 m)."""
MAX_SCAN_TURN = 1.73
"""The paper's largest rotation between consecutive scans (Section V: up to 1.73 rad)."""
ROBOT_CLEARANCE = 0.25
"""How close (m) a robot's path may come to a wall: a robot has a body."""
PATH_CHECK_STEP = 0.05
"""Paths are checked for clearance every this many metres."""

TOP_KEYS = ("name", "description", "world", "seed", "laser", "odometry", "robots", "events")
LASER_KEYS = ("fov_deg", "resolution_deg", "max_range", "noise", "dropout", "spurious")
ODOMETRY_KEYS = ("enabled", "translation_error", "rotation_error_deg_per_m", "noise")
ROBOT_KEYS = ("id", "path", "spacing", "period", "turn_rate", "start")
EVENT_KEYS: dict[str, tuple[str, ...]] = {
    "join": ("t", "type", "robot"),
    "leave": ("t", "type", "robot"),
    "crash": ("t", "type", "robot"),
    "kidnap": ("t", "type", "robot", "pose", "path"),
    "merger_restart": ("t", "type", "down_for"),
}


class _Fields:
    """Typed reads of a decoded TOML document; every error names the file and the field path."""

    def __init__(self, source: str) -> None:
        self.source = source

    def error(self, where: str, reason: str) -> ConfigError:
        return ConfigError(f"{self.source}: {where}" if where else self.source, reason)

    def table(self, value: Any, where: str, known: Iterable[str], required: Iterable[str] = ()) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.error(where, f"must be a table, got {_kind(value)}")
        known = tuple(known)
        for key in value:
            if key not in known:
                raise self.error(_join(where, key), f"unknown key (known: {', '.join(known)})")
        for key in required:
            if key not in value:
                raise self.error(_join(where, key), "missing (required)")
        return value

    def value(self, table: Mapping[str, Any], key: str, where: str, default: Any) -> tuple[str, Any]:
        """The field's path and its value, or ``default`` when it is missing (None: required)."""
        at = _join(where, key)
        if key in table:
            return at, table[key]
        if default is None:
            raise self.error(at, "missing (required)")
        return at, default

    def number(
        self,
        table: Mapping[str, Any],
        key: str,
        where: str,
        default: float | None = None,
        low: float | None = None,
        high: float | None = None,
        low_open: bool = False,
    ) -> float:
        at, v = self.value(table, key, where, default)
        if key not in table:
            return float(v)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(at, f"must be a number, got {_kind(v)} {v!r}")
        x = float(v)
        if not math.isfinite(x):
            raise self.error(at, f"must be finite, got {v!r}")
        if low is not None and (x <= low if low_open else x < low):
            raise self.error(at, f"must be {'>' if low_open else '>='} {low:g}, got {x:g}")
        if high is not None and x > high:
            raise self.error(at, f"must be <= {high:g}, got {x:g}")
        return x

    def string(self, table: Mapping[str, Any], key: str, where: str, default: str | None = None) -> str:
        at, v = self.value(table, key, where, default)
        if not isinstance(v, str):
            raise self.error(at, f"must be a string, got {_kind(v)} {v!r}")
        return v

    def numbers(self, value: Any, where: str, n: int, what: str) -> tuple[float, ...]:
        if not isinstance(value, list) or len(value) != n:
            raise self.error(where, f"must be {what}, got {value!r}"[:200])
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise self.error(where, f"must be {what} of finite numbers, got {value!r}"[:200])
        return tuple(float(v) for v in value)

    def array_of_tables(self, value: Any, where: str) -> list[Any]:
        if not isinstance(value, list):
            raise self.error(where, f"must be an array of tables ([[{where}]]), got {_kind(value)}")
        return value


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _kind(v: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array"}.get(
        type(v), "a table" if isinstance(v, dict) else type(v).__name__
    )


def _laser(f: _Fields, value: Any) -> LaserParams:
    t = f.table(value, "laser", LASER_KEYS)
    d = LaserParams()
    fov = f.number(t, "fov_deg", "laser", math.degrees(d.fov), low=0.0, high=360.0, low_open=True)
    res = f.number(t, "resolution_deg", "laser", math.degrees(d.resolution), low=0.0, high=fov, low_open=True)
    if fov / res > 10_000:
        raise f.error("laser.resolution_deg", f"gives {fov / res:.0f} beams (at most 10000)")
    return LaserParams(
        fov=math.radians(fov),
        resolution=math.radians(res),
        max_range=f.number(t, "max_range", "laser", d.max_range, low=0.0, high=1000.0, low_open=True),
        noise=f.number(t, "noise", "laser", d.noise, low=0.0, high=1.0),
        dropout=f.number(t, "dropout", "laser", d.dropout, low=0.0, high=0.99),
        spurious=f.number(t, "spurious", "laser", d.spurious, low=0.0, high=0.99),
    )


def _odometry(f: _Fields, value: Any) -> OdometryParams:
    t = f.table(value, "odometry", ODOMETRY_KEYS)
    d = OdometryParams()
    enabled = t.get("enabled", d.enabled)
    if not isinstance(enabled, bool):
        raise f.error("odometry.enabled", f"must be true or false, got {enabled!r}")
    rotation = f.number(t, "rotation_error_deg_per_m", "odometry", math.degrees(d.rotation_error), low=0.0, high=90.0)
    return OdometryParams(
        enabled=enabled,
        translation_error=f.number(t, "translation_error", "odometry", d.translation_error, low=0.0, high=1.0),
        rotation_error=math.radians(rotation),
        noise=f.number(t, "noise", "odometry", d.noise, low=0.0, high=1.0),
    )


def _waypoints(f: _Fields, value: Any, where: str, world: World, minimum: int) -> tuple[Point, ...]:
    if not isinstance(value, list) or len(value) < minimum:
        raise f.error(where, f"must be a list of at least {minimum} waypoints [x, y], got {value!r}"[:200])
    points = []
    for i, v in enumerate(value):
        x, y = f.numbers(v, f"{where}[{i}]", 2, "a waypoint [x, y]")
        _check_position(f, (x, y), f"{where}[{i}]", world)
        points.append((x, y))
    return tuple(points)


def _check_position(f: _Fields, p: Point, where: str, world: World) -> None:
    if not world.inside(np.array(p))[()]:
        xmin, ymin, xmax, ymax = world.bounds
        raise f.error(
            where,
            f"({p[0]:g}, {p[1]:g}) is outside the free space of world {world.name!r} "
            f"(outside the building [{xmin:g}, {xmax:g}] x [{ymin:g}, {ymax:g}] or inside an obstacle)",
        )
    gap = float(world.clearance(np.array([p]))[0])
    if gap < ROBOT_CLEARANCE:
        raise f.error(where, f"({p[0]:g}, {p[1]:g}) is {gap:.2f} m from a wall (a robot needs {ROBOT_CLEARANCE} m)")


def _check_moves(f: _Fields, points: tuple[Point, ...], names: list[str], world: World) -> None:
    """Each straight move between consecutive waypoints stays clear of walls; errors name the move's end."""
    for i, (a, b) in enumerate(itertools.pairwise(points)):
        move = f"the move from {names[i]} {_pt(a)} to {_pt(b)}"
        length = math.hypot(b[0] - a[0], b[1] - a[1])
        if length < 1e-6:
            raise f.error(names[i + 1], f"the same point as {names[i]}")
        wall = world.crossing(a, b)
        if wall is not None:
            raise f.error(names[i + 1], f"{move} goes through the wall {_pt(wall[:2])}-{_pt(wall[2:])}")
        k = np.linspace(0.0, 1.0, max(2, math.ceil(length / PATH_CHECK_STEP) + 1))
        samples = np.array(a) + (np.array(b) - np.array(a)) * k[:, None]
        gaps = world.clearance(samples)
        worst = int(gaps.argmin())
        if gaps[worst] < ROBOT_CLEARANCE:
            raise f.error(
                names[i + 1],
                f"{move} passes {gaps[worst]:.2f} m from a wall near {_pt(samples[worst])} "
                f"(a robot needs {ROBOT_CLEARANCE} m)",
            )


def _pt(p: Any) -> str:
    return f"({float(p[0]):.2f}, {float(p[1]):.2f})"


def _check_turns(
    f: _Fields,
    path: tuple[Point, ...],
    robot: RobotSpec,
    names: list[str],
    heading: float | None,
) -> None:
    """No turn between two consecutive scans beyond the paper's largest (MAX_SCAN_TURN)."""
    samples = sample_motion(path, robot.spacing, robot.period, robot.turn_rate, heading)
    turns = np.abs(wrap_angle(np.diff(samples.poses[:, 2])))
    bad = np.flatnonzero(turns > MAX_SCAN_TURN)
    if len(bad):
        j = int(bad[0])
        corner = int(samples.legs[j]) + 1 if samples.legs[j + 1] > samples.legs[j] else 0
        raise f.error(
            names[corner],
            f"the robot turns {turns[j]:.2f} rad between two consecutive scans here (at most {MAX_SCAN_TURN} rad, "
            "the paper's largest rotation): add a waypoint to round the corner",
        )


def _robot(f: _Fields, value: Any, where: str, world: World) -> tuple[RobotSpec, bool]:
    t = f.table(value, where, ROBOT_KEYS, ("id", "path", "spacing", "period"))
    rid = f.string(t, "id", where)
    if not ROBOT_ID.match(rid):
        raise f.error(
            f"{where}.id", f"{rid!r} is not a robot id (lower-case letters, digits, - and _, 1-32 characters)"
        )
    path = _waypoints(f, t["path"], f"{where}.path", world, 2)
    names = [f"{where}.path[{i}]" for i in range(len(path))]
    _check_moves(f, path, names, world)
    spacing = f.number(t, "spacing", where, low=0.0, high=MAX_SCAN_SPACING, low_open=True)
    period = f.number(t, "period", where, low=0.0, high=3600.0, low_open=True)
    start = f.number(t, "start", where, 0.0, low=0.0)
    turn_rate = f.number(t, "turn_rate", where, 0.0, low=0.0, high=MAX_SCAN_TURN / period)
    robot = RobotSpec(rid, path, spacing, period, start, turn_rate)
    _check_turns(f, path, robot, names, None)
    return robot, "start" in t


def _event(f: _Fields, value: Any, where: str, robots: Mapping[str, RobotSpec], world: World) -> Event:
    if not isinstance(value, dict):
        raise f.error(where, f"must be a table, got {_kind(value)}")
    kind = f.string(value, "type", where)
    if kind not in EVENT_KINDS:
        raise f.error(f"{where}.type", f"unknown event type {kind!r} (known: {', '.join(EVENT_KINDS)})")
    keys = EVENT_KEYS[kind]
    t = f.table(value, where, keys, keys)
    when = f.number(t, "t", where, low=0.0)
    if kind == "merger_restart":
        return MergerRestart(when, f.number(t, "down_for", where, low=0.0, high=3600.0, low_open=True))
    rid = f.string(t, "robot", where)
    if rid not in robots:
        raise f.error(f"{where}.robot", f"unknown robot {rid!r} (robots: {', '.join(robots)})")
    if kind == "join":
        return Join(when, rid)
    if kind == "leave":
        return Leave(when, rid)
    if kind == "crash":
        return Crash(when, rid)
    x, y, theta = f.numbers(t["pose"], f"{where}.pose", 3, "a pose [x, y, theta]")
    _check_position(f, (x, y), f"{where}.pose", world)
    path = _waypoints(f, t["path"], f"{where}.path", world, 1)
    names = [f"{where}.pose"] + [f"{where}.path[{i}]" for i in range(len(path))]
    _check_moves(f, ((x, y), *path), names, world)
    _check_turns(f, ((x, y), *path), robots[rid], names, theta)
    return Kidnap(when, rid, Transform2D(x, y, float(wrap_angle(theta))), path)


def _check_timeline(f: _Fields, robot: RobotSpec, start_given: bool, events: list[tuple[int, RobotEvent]]) -> RobotSpec:
    """A robot's events make sense in time; returns the robot with its start set by a join."""
    joins = [(i, e) for i, e in events if isinstance(e, Join)]
    if len(joins) > 1:
        raise f.error(f"events[{joins[1][0]}]", f"robot {robot.id!r} joins twice (also events[{joins[0][0]}])")
    if joins:
        i, join = joins[0]
        if start_given and abs(join.t - robot.start) > 1e-9:
            raise f.error(
                f"events[{i}].t", f"robot {robot.id!r} has start = {robot.start:g} and joins at {join.t:g}: give one"
            )
        robot = RobotSpec(robot.id, robot.path, robot.spacing, robot.period, join.t, robot.turn_rate)
    ends = [(i, e) for i, e in events if isinstance(e, (Leave, Crash))]
    if len(ends) > 1:
        raise f.error(f"events[{ends[1][0]}]", f"robot {robot.id!r} already ends at events[{ends[0][0]}]")
    if ends:
        i, end = ends[0]
        if end.t <= robot.start:
            raise f.error(
                f"events[{i}].t", f"robot {robot.id!r} {end.kind}s at {end.t:g}, before it starts at {robot.start:g}"
            )
        for j, e in events:
            if j != i and e.t >= end.t:
                raise f.error(f"events[{j}].t", f"robot {robot.id!r} has already ended ({end.kind} at {end.t:g})")
    scans = plan_robot(robot, [e for _, e in events])
    for number, (i, e) in enumerate((i, e) for i, e in events if isinstance(e, Kidnap)):
        if e.t <= robot.start:
            raise f.error(
                f"events[{i}].t", f"robot {robot.id!r} is kidnapped at {e.t:g}, before it starts at {robot.start:g}"
            )
        if not any(s.leg == number + 1 for s in scans):
            last = scans[-1].stamp if scans else robot.start
            raise f.error(
                f"events[{i}].t",
                f"robot {robot.id!r} has finished its path (last scan at {last:g}) before the kidnap at {e.t:g}",
            )
    return robot


def parse_scenario(data: Any, source: str, default_name: str = "scenario") -> Scenario:
    """A Scenario from a decoded TOML document; ``source`` (the file) is named in every error."""
    f = _Fields(source)
    top = f.table(data, "", TOP_KEYS, ("world", "robots"))
    name = f.string(top, "name", "", default_name)
    description = f.string(top, "description", "", "")
    world_name = f.string(top, "world", "")
    if world_name not in WORLDS:
        raise f.error("world", f"unknown world {world_name!r} (known: {', '.join(WORLDS)})")
    world = get_world(world_name)
    seed_value = top.get("seed", 0)
    if isinstance(seed_value, bool) or not isinstance(seed_value, int) or seed_value < 0:
        raise f.error("seed", f"must be a non-negative integer, got {seed_value!r}")
    laser = _laser(f, top.get("laser", {}))
    odometry = _odometry(f, top.get("odometry", {}))
    robot_tables = f.array_of_tables(top["robots"], "robots")
    if not robot_tables:
        raise f.error("robots", "no robots")
    robots: dict[str, RobotSpec] = {}
    start_given: dict[str, bool] = {}
    for i, value in enumerate(robot_tables):
        robot, given = _robot(f, value, f"robots[{i}]", world)
        if robot.id in robots:
            raise f.error(f"robots[{i}].id", f"duplicate robot id {robot.id!r}")
        robots[robot.id] = robot
        start_given[robot.id] = given
    events = [
        _event(f, v, f"events[{i}]", robots, world)
        for i, v in enumerate(f.array_of_tables(top.get("events", []), "events"))
    ]
    for rid in list(robots):
        mine = [(i, e) for i, e in enumerate(events) if not isinstance(e, MergerRestart) and e.robot == rid]
        robots[rid] = _check_timeline(f, robots[rid], start_given[rid], mine)
    ordered = tuple(e for _, e in sorted(enumerate(events), key=lambda ie: (ie[1].t, ie[0])))
    return Scenario(name, description, world, seed_value, laser, tuple(robots.values()), ordered, source, odometry)


def read_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(path), "no such scenario file") from None
    except IsADirectoryError:
        raise ConfigError(str(path), "is a directory, not a scenario file") from None
    except UnicodeDecodeError:
        raise ConfigError(str(path), "not a text file (not UTF-8)") from None
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), f"not valid TOML: {exc}") from None
    scenario = parse_scenario(data, str(path), p.stem)
    log.debug(
        "scenario %s from %s: %d robots, %d events", scenario.name, path, len(scenario.robots), len(scenario.events)
    )
    return scenario


def list_scenarios() -> list[str]:
    """Names of the bundled scenarios."""
    data = resources.files("fleetmap.scenarios") / "data"
    return sorted(e.name.removesuffix(".toml") for e in data.iterdir() if e.name.endswith(".toml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A bundled scenario by name (``"department"``) or a scenario file by path."""
    text = str(name_or_path)
    if isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text or Path(text).is_file():
        return read_scenario(name_or_path)
    if text not in list_scenarios():
        raise ConfigError(
            f"scenario {text!r}", f"unknown scenario (bundled: {', '.join(list_scenarios())}; or a .toml file)"
        )
    with resources.as_file(resources.files("fleetmap.scenarios") / "data" / f"{text}.toml") as p:
        return read_scenario(p)


def scenario_to_toml(scenario: Scenario) -> str:
    """The resolved scenario as a scenario file (defaults filled in; reading it back gives the same scenario)."""
    lp = scenario.laser
    lines = [
        f"name = {_q(scenario.name)}",
        f"description = {_q(scenario.description)}",
        f"world = {_q(scenario.world.name)}",
        f"seed = {scenario.seed}",
        "",
        "[laser]",
        f"fov_deg = {math.degrees(lp.fov)!r}",
        f"resolution_deg = {math.degrees(lp.resolution)!r}",
        f"max_range = {lp.max_range!r}",
        f"noise = {lp.noise!r}",
        f"dropout = {lp.dropout!r}",
        f"spurious = {lp.spurious!r}",
        "",
        "[odometry]",
        f"enabled = {'true' if scenario.odometry.enabled else 'false'}",
        f"translation_error = {scenario.odometry.translation_error!r}",
        f"rotation_error_deg_per_m = {math.degrees(scenario.odometry.rotation_error)!r}",
        f"noise = {scenario.odometry.noise!r}",
    ]
    for r in scenario.robots:
        lines += ["", "[[robots]]", f"id = {_q(r.id)}", f"path = {_points(r.path)}"]
        lines += [f"spacing = {r.spacing!r}", f"period = {r.period!r}", f"turn_rate = {r.turn_rate!r}"]
        if not any(isinstance(e, Join) and e.robot == r.id for e in scenario.events):
            lines.append(f"start = {r.start!r}")
    for e in scenario.events:
        lines += ["", "[[events]]", f"t = {e.t!r}", f"type = {_q(e.kind)}"]
        if isinstance(e, MergerRestart):
            lines.append(f"down_for = {e.down_for!r}")
            continue
        lines.append(f"robot = {_q(e.robot)}")
        if isinstance(e, Kidnap):
            lines.append(f"pose = [{e.pose.x!r}, {e.pose.y!r}, {e.pose.theta!r}]")
            lines.append(f"path = {_points(e.path)}")
    return "\n".join(lines) + "\n"


def _q(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _points(points: tuple[Point, ...]) -> str:
    return "[" + ", ".join(f"[{x!r}, {y!r}]" for x, y in points) + "]"
