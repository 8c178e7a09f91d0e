"""``--start-poses``: a log's two halves placed from their start poses, a wrong one corrected where
their maps meet; bad files exit 2 naming the file and line."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from fleetmap.merger.executor import InlineExecutor
from fleetmap.shared.core.geometry import Transform2D

from fleetmap.cli import main
from fleetmap.config_args import preset
from fleetmap.mapping import Piece, map_logs


@pytest.mark.parametrize("command", [["map", "no-such.clf", "--out", "out"], ["merger"]])
def test_a_bad_start_pose_row_exits_2_naming_the_file_and_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    bad = tmp_path / "poses.csv"
    bad.write_text("robot,x,y,theta\nr1,0,0,0\nr2,1.5,two,0\n")
    assert main([*command, "--start-poses", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}, line 3: y 'two' is not a number" in err[0], err


@pytest.mark.slow  # maps 360 real scans as two robots, in this process (about 10 s)
def test_a_start_pose_3_m_wrong_is_corrected_where_the_maps_meet(
    csail_pieces: list[Piece], datasets: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    first, second = (p.robot for p in csail_pieces)
    # the second half starts about (-3.5, -5.4) m and -77 degrees from the first; said 3 m east of that
    given = Transform2D(-0.5, -5.4, -1.34)
    start = {first: Transform2D(0.0, 0.0, 0.0), second: given, "ghost": Transform2D(9.0, 9.0, 0.0)}
    with caplog.at_level(logging.WARNING):
        result = map_logs(
            csail_pieces, tmp_path, preset("offline"), None, InlineExecutor(), tracking_processes=0, start_poses=start
        )
    assert any("ghost" in r.getMessage() and "not used" in r.getMessage() for r in caplog.records)
    assert {c for _, _, c, _ in result.poses} == {0}
    by_stamp = {round(stamp, 4): (robot, pose) for robot, stamp, _, pose in result.poses}
    origin = {r: next(pose for robot, _, _, pose in result.poses if robot == r) for r in (first, second)}
    found = origin[first].inverse().compose(origin[second])  # the second half's start in the first's
    # where the log's relations between scans of the two halves put it (each in its own half's frame)
    implied = []
    for t1, t2, x, y, _z, _roll, _pitch, yaw in np.loadtxt(datasets / "relations" / "mit-csail.relations"):
        for (a, b), rel in (((t1, t2), Transform2D(x, y, yaw)), ((t2, t1), Transform2D(x, y, yaw).inverse())):
            pa, pb = by_stamp.get(round(a, 4)), by_stamp.get(round(b, 4))
            if pa is not None and pb is not None and (pa[0], pb[0]) == (first, second):
                in_first = origin[first].inverse().compose(pa[1])
                in_second = origin[second].inverse().compose(pb[1])
                implied.append(in_first.compose(rel).compose(in_second.inverse()).as_array())
    assert len(implied) >= 3
    truth = Transform2D.from_array(np.median(np.array(implied), axis=0))
    assert given.distance(truth)[0] > 2.5  # the start pose was wrong ...
    dt, dr = found.distance(truth)
    assert dt < 0.10 and math.degrees(dr) < 2.0, (found, truth)  # ... and the overlap corrected it
