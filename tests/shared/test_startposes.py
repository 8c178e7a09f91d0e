"""Reading known start poses (``--start-poses``): every bad row named by file and line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.startposes import read_start_poses


def test_start_poses_are_read_with_or_without_a_header(tmp_path: Path) -> None:
    with_header = tmp_path / "a.csv"
    with_header.write_text("robot,x,y,theta\nr1,0,0,0\n\n# the second dock\nr2, 3.5, -1.25, 1.5708\n")
    without = tmp_path / "b.csv"
    without.write_text("r1,0,0,0\nr2,3.5,-1.25,1.5708")
    for path in (with_header, without):
        poses = read_start_poses(path)
        assert poses == {"r1": Transform2D(0.0, 0.0, 0.0), "r2": Transform2D(3.5, -1.25, 1.5708)}
        assert math.isclose(poses["r2"].theta, 1.5708)


@pytest.mark.parametrize(
    ("text", "line", "says"),
    [
        ("robot,x,y,theta\nr1,0,0\n", 2, "4 fields"),
        ("r1,0,0,0\nr2,1,north,0\n", 2, "y 'north' is not a number"),
        ("r1,0,0,nan\n", 1, "theta 'nan' is not finite"),
        ("r1,0,0,0\n\nRobot 2,1,1,0\n", 3, "is not a robot id"),
        ("r1,0,0,0\nr1,1,1,0\n", 2, "twice"),
        ("robot,x,y,theta\nrobot,x,y,theta\n", 2, "x 'x' is not a number"),
    ],
)
def test_a_bad_row_is_named_by_file_and_line(tmp_path: Path, text: str, line: int, says: str) -> None:
    path = tmp_path / "poses.csv"
    path.write_text(text)
    with pytest.raises(BadInput) as caught:
        read_start_poses(path)
    assert caught.value.source == f"{path}, line {line}"
    assert says in caught.value.reason


def test_a_file_without_start_poses_or_not_there_is_named(tmp_path: Path) -> None:
    empty = tmp_path / "empty.csv"
    empty.write_text("robot,x,y,theta\n")
    with pytest.raises(BadInput, match="holds no start pose") as caught:
        read_start_poses(empty)
    assert caught.value.source == str(empty)
    with pytest.raises(BadInput, match="cannot be read"):
        read_start_poses(tmp_path / "missing.csv")
