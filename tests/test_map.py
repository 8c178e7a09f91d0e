"""``fleetmap map``: real logs mapped offline; poses.csv as the contract gives it; bad inputs exit 2."""

from __future__ import annotations

import csv
import gzip
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fleetmap.agents.sources import ScenarioSource
from fleetmap.shared.geometry import Transform2D

from fleetmap.cli import main
from tests.agents.test_sources import write_bag

SCANS = 360


def fleetmap(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetmap", *args], capture_output=True, text=True, timeout=600, check=False
    )


@pytest.fixture(scope="module")
def csail_start(datasets: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first SCANS laser lines of the mit-csail log (odometry on its FLASER lines)."""
    out = tmp_path_factory.mktemp("csail") / "csail-start.clf"
    lines = []
    with gzip.open(datasets / "mit-csail" / "mit-csail.clf.gz", "rt") as fh:
        for line in fh:
            if line.startswith("FLASER"):
                lines.append(line)
                if len(lines) == SCANS:
                    break
    out.write_text("".join(lines))
    return out


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # maps 360 real scans twice as two robots (about 30 s)
def test_a_real_log_cut_in_two_maps_as_one_with_its_own_stamps(
    csail_start: Path, datasets: Path, tmp_path: Path
) -> None:
    runs = []
    for n in range(2):
        out = tmp_path / f"run{n}"
        done = fleetmap(
            "map", str(csail_start), "--out", str(out), "--split", "2", "--range-max", "81.91", "--no-progress"
        )
        assert done.returncode == 0, done.stderr
        runs.append(out)
    first, second = runs
    for name in (
        "global_map.json",
        "global_map.png",
        "report.json",
        "poses.csv",
        "csail-start-1.tum",
        "csail-start-2.tum",
    ):
        assert (first / name).is_file(), name
    # the same inputs give the same outputs, byte for byte
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
