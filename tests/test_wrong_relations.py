"""benchmarks/wrong_relations.py: wrong relations are listed by the stretches of scans they hold,
and a submap's truth is its frame scan's corrected pose."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.messages import LocalMap

from tests.helpers import benchmark_tool

pytestmark = pytest.mark.slow  # importing the tool imports the mapping and the benchmarks (2 s): CI runs it


@pytest.fixture(scope="module")
def tool():  # type: ignore[no-untyped-def]
    return benchmark_tool("wrong_relations")


def test_wrong_relations_are_grouped_by_a_robots_consecutive_scans_most_first(tool) -> None:  # type: ignore[no-untyped-def]
    scans = {
        ("r1", 100): [2.0, 4.0],
        ("r1", 103): [6.0],  # 3 scans on: the same stretch
        ("r1", 200): [0.5],  # far on: another
        ("r2", 101): [1.0],  # another robot's scan between: its own stretch
    }
    assert tool.stretches(scans) == [("r1", 100, 103, 3, 4.0), ("r1", 200, 200, 1, 0.5), ("r2", 101, 101, 1, 1.0)]


def test_a_submaps_truth_is_its_frame_scans_corrected_pose(tool) -> None:  # type: ignore[no-untyped-def]
    truth = [Transform2D(float(i), 0.0, 0.1 * i) for i in range(10)]
    submap = LocalMap(
        "r1",
        0,
        1,
        0.0,
        np.array([[0.0, 0.0, 1.0, 0.0]]),
        3,
        submap=2,
        scan_indices=np.array([6, 7]),
        scan_stamps=np.array([6.0, 7.0]),
        scan_poses=np.array([[1.0, 0.0, 0.1], [2.0, 0.0, 0.2]]),
        frame_scan=5,
    )
    assert tool.frame_truth(submap, truth) == truth[5], "the scan whose laser pose is the frame, not a placed one"
    assert tool.frame_truth(replace(submap, frame_scan=12), truth) is None, "beyond the log"


def test_frames_are_laid_on_the_truth_and_a_drifted_stretch_stands_out(tool) -> None:  # type: ignore[no-untyped-def]
    # a chain of ten frames along a corridor, solved in its own frame (turned and moved), with
    # frames 6-7 pushed 2 m aside: laid on the truth, those two stand out and the rest not
    true = {f"r1/0/{i}": Transform2D(2.0 * i, 0.0, 0.0) for i in range(10)}
    frame = Transform2D(5.0, -3.0, 0.7)
    solved = {k: frame.inverse().compose(p) for k, p in true.items()}
    for k in ("r1/0/6", "r1/0/7"):
        solved[k] = solved[k].compose(Transform2D(0.0, 2.0, 0.0))
    offsets = tool.frame_offsets(solved, true)
    # (the median: the pushed pair's error is theirs alone, not spread over the rest)
    assert all(abs(offsets[k][0] - 2.0) < 1e-6 for k in ("r1/0/6", "r1/0/7")), offsets
    assert all(offsets[k][0] < 1e-6 for k in true if k not in ("r1/0/6", "r1/0/7")), offsets
    assert all(offsets[k][1] < 1e-6 for k in true), "headings untouched"
    scans = [10 * i for i in range(10)]
    assert tool.runs_over(scans, [offsets[f"r1/0/{i}"][0] for i in range(10)], 1.0) == [(60, 70)]
    assert tool.runs_over([1, 2, 3], [2.0, 0.0, 2.0], 1.0) == [(1, 1), (3, 3)]
