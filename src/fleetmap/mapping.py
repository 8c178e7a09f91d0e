"""``fleetmap map``: real logs and bags mapped offline, in one command, by the live services' code.

Each input is one robot (``--split K`` cuts it into K robots' consecutive pieces, no scan in two).
Every robot's scans run through its own :class:`~fleetmap.agents.agent.Agent`, side by side in the
order of their clocks (each piece's clock starting at 0, as a fleet started together); the submaps
they publish go, as bytes, through one :class:`~fleetmap.merger.engine.Merger`, which takes a step
every ``merge.step_seconds`` of fleet time (the offline preset's 5 s) and, at the end, until it has
nothing left to do. Nothing is re-implemented: the same messages, in a fixed order, so the same
inputs give the same outputs.
The agents track in worker processes of their own (:class:`~fleetmap.agent_processes.AgentProcesses`:
the merger's work cannot starve them, as live), and the merger's side runs on a thread of its own,
a little behind them (:class:`_Behind`): its calls are the same, in the same order, while the
agents track the next scans and the executor's workers integrate.

Every scan an agent placed gets a global pose in its component (the merged map it belongs to):
its submap's pose composed with its pose in the submap, refined by the key scans registered on
the submaps they revisit (:meth:`~fleetmap.merger.engine.Merger.scan_poses`). While this
process refines them, a process of its own writes the session's files (the global map, its
picture, the occupancy grid): neither waits for the other (:class:`_Files`).
"""

from __future__ import annotations

import csv
import functools
import json
import math
import multiprocessing
import queue
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fleetmap.agent_processes import AgentProcesses, Finished
from fleetmap.merger.engine import Merger
from fleetmap.merger.executor import Executor
from fleetmap.report import SessionLog, write_outputs
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.warmup import warm
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import LocalMap, Message, Scan
from fleetmap.shared.io.sources import SourceScan, open_input

MAX_SPLIT = 64


def robot_name(path: str | Path, taken: set[str], piece: int | None = None) -> str:
    """A robot id from an input's file name (``aces.clf.gz`` -> ``aces``), unique among ``taken``;
    ``piece``: the number of one of its pieces (``--split``), kept after the name's first 24
    characters (cut off with them, a long name's pieces were numbered from 2, each after the last:
    ``freiburg-campus-correcte-2`` to ``-5`` for four)."""
    stem = Path(path).name.split(".")[0].lower()
    name = re.sub(r"[^a-z0-9_-]+", "-", stem).strip("-_") or "robot"
    if not name[0].isalpha():
        name = "r" + name
    name = name[:24] + ("" if piece is None else f"-{piece}")
    out, n = name, 2
    while out in taken:
        out, n = f"{name}-{n}", n + 1
    taken.add(out)
    return out


@dataclass
class Piece:
    """One robot of the run: consecutive scans of one input."""

    robot: str
    source: str
    scans: list[SourceScan]
    has_odometry: bool
    stamps: dict[int, float] = field(default_factory=dict)
    """Each scan's own stamp, by its index (what poses.csv writes)."""


def read_inputs(
    inputs: list[str],
    split: int,
    topic: str | None = None,
    range_max: float = math.inf,
    odometry_topic: str | None = None,
) -> list[Piece]:
    """Every input read whole, cut into ``split`` pieces of consecutive scans."""
    if not inputs:
        raise BadInput("INPUT", "give at least one log or bag")
    if isinstance(split, bool) or not 1 <= split <= MAX_SPLIT:
        raise BadInput("--split", f"must be an integer from 1 to {MAX_SPLIT}, got {split}")
    taken: set[str] = set()
    pieces: list[Piece] = []
    for path in inputs:
        source = open_input(path, topic, odometry_topic, range_max)
        try:
            scans = list(source)
        except (OSError, EOFError, UnicodeDecodeError) as exc:
            raise BadInput(str(path), f"cannot be read to its end ({exc.__class__.__name__}: {exc})") from None
        if not scans:
            raise BadInput(str(path), "holds no laser scan")
        if len(scans) < split:
            raise BadInput(str(path), f"has {len(scans)} scans: too few to split into {split} robots")
        base = robot_name(path, taken)
        cuts = np.array_split(np.arange(len(scans)), split)
        for k, cut in enumerate(cuts):
            robot = base if split == 1 else robot_name(base, taken, k + 1)
            part = scans[int(cut[0]) : int(cut[-1]) + 1]
            given = {s.index: s.stamp if s.given is None else s.given for s in part}
            pieces.append(Piece(robot, str(path), part, source.has_odometry, given))
    return pieces


class _Behind:
    """Calls run one after another on a thread of their own, in the order given (the merger's side
    of :func:`map_logs`: the same calls, in the same order, as run in line, so the same outputs). At
    most ``depth`` wait; the caller waits for room. The first call that raises stops the rest, and
    the next :meth:`call`, or :meth:`finish`, raises it in the caller."""

    def __init__(self, depth: int = 10_000) -> None:
        self._calls: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._cancelled = False
        self._thread = threading.Thread(target=self._run, name="fleetmap-merger", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            call = self._calls.get()
            if call is None:
                return
            if self._error is None and not self._cancelled:
                try:
                    call()
                except BaseException as exc:  # raised again in the caller's thread
                    self._error = exc

    def call(self, fn: Callable[[], None]) -> None:
        if self._error is not None:
            raise self._error
        self._calls.put(fn)

    def finish(self, cancel: bool = False) -> None:
        """Wait for every call given (with ``cancel``, for the one running: the caller is failing)."""
        self._cancelled = cancel
        self._calls.put(None)
        self._thread.join()
        if self._error is not None and not cancel:
            raise self._error


@dataclass
class MapResult:
    report: dict[str, Any]
    poses: list[tuple[str, float, int, Transform2D]]
    """(robot, stamp, component, laser pose in the component's frame) of every placed scan."""
    by_index: dict[tuple[str, int], tuple[int, Transform2D]] = field(default_factory=dict)
    """The same by (robot, the scan's index in its input): a log's stamps may repeat."""
    merger: Merger | None = None
    """The merger that made the map, its pose graph and all (benchmarks look inside it)."""


def map_logs(
    pieces: list[Piece],
    out_dir: str | Path,
    config: FleetmapConfig,
    progress: Callable[[int, int], None] | None = None,
    executor: Executor | None = None,
    on_step: Callable[[int, int, float], None] | None = None,
    tracking_processes: int | None = None,
    start_poses: dict[str, Transform2D] | None = None,
) -> MapResult:
    """Map the pieces (see the module docstring) and write the outputs into ``out_dir``, the
    integrations run by ``executor`` (default: in this process; the map is the same).
    ``on_step(submaps, integrations, seconds)`` hears of every merger step: the submaps in its
    graph, the integrations it has done in all, and the seconds the step took. The agents track in
    ``tracking_processes`` worker processes (:class:`~fleetmap.agent_processes.AgentProcesses`;
    default: one per robot, up to one fewer than the CPUs; 0: in this process); the map is the same.
    ``start_poses``: robots' known start poses in one frame, by robot id (a warning names those
    given for no piece; :mod:`fleetmap.merger.startposes`)."""
    started = time.perf_counter()
    _check_odometry(pieces, config)
    warm()  # the compiled loops built once, here, before the tracking workers start
    keys = FleetKeys()
    merger = Merger(keys, config, executor, keep_key_scans=True, start_poses=start_poses)
    if merger.start is not None:
        merger.start.warn_unknown([p.robot for p in pieces], "the inputs")
    side = _MergerSide(merger, keys, on_step)
    # every scan of every piece on one fleet clock (each piece's starting at 0), in a fixed order
    timeline = sorted((s.stamp - p.scans[0].stamp, n, i) for n, p in enumerate(pieces) for i, s in enumerate(p.scans))
    processes = AgentProcesses.default_processes(len(pieces)) if tracking_processes is None else tracking_processes
    agents = AgentProcesses(pieces, [(n, i) for _, n, i in timeline], config, processes)
    title = "fleetmap map: " + ", ".join(sorted({p.source for p in pieces}))
    with _Files(apart=processes > 0) as files:
        _track_and_merge(timeline, agents, side, progress, config.merge.step_seconds)
        written = files.write(side.log, out_dir, title)
        by_index = merger.scan_poses()
        report = written.result()
    poses = _with_stamps(by_index, pieces)
    seconds = time.perf_counter() - started
    report["map"] = _summary(pieces, poses, merger, agents.finished, seconds, agents.seconds, side.seconds)
    _write_map_files(Path(out_dir), report, poses, pieces)
    return MapResult(report, poses, by_index, merger)


class _Files:
    """Writes a session's files (:func:`~fleetmap.report.write_outputs`) in a process of its own
    when ``apart`` (else in this one), so that the key scans' refinement, on this process, and the
    picture, the occupancy grid and the global map's JSON, on that one, take the longer of their
    two times rather than the sum (mit-csail: about 4 s and 5 s, each on one core). The process
    starts with the block and loads what the writing needs (matplotlib: a second and a half)
    while the agents track. What it raises, :meth:`write`'s future raises here."""

    def __init__(self, apart: bool) -> None:
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("forkserver")) if apart else None

    def __enter__(self) -> _Files:
        if self._pool is not None:
            self._pool.submit(_load_writing)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)

    def write(self, log: SessionLog, out_dir: str | Path, title: str) -> Future[dict[str, Any]]:
        if self._pool is not None:
            return self._pool.submit(write_outputs, log, None, out_dir, title)
        done: Future[dict[str, Any]] = Future()
        done.set_result(write_outputs(log, None, out_dir, title))
        return done


def _load_writing() -> None:
    import fleetmap.merger.plot  # noqa: F401  (matplotlib, loaded before the files are due)


class _MergerSide:
    """The merger's side of :func:`map_logs`: the agents' messages in, as bytes, a step when due,
    and the session's log of both; its calls run in order on a :class:`_Behind` thread."""

    def __init__(self, merger: Merger, keys: FleetKeys, on_step: Callable[[int, int, float], None] | None) -> None:
        self.merger = merger
        self.keys = keys
        self.log = SessionLog()
        self.seconds = 0.0
        """The time the merger's steps took."""
        self._on_step = on_step

    def step(self, final: bool = False) -> None:
        t0 = time.perf_counter()
        out = self.merger.step(fuse=final)
        took = time.perf_counter() - t0  # the merger's step, not the session log's reading of it
        for o in out:
            self.log.add_payload(o.payload)
        self.seconds += took
        if self._on_step is not None:
            self._on_step(len(self.merger.submaps), self.merger.stats.integrations, took)

    def send(self, messages: list[Message]) -> None:
        for m in messages:
            self.log.add(m)
            if isinstance(m, (LocalMap, Scan)):
                self.merger.take(m)

    def steps_due(self, n: int = 1) -> None:
        """Up to ``n`` steps, while the merger has work."""
        for _ in range(n):
            if not self.merger.has_work:
                return
            self.step()

    def finish(self) -> None:
        while self.merger.has_work:
            self.step()
        self.step(final=True)  # the global map's walls, fused once


def _track_and_merge(
    timeline: list[tuple[float, int, int]],
    agents: AgentProcesses,
    side: _MergerSide,
    progress: Callable[[int, int], None] | None,
    step: float,
) -> None:
    """Every scan to its agent in the order of ``timeline`` (fleet seconds, piece, scan), what the
    agents publish to the merger's side, a merger step every ``step`` seconds of fleet time,
    and at the end the agents' last messages and the merger's last steps."""
    total = len(timeline)
    behind = _Behind()
    try:
        due = step
        with agents:
            for done, ((t, _, _), (_, _, out)) in enumerate(zip(timeline, agents, strict=True), 1):
                if t >= due:
                    # the steps due since the last scan, while the merger has work (a log's clock can
                    # jump by years: a call a step would never end)
                    after = (math.floor(t / step) + 1) * step if step > 0 else math.nextafter(t, math.inf)
                    n = max(1, round((after - due) / step)) if step > 0 else 1
                    behind.call(functools.partial(side.steps_due, n))
                    due = after
                if out:
                    behind.call(functools.partial(side.send, out))
                if progress is not None and (done % 50 == 0 or done == total):
                    progress(done, total)
        for n in range(len(agents.pieces)):
            behind.call(functools.partial(side.send, agents.finished[n].messages))
        behind.call(side.finish)
    except BaseException:
        behind.finish(cancel=True)
        raise
    behind.finish()


def _check_odometry(pieces: list[Piece], config: FleetmapConfig) -> None:
    if config.tracking.odometry == "on":
        for p in pieces:
            if not p.has_odometry:
                raise BadInput(p.source, "has no odometry (--odometry on needs it; auto uses it where there is some)")


def _write_map_files(
    folder: Path, report: dict[str, Any], poses: list[tuple[str, float, int, Transform2D]], pieces: list[Piece]
) -> None:
    """What ``fleetmap map`` adds to a session's outputs: report.json with its map section,
    poses.csv, and one TUM trajectory per robot."""
    (folder / "report.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    write_poses_csv(folder / "poses.csv", poses)
    for p in pieces:
        write_tum(folder / f"{p.robot}.tum", [x for x in poses if x[0] == p.robot])


def _with_stamps(
    by_index: dict[tuple[str, int], tuple[int, Transform2D]], pieces: list[Piece]
) -> list[tuple[str, float, int, Transform2D]]:
    """Every placed scan as ``(robot, stamp, component, pose)``, its stamp as its input gives it, by
    robot in input order, then in the input's order (the order poses.csv and the TUM files write:
    a log's stamps may repeat or go back)."""
    poses: list[tuple[str, float, int, Transform2D]] = []
    stamps = {p.robot: p.stamps for p in pieces}
    order = {p.robot: n for n, p in enumerate(pieces)}
    for (robot, index), (n, pose) in sorted(by_index.items(), key=lambda x: (order[x[0][0]], x[0][1])):
        stamp = stamps[robot].get(index)
        if stamp is not None:
            poses.append((robot, stamp, n, pose))
    return poses


def _summary(
    pieces: list[Piece],
    poses: list[tuple[str, float, int, Transform2D]],
    merger: Merger,
    finished: dict[int, Finished],
    seconds: float,
    agent_seconds: float,
    merger_seconds: float,
) -> dict[str, Any]:
    placed: dict[str, int] = {}
    components: dict[str, set[int]] = {}
    for robot, _, n, _ in poses:
        placed[robot] = placed.get(robot, 0) + 1
        components.setdefault(robot, set()).add(n)
    session: float | None = max(p.scans[-1].stamp - p.scans[0].stamp for p in pieces)
    inputs: dict[str, list[float]] = {}
    for p in pieces:
        inputs.setdefault(p.source, []).extend((p.scans[0].stamp, p.scans[-1].stamp))
    duration: float | None = sum(max(stamps) - min(stamps) for stamps in inputs.values())
    if any(s.given is not None for p in pieces for s in p.scans):
        duration = session = None  # stamps that could not be times (BusStamps) measure no duration
    result = merger.result
    return {
        "inputs": sorted({p.source for p in pieces}),
        "robots": [
            {
                "robot": p.robot,
                "input": p.source,
                "scans": len(p.scans),
                "first_stamp": p.stamps.get(p.scans[0].index, p.scans[0].stamp),
                "last_stamp": p.stamps.get(p.scans[-1].index, p.scans[-1].stamp),
                "odometry": p.has_odometry,
                "odometry_used": p.has_odometry and merger.config.tracking.odometry != "off",
                "epochs": finished[n].epochs,
                "scans_placed": placed.get(p.robot, 0),
                "components": sorted(components.get(p.robot, set())),
                "clock": finished[n].clock,
            }
            for n, p in enumerate(pieces)
        ],
        "submaps": len(merger.submaps),
        "components": 0 if result is None else len(result.components),
        "largest_component_submaps": 0
        if result is None or not result.components
        else len(result.components[0].members),
        "integrations": merger.stats.integrations,
        "integrations_near": merger.stats.near,
        "integrations_idle": merger.stats.idle,
        "join_pairs": merger.stats.join_pairs,
        "join_pairs_retried": merger.stats.retried,
        "far_scored": merger.stats.far_scored,
        "key_scans": merger.stats.key_scans,
        "scan_constraints": merger.stats.scan_constraints,
        "duration_s": duration,
        "session_s": session,
        "seconds": seconds,
        "agent_seconds": agent_seconds,
        "merger_seconds": merger_seconds,
        "time_share": seconds / duration if duration else None,
    }


def write_poses_csv(path: Path, poses: list[tuple[str, float, int, Transform2D]]) -> None:
    """``robot,stamp,component,x,y,theta`` (``docs/formats.md``), one line per placed scan."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["robot", "stamp", "component", "x", "y", "theta"])
        for robot, stamp, n, pose in poses:
            w.writerow([robot, repr(stamp), n, f"{pose.x:.6f}", f"{pose.y:.6f}", f"{pose.theta:.6f}"])


def write_tum(path: Path, poses: list[tuple[str, float, int, Transform2D]]) -> None:
    """A robot's trajectory in TUM format (``stamp x y z qx qy qz qw``, as evo reads it): its scans
    in the component that holds most of them (scans of other components share no frame with them)."""
    counts: dict[int, int] = {}
    for _, _, n, _ in poses:
        counts[n] = counts.get(n, 0) + 1
    lines = []
    if counts:
        main = min(counts, key=lambda n: (-counts[n], n))
        for _, stamp, n, pose in poses:
            if n == main:
                half = 0.5 * pose.theta
                lines.append(f"{stamp!r} {pose.x:.6f} {pose.y:.6f} 0 0 0 {math.sin(half):.9f} {math.cos(half):.9f}")
    path.write_text("".join(line + "\n" for line in lines), encoding="utf-8")
