"""``fleetmap map``: real logs mapped offline; poses.csv as the contract gives it; bad inputs exit 2."""

from __future__ import annotations

import csv
import gzip
import json
import logging
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fleetmap.scenarios import load_scenario, robot_stream
from fleetmap.scenarios.stream import ScenarioSource
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.sources import open_input
from rosbags.rosbag2 import StoragePlugin
from scipy.spatial import cKDTree

from fleetmap.cli import main
from fleetmap.mapping import MapResult, _Behind
from tests.agents.test_sources import write_bag, write_scans_rosbag2
from tests.conftest import CSAIL_SCANS as SCANS
from tests.shared.test_occupancy import read_map_server


def fleetmap(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetmap", *args], capture_output=True, text=True, timeout=600, check=False
    )


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # maps 360 real scans as two robots (about 15 s)
def test_a_real_log_cut_in_two_maps_as_one_with_its_own_stamps(
    csail_start: Path, csail_in_line: tuple[MapResult, Path], datasets: Path, tmp_path: Path
) -> None:
    first, second = tmp_path / "run", csail_in_line[1]
    done = fleetmap(
        "map", str(csail_start), "--out", str(first), "--split", "2", "--no-return-reading", "81.91", "--no-progress",
        "--executor", "local", "--workers", "2",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    for name in (
        "global_map.json",
        "global_map.png",
        "report.json",
        "poses.csv",
        "csail-start-1.tum",
        "csail-start-2.tum",
    ):
        assert (first / name).is_file(), name
    # the same inputs give the same outputs, byte for byte, whether the command's worker processes
    # and process pool ran the tracking and the integrations or the mapping process alone did
    assert (first / "poses.csv").read_bytes() == (second / "poses.csv").read_bytes()
    text = (first / "poses.csv").read_text()
    assert text.splitlines()[0] == "robot,stamp,component,x,y,theta"
    rows = _rows(first / "poses.csv")
    # every scan placed, in one component (the two robots' maps merged), with the log's own stamps
    stamps = [line.split()[-3] for line in csail_start.read_text().splitlines()]
    assert len(rows) == SCANS and {r["robot"] for r in rows} == {"csail-start-1", "csail-start-2"}
    assert {r["component"] for r in rows} == {"0"}
    assert sorted(float(r["stamp"]) for r in rows) == sorted(float(s) for s in stamps)
    # the log's relations between these scans: the map is right, across the two robots too
    poses = {
        round(float(r["stamp"]), 4): (r["robot"], Transform2D(float(r["x"]), float(r["y"]), float(r["theta"])))
        for r in rows
    }
    errors = {True: [], False: []}  # type: dict[bool, list[float]]
    for t1, t2, x, y, _z, _roll, _pitch, yaw in np.loadtxt(datasets / "relations" / "mit-csail.relations"):
        a, b = poses.get(round(t1, 4)), poses.get(round(t2, 4))
        if a is None or b is None:
            continue
        error = Transform2D(x, y, yaw).inverse().compose(a[1].inverse().compose(b[1]))
        errors[a[0] != b[0]].append(math.hypot(error.x, error.y))
    assert errors[True], "no relation across the two robots"
    assert np.mean(errors[False] + errors[True]) < 0.10 and max(errors[True]) < 0.5, errors
    tum = (first / "csail-start-1.tum").read_text().splitlines()
    assert len(tum) == sum(r["robot"] == "csail-start-1" for r in rows) and len(tum[0].split()) == 8
    # the time is reported against the log's own duration; the two halves play as a session half as long
    summary = json.loads((first / "report.json").read_text())["map"]
    assert summary["duration_s"] == pytest.approx(float(stamps[-1]) - float(stamps[0]))
    assert summary["session_s"] < 0.6 * summary["duration_s"]
    assert summary["time_share"] == pytest.approx(summary["seconds"] / summary["duration_s"])
    # the global map it writes, integrated with itself, is the identity, valid (its fused walls
    # cross each other at junctions: that refused every transformation)
    done = fleetmap("integrate", str(first / "global_map.json"), str(first / "global_map.json"), "--json")
    assert done.returncode == 0, done.stderr
    itself = json.loads(done.stdout)
    assert itself["valid"] and itself["value"] > 100.0
    assert math.hypot(itself["x"], itself["y"]) < 0.01 and abs(itself["theta"]) < 1e-3


@pytest.mark.slow  # maps mit-csail's two halves apart, side by side (about 25 s)
def test_a_logs_two_halves_mapped_apart_merge_where_its_relations_put_them(datasets: Path, tmp_path: Path) -> None:
    with gzip.open(datasets / "mit-csail" / "mit-csail.clf.gz", "rt") as fh:
        lines = [line for line in fh if line.startswith(("FLASER", "ODOM"))]
    lasers = [n for n, line in enumerate(lines) if line.startswith("FLASER")]
    cut = lasers[len(lasers) // 2]
    maps, placed = [], []
    runs = {}
    for name, part in (("first", lines[:cut]), ("second", lines[cut:])):
        log = tmp_path / f"{name}.clf"
        log.write_text("".join(part))
        args = ["map", str(log), "--out", str(tmp_path / name), "--no-return-reading", "81.91", "--no-progress"]
        runs[name] = subprocess.Popen(
            [sys.executable, "-m", "fleetmap", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
    try:
        said = {name: run.communicate(timeout=600) for name, run in runs.items()}
    finally:
        for run in runs.values():
            if run.poll() is None:
                run.kill()
                run.wait()
    for name, run in runs.items():
        out = tmp_path / name
        done = subprocess.CompletedProcess(run.args, run.returncode, *said[name])
        assert done.returncode == 0, done.stderr
        # the summary names each robot's merged map as poses.csv does (#0: the largest), not a count
        header, row = done.stdout.splitlines()[:2]
        assert header.split()[4:6] == ["in", "map"] and row.split()[4] == "#0", done.stdout
        maps.append(out / "global_map.json")
        # the maps fleetmap writes say where their walls were seen from
        assert len(json.loads(maps[-1].read_text()).get("viewpoints", ())) > 10
        placed.append({round(float(r["stamp"]), 4): _pose(r) for r in _rows(out / "poses.csv")})
    done = fleetmap("merge", *map(str, maps), "--order", "unknown", "--json")
    assert done.returncode == 0, done.stderr
    merged = json.loads(done.stdout)
    assert len(merged["components"]) == 1, "the two halves stayed apart"
    first, second = (Transform2D(**merged["poses"][str(m)]) for m in maps)
    found = second.inverse().compose(first)  # the first half's frame in the second's
    # where the log's relations between scans of the two halves put it (each relation: the second
    # scan's pose in the first's)
    implied = []
    for t1, t2, x, y, _z, _roll, _pitch, yaw in np.loadtxt(datasets / "relations" / "mit-csail.relations"):
        for (a, b), rel in (((t1, t2), Transform2D(x, y, yaw)), ((t2, t1), Transform2D(x, y, yaw).inverse())):
            pa, pb = placed[0].get(round(a, 4)), placed[1].get(round(b, 4))
            if pa is not None and pb is not None:
                implied.append(pb.compose(rel.inverse()).compose(pa.inverse()).as_array())
    assert len(implied) >= 3
    truth = np.median(np.array(implied), axis=0)
    assert math.hypot(found.x - truth[0], found.y - truth[1]) < 0.5, (found, truth)
    assert abs(math.remainder(found.theta - truth[2], math.tau)) < math.radians(2), (found, truth)


def _pose(row: dict[str, str]) -> Transform2D:
    return Transform2D(float(row["x"]), float(row["y"]), float(row["theta"]))


def _one_error_line(capsys: pytest.CaptureFixture[str], args: list[str], names: str) -> None:
    """``fleetmap map ARGS`` in this process (the CLI's own entry point): exit 2, one line on
    stderr naming the input."""
    assert main(["map", *args]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and names in lines[0], lines


def test_bad_inputs_exit_2_naming_the_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a truncated compressed log
    scans = list(ScenarioSource("department", "r1"))[:20]
    lines = []
    for s in scans:
        ranges = " ".join(f"{r:.3f}" for r in s.scan.ranges)
        lines.append(f"FLASER {len(s.scan.ranges)} {ranges} 0 0 0 0 0 0 {s.stamp:.6f} host {s.stamp:.6f}\n")
    log = "".join(lines)
    truncated = tmp_path / "cut.clf.gz"
    truncated.write_bytes(gzip.compress(log.encode())[:-200])
    _one_error_line(capsys, [str(truncated), "--out", str(tmp_path / "a")], str(truncated))
    # a bag without scans
    bag = tmp_path / "empty.mcap"
    write_bag(bag, [])
    _one_error_line(capsys, [str(bag), "--out", str(tmp_path / "b")], str(bag))
    # an empty directory
    empty = tmp_path / "nothing"
    empty.mkdir()
    _one_error_line(capsys, [str(empty), "--out", str(tmp_path / "c")], str(empty))
    # a log too short for the robots it is to be cut into
    plain = tmp_path / "short.clf"
    plain.write_text(log)
    _one_error_line(capsys, [str(plain), "--out", str(tmp_path / "d"), "--split", "30"], str(plain))
    assert not any((tmp_path / d).exists() for d in "abcd")


@pytest.mark.slow  # runs fleetmap processes
def test_a_log_whose_logger_crashed_mid_line_maps_with_one_warning(tmp_path: Path) -> None:
    # the last line cut where the logger died: every whole scan is mapped, and the user is told once
    # which line was skipped
    scans = list(ScenarioSource("department", "r1"))[:30]
    lines = [
        f"FLASER {len(s.scan.ranges)} {' '.join(f'{r:.3f}' for r in s.scan.ranges)} 0 0 0 0 0 0 "
        f"{s.stamp:.6f} host {s.stamp:.6f}\n"
        for s in scans
    ]
    log = tmp_path / "crashed.clf"
    log.write_text("".join(lines) + lines[0][:200])
    run = fleetmap("map", str(log), "--out", str(tmp_path / "out"), "--no-progress")
    assert run.returncode == 0, run.stderr
    warnings = [line for line in run.stderr.splitlines() if "WARNING" in line]
    assert len(warnings) == 1 and f"{log}:31" in warnings[0] and "cut short" in warnings[0], run.stderr
    with (tmp_path / "out" / "poses.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 30


@pytest.mark.slow
def test_a_rosbag2_directory_its_mcap_and_a_db3_bag_map_alike(tmp_path: Path) -> None:
    # a simulated robot's scans and odometry recorded as ros2 bag record leaves them, in both of
    # rosbag2's storages: the directory, its .mcap file alone and the .db3 bag give one map, every
    # scan placed, within centimetres of the scenario's truth
    scans = list(ScenarioSource("department", "r1"))[:120]
    write_scans_rosbag2(tmp_path / "mcap_bag", StoragePlugin.MCAP, scans)
    write_scans_rosbag2(tmp_path / "db3_bag", StoragePlugin.SQLITE3, scans)
    (mcap_file,) = (tmp_path / "mcap_bag").glob("*.mcap")
    (db3_file,) = (tmp_path / "db3_bag").glob("*.db3")
    # the .mcap file alone is read as its directory is, scan for scan (so it maps as the directory
    # does: the command's work from the scans on is the same; each map run costs seconds)
    from_dir, from_file = list(open_input(tmp_path / "mcap_bag")), list(open_input(mcap_file))
    assert [(s.index, s.stamp, s.odometry) for s in from_dir] == [(s.index, s.stamp, s.odometry) for s in from_file]
    assert all(np.array_equal(a.scan.ranges, b.scan.ranges) for a, b in zip(from_dir, from_file, strict=True))
    poses = {}
    for name, bag in [("dir", tmp_path / "mcap_bag"), ("db3", db3_file)]:
        run = fleetmap("map", str(bag), "--out", str(tmp_path / name), "--no-progress")
        assert run.returncode == 0, run.stderr
        with (tmp_path / name / "poses.csv").open() as fh:
            rows = list(csv.DictReader(fh))
        poses[name] = [(row["stamp"], row["x"], row["y"], row["theta"]) for row in rows]
    assert len(poses["dir"]) == 120
    assert poses["dir"] == poses["db3"]
    # the stamps are the bag's own, and the trajectory is the one the simulator drove (its best
    # rigid fit: the map's frame is the robot's own first pose)
    assert [float(row[0]) for row in poses["dir"]] == pytest.approx([1.7e9 + s.stamp for s in scans], abs=1e-6)
    mapped = np.array([[float(x), float(y)] for _, x, y, _ in poses["dir"]])
    true = np.array([[p.x, p.y] for p in [s.pose for s in robot_stream(load_scenario("department"), "r1")][:120]])
    a, b = mapped - mapped.mean(axis=0), true - true.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    rotation = (u @ vt).T
    if np.linalg.det(rotation) < 0:
        rotation = (u @ np.diag([1.0, -1.0]) @ vt).T
    errors = np.hypot(*((a @ rotation.T) - b).T)
    assert errors.mean() < 0.08 and errors.max() < 0.2, (errors.mean(), errors.max())
    # map.yaml + map.pgm as nav2's map_server reads them: the occupied cells lie on the
    # department's walls, and no free cell does
    cells, origin, resolution = read_map_server(tmp_path / "dir" / "map.yaml")
    walls = load_scenario("department").world.walls
    t = np.linspace(0.0, 1.0, 400)[:, None]
    on_walls = cKDTree(np.vstack([w[0:2] + t * (w[2:4] - w[0:2]) for w in walls]))

    def to_world(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        centre = np.column_stack([origin[0] + (cols + 0.5) * resolution, origin[1] + (rows + 0.5) * resolution])
        return (centre - mapped.mean(axis=0)) @ rotation.T + true.mean(axis=0)

    # global_map.json holds the fused walls, on the department's
    fused = np.asarray(json.loads((tmp_path / "dir" / "global_map.json").read_text())["segments"]).reshape(-1, 2)
    assert len(fused) > 100
    assert np.median(on_walls.query((fused - mapped.mean(axis=0)) @ rotation.T + true.mean(axis=0))[0]) < 0.05
    occupied = on_walls.query(to_world(*np.nonzero(cells == 100)))[0]
    free = on_walls.query(to_world(*np.nonzero(cells == 0)))[0]
    assert len(occupied) > 1000 and len(free) > 20 * len(occupied)
    assert np.mean(occupied < 0.15) > 0.9, np.mean(occupied < 0.15)
    assert np.mean(free < resolution / 2) < 0.02, np.mean(free < resolution / 2)  # a wall through the cell


def test_the_merger_side_runs_in_order_and_its_first_error_reaches_the_caller() -> None:
    seen: list[int] = []
    behind = _Behind(depth=2)  # the caller waits for room: order kept however far ahead it is
    for k in range(50):
        behind.call(lambda k=k: seen.append(k))
    behind.finish()
    assert seen == list(range(50))

    def fail() -> None:
        raise RuntimeError("the merger broke")

    seen.clear()
    failing = _Behind()
    failing.call(lambda: seen.append(1))
    failing.call(fail)
    # the error comes back at the next call, or at the latest when the caller finishes
    with pytest.raises(RuntimeError, match="the merger broke"):
        failing.call(lambda: seen.append(2))  # after the error: never run
        failing.finish()
    assert seen == [1]


def test_the_summary_says_whether_the_tracking_used_each_robot_s_odometry() -> None:
    from fleetmap.commands.map import table

    robot = {"scans": 10, "scans_placed": 10, "epochs": 1, "components": [0]}
    summary = {
        "robots": [
            {**robot, "robot": "wheels", "odometry": True, "odometry_used": True},
            {**robot, "robot": "ignored", "odometry": True, "odometry_used": False},
            {**robot, "robot": "laser-only", "odometry": False, "odometry_used": False},
        ],
        "time_share": 0.1, "session_s": 10.0, "duration_s": 10.0, "submaps": 3, "components": 1,
        "largest_component_submaps": 3, "integrations": 2, "integrations_near": 1, "integrations_idle": 0,
        "seconds": 1.0,
    }  # fmt: skip
    said = {line.split()[0]: line.split(None, 5)[5].strip() for line in table(summary).splitlines()[1:4]}
    assert said == {"wheels": "used", "ignored": "not used", "laser-only": "none"}


@pytest.mark.slow  # maps 360 real scans (about 8 s)
def test_a_log_stamped_before_its_start_and_then_never_again_maps_with_its_own_stamps(
    csail_start: Path, datasets: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A converter that counted time from its own start, backwards, then lost the clock (the
    stamps of corrected/infinite-corridor: -0.45 to -1.82 s, then 4.29e9 s for every scan). It was
    refused for its first stamp; a merger step per second of its jump would never have ended."""
    from fleetmap.merger.executor import InlineExecutor

    from fleetmap.config_args import preset
    from fleetmap.mapping import map_logs, read_inputs

    lines = csail_start.read_text().splitlines()
    own = [float(line.split()[-3]) for line in lines]
    given = [-0.4 - (t - own[0]) if n < 4 else 4294970000.0 for n, t in enumerate(own)]
    log = tmp_path / "no-clock.clf"
    log.write_text(
        "".join(
            " ".join([*line.split()[:-3], repr(t), "host", repr(t)]) + "\n"
            for line, t in zip(lines, given, strict=True)
        )
    )
    with caplog.at_level(logging.WARNING, logger="fleetmap.shared.io.sources"):
        pieces = read_inputs([str(log)], 1, None, 81.91, None)
    said = [r.getMessage() for r in caplog.records if r.name == "fleetmap.shared.io.sources"]
    assert len(said) == 2 and "scan 0: stamp -0.4 cannot be a time (it is negative)" in said[0], said
    assert "4 of its 360 scans' stamps could not be times" in said[1], said
    result = map_logs(pieces, tmp_path / "out", preset("offline"), None, InlineExecutor(), tracking_processes=0)
    rows = _rows(tmp_path / "out" / "poses.csv")
    # every scan placed, in one map, in the log's order, with the log's own stamps
    assert [float(r["stamp"]) for r in rows] == given
    assert {r["component"] for r in rows} == {"0"}
    assert result.report["map"]["robots"][0]["first_stamp"] == -0.4
    # such stamps measure no duration (not 4.29e9 s of log)
    assert result.report["map"]["duration_s"] is None and result.report["map"]["time_share"] is None
    # the map is right: the log's relations between these scans, by the scans' true times
    poses = {round(t, 4): _pose(r) for t, r in zip(own, rows, strict=True)}
    errors = []
    for t1, t2, x, y, _z, _roll, _pitch, yaw in np.loadtxt(datasets / "relations" / "mit-csail.relations"):
        a, b = poses.get(round(t1, 4)), poses.get(round(t2, 4))
        if a is not None and b is not None:
            errors.append(math.hypot(*Transform2D(x, y, yaw).inverse().compose(a.inverse().compose(b)).as_array()[:2]))
    assert len(errors) > 50 and np.mean(errors) < 0.10, errors


def test_a_long_named_log_cut_into_pieces_names_them_1_to_k(csail_start: Path, tmp_path: Path) -> None:
    from fleetmap.mapping import read_inputs

    # robot ids keep a file name's first 24 characters; the piece's number used to be cut off
    # with the rest, so a long name's four pieces were named -2 to -5
    long = tmp_path / "freiburg-campus-corrected.clf"
    long.symlink_to(csail_start)
    names = [p.robot for p in read_inputs([str(long), str(csail_start)], 4)]
    assert names[:4] == [f"freiburg-campus-correcte-{k}" for k in (1, 2, 3, 4)]
    assert names[4:] == [f"csail-start-{k}" for k in (1, 2, 3, 4)]
