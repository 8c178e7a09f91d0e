"""Synthetic worlds and scans for the tests (seeded, so every run sees the same data)."""

from __future__ import annotations

import functools
import importlib
import itertools
import math
import sys
from collections.abc import Iterable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from fleetmap.agents.agent import Agent
from fleetmap.scenarios.laser import LaserParams, simulate_scan
from fleetmap.shared.config import ExtractionParams, FleetmapConfig
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.segmap import SegmentMap
from pytest import MonkeyPatch

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def benchmark_tool(name: str) -> ModuleType:
    """The benchmark script ``benchmarks/NAME.py`` imported as a module (the scripts import each
    other by name, so their folder is on the path while it loads)."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCHMARKS))


def set_constant(monkeypatch: MonkeyPatch, owner: ModuleType, name: str, value: Any) -> None:
    """Set the module constant ``owner.name`` to ``value`` for one test, in ``owner`` and in every
    fleetmap module that imported it by name (``from owner import NAME``), so the code that reads it
    anywhere sees the new value; the test's processes only (a worker process keeps its own)."""
    old = getattr(owner, name)
    for module in list(sys.modules.values()):
        if module.__name__.startswith("fleetmap") and getattr(module, name, None) is old:
            monkeypatch.setattr(module, name, value)


# A 12 m x 10 m room with an irregular inside: boxes, an L-shaped wall, a slanted wall and a
# pillar, so that no rotation or shift of it looks like itself.
ROOM = np.array(
    [
        [0, 0, 12, 0],
        [12, 0, 12, 10],
        [12, 10, 0, 10],
        [0, 10, 0, 0],
        [2, 2, 3.5, 2],
        [3.5, 2, 3.5, 3],
        [3.5, 3, 2, 3],
        [2, 3, 2, 2],
        [7, 6, 9.5, 6],
        [9.5, 6, 9.5, 8.5],
        [8, 1, 10.5, 2.2],
        [5, 7.5, 5.6, 7.5],
        [5.6, 7.5, 5.6, 8.1],
        [5.6, 8.1, 5, 8.1],
        [5, 8.1, 5, 7.5],
        [0, 5, 1.2, 5],
        [10.8, 4, 12, 4.6],
    ],
    dtype=np.float64,
)

OMNI = LaserParams(fov=2 * math.pi - math.radians(1.0), resolution=math.radians(1.0), max_range=8.0, noise=0.01)
"""A 360 degree laser (1 deg, 8 m, 1 cm noise): any rotation between two poses keeps an overlap."""


def scan_map(world: Array, pose: tuple[float, float, float], laser: LaserParams, seed: int) -> SegmentMap:
    scan = simulate_scan(world, pose, laser, np.random.default_rng(seed))
    return SegmentMap(extract_segments(scan, ExtractionParams(max_range=laser.max_range)), ordered=True, oriented=True)


def pose_pair(rng: np.random.Generator, max_shift: float = 3.0) -> tuple[tuple[float, float, float], Transform2D]:
    """A laser pose A inside ROOM (away from walls and boxes) and a random T = pose of B in A's frame
    (any rotation in [-pi, pi), translation up to ``max_shift``) keeping B inside the room too."""
    free = [(4.5, 4.5), (6.5, 4.0), (4.0, 6.0), (6.0, 2.5), (9.0, 4.5), (3.0, 7.5)]
    while True:
        ax, ay = free[int(rng.integers(len(free)))]
        a = (ax + rng.uniform(-0.3, 0.3), ay + rng.uniform(-0.3, 0.3), rng.uniform(-math.pi, math.pi))
        r = rng.uniform(0.0, max_shift)
        phi = rng.uniform(-math.pi, math.pi)
        t = Transform2D(r * math.cos(phi), r * math.sin(phi), rng.uniform(-math.pi, math.pi))
        b = Transform2D(*a).compose(t)
        if 1.0 < b.x < 11.0 and 1.0 < b.y < 9.0 and _clear(b.x, b.y):
            return a, t


def _clear(x: float, y: float) -> bool:
    boxes = [(1.5, 1.5, 4.0, 3.5), (6.5, 5.5, 10.0, 9.0), (4.5, 7.0, 6.1, 8.6), (7.5, 0.5, 11.0, 2.7)]
    return not any(x0 <= x <= x1 and y0 <= y <= y1 for x0, y0, x1, y1 in boxes)


def true_local_map(scenario_name: str, robot: str, start: int, stop: int, epoch: int = 0, version: int = 0):  # type: ignore[no-untyped-def]
    """A robot's local map built from its scans ``start:stop`` placed at their TRUE poses (a perfect
    agent), as the LocalMap message the merger receives; its frame is scan ``start``'s, as an
    agent's epoch would be (an epoch after the first follows the one before, as an agent's do).
    Returns (message, true pose of the frame in the world). A bundled scenario's scans are its
    sparse copy's (:func:`sparse`)."""
    from fleetmap.scenarios import load_scenario, robot_stream
    from fleetmap.shared.core.fusion import fuse
    from fleetmap.shared.io.messages import EpochLink, LocalMap

    sc = load_scenario(sparse(scenario_name))
    scans = [s for s in robot_stream(sc, robot) if start <= s.index < stop]
    frame = scans[0].pose
    merged = None
    for s in scans:
        m = SegmentMap(extract_segments(s.scan), ordered=True, oriented=True)
        t = frame.inverse().compose(s.pose)
        merged = SegmentMap(t.apply(m.segments), oriented=True) if merged is None else fuse(merged, m, t)
    assert merged is not None
    last = frame.inverse().compose(scans[-1].pose)
    link = EpochLink(epoch - 1, "lost") if epoch > 0 else None
    message = LocalMap(robot, epoch, version, scans[-1].stamp, merged.segments, len(scans), last, link)
    return message, frame


SPARSE = Path(__file__).parent / "data" / "sparse"
"""Copies of the bundled scenarios whose robots scan every 0.8-1.2 m of path (the paper's Section V
spacing): the tests of pose-free integration and merging cut their maps from these."""


def sparse(name: str) -> str:
    """A bundled scenario's sparse copy (:data:`SPARSE`), or ``name`` itself (a file, or a name
    without one)."""
    path = SPARSE / f"{name}.toml"
    return str(path) if path.exists() else name


NORTH_LANE = str(Path(__file__).parent / "data" / "warehouse-north-lane.toml")
"""A warehouse-events variant: r1 carried to the north lane facing west (its scans 16 on), driving
away from the forklift's bay; the lane cases of the tests are cut from it."""


@functools.cache
def scenario_scans(name: str, robot: str, stop: int) -> list[tuple[float, SegmentMap, Transform2D]]:
    """(stamp, scan, true pose) of one robot's scans 0 to stop - 1 in a bundled scenario's sparse
    copy (:func:`sparse`) or a scenario file (once per test process: several tests cut their cases
    from the same scans)."""
    from fleetmap.scenarios import load_scenario, robot_stream

    out = []
    for s in itertools.islice(robot_stream(load_scenario(sparse(name)), robot), stop):
        m = SegmentMap(extract_segments(s.scan, ExtractionParams()), ordered=True, oriented=True)
        out.append((s.stamp, m, s.pose))
    return out


def tracked(scans: Iterable[Any], odometry: bool = True) -> tuple[Agent, dict[int, Transform2D]]:
    """Scans (each with ``index``, ``stamp``, ``scan``, ``odometry``) through one agent with the
    default config (reading their odometry unless not ``odometry``), finished: the agent, and the
    epoch poses of the scans it placed, by index."""
    agent = Agent("r1", FleetmapConfig(), odometry=odometry)
    poses: dict[int, Transform2D] = {}
    for s in [*scans, None]:
        agent.finish() if s is None else agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        poses.update({index: pose for index, _epoch, pose in agent.tracked if pose is not None})
    return agent, poses


def steps_off(
    truth: list[Transform2D],
    poses: dict[int, Transform2D],
    scans: Iterable[int],
    metres: float = 0.3,
    degrees: float = 5.0,
) -> dict[int, tuple[float, float]]:
    """The tracked steps into each of ``scans`` (from the scan before) off the corrected poses' by
    more than ``metres`` or ``degrees``: (m, deg) by scan."""
    return steps_between_off(truth, poses, ((i - 1, i) for i in scans), metres, degrees)


def steps_between_off(
    truth: list[Transform2D],
    poses: dict[int, Transform2D],
    pairs: Iterable[tuple[int, int]],
    metres: float = 0.3,
    degrees: float = 5.0,
) -> dict[int, tuple[float, float]]:
    """The tracked steps from ``a`` to ``b`` of each pair (a log with scans dropped steps over the
    gap) off the corrected poses' by more than ``metres`` or ``degrees``: (m, deg) by ``b``."""
    off = {}
    for a, b in pairs:
        error = truth[a].inverse().compose(truth[b]).inverse().compose(poses[a].inverse().compose(poses[b]))
        if math.hypot(error.x, error.y) > metres or abs(math.degrees(error.theta)) > degrees:
            off[b] = (round(math.hypot(error.x, error.y), 2), round(math.degrees(error.theta), 1))
    return off
