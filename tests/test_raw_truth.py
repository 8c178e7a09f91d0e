"""benchmarks/raw_truth.py: a corrected log's relation that its own raw scans contradict is not
counted against a map that placed the scans as the raw scans do; a map's own error still is."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
from fleetmap.shared.core.geometry import Transform2D

pytestmark = pytest.mark.slow  # the fast suite's slowest module fixture (a log read, 1.3 s): CI runs it

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.fixture(scope="module")
def csail(datasets: Path):  # type: ignore[no-untyped-def]
    sys.path.insert(0, str(BENCHMARKS))
    try:
        from raw_truth import RawTruth
    finally:
        sys.path.remove(str(BENCHMARKS))
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
