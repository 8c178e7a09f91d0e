"""benchmarks/raw_truth.py: a corrected log's relation that its own raw scans contradict is not
counted against a map that placed the scans as the raw scans do; a map's own error still is."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from fleetmap.shared.core.geometry import Transform2D

from tests.helpers import benchmark_tool

pytestmark = pytest.mark.slow  # the fast suite's slowest module fixture (a log read, 1.3 s): CI runs it


@pytest.fixture(scope="module")
def csail(datasets: Path):  # type: ignore[no-untyped-def]
    RawTruth = benchmark_tool("raw_truth").RawTruth
    path = datasets / "corrected" / "csail-corrected.log.gz"
    raw = RawTruth(path)
    poses = [Transform2D(*s.odometry) for s in raw.scans]
    return raw, poses


def turned(t: Transform2D, degrees: float) -> Transform2D:
    return t.compose(Transform2D(0.0, 0.0, math.radians(degrees)))


def test_a_corrected_pose_its_neighbours_raw_scans_turn_12_degrees_is_the_truths_error(csail) -> None:  # type: ignore[no-untyped-def]
    # GMapping's pose of csail-corrected's scan 42 lies 11-12 degrees off the walls of scans 41 and 43
    raw, poses = csail
    truth = poses[41].inverse().compose(poses[42])
    assert raw.sides_with_map(41, 42, truth, turned(truth, +11.3), 1.0, 10.0), "a map that placed 42 as the walls do"
    assert not raw.sides_with_map(41, 42, truth, turned(truth, -11.3), 1.0, 10.0), "a map turned the other way"


def test_a_maps_own_error_against_a_sound_corrected_relation_is_still_wrong(csail) -> None:  # type: ignore[no-untyped-def]
    raw, poses = csail
    truth = poses[40].inverse().compose(poses[41])
    for degrees in (-12.0, 12.0):
        assert not raw.sides_with_map(40, 41, truth, turned(truth, degrees), 1.0, 10.0)
    shifted = truth.compose(Transform2D(1.5, 0.0, 0.0))
    assert not raw.sides_with_map(40, 41, truth, shifted, 1.0, 10.0)


def test_a_run_of_scans_the_raw_steps_in_and_out_both_turn_is_re_placed_where_they_agree(csail) -> None:  # type: ignore[no-untyped-def]
    # GMapping turned csail-corrected's scans 397-399 11 degrees together and back; scans 15 and 398
    # face away from each other (1.3 m apart), so the pair's own returns cannot say
    raw, poses = csail
    truth = poses[15].inverse().compose(poses[398])
    assert raw.replaced(398, 1.0, 10.0) is not None
    assert raw.sides_with_map(15, 398, truth, turned(truth, +11.5), 1.0, 10.0), (
        "a map that placed 398 as its run's walls do"
    )
    assert not raw.sides_with_map(15, 398, truth, turned(truth, -11.5), 1.0, 10.0), "a map turned the other way"
    assert not raw.sides_with_map(15, 398, truth, truth.compose(Transform2D(1.5, 0.0, 0.0)), 1.0, 10.0)


def test_a_run_whose_two_re_placements_disagree_is_not_re_placed(csail) -> None:  # type: ignore[no-untyped-def]
    # scan 364: its fits on the returns of scans 363 and 365 put it in two different places
    raw, poses = csail
    assert raw.step(363, 1.0, 10.0) is not None and raw.step(364, 1.0, 10.0) is not None
    assert raw.replaced(364, 1.0, 10.0) is None
    truth = poses[357].inverse().compose(poses[364])
    assert not raw.sides_with_map(357, 364, truth, turned(truth, +20.0), 1.0, 10.0)
    assert raw.replaced(200, 1.0, 10.0) is None, "scan 200, deep in the run 43-363, shares no wall with scan 42 or 364"
