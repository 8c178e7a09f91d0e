"""Segment extraction (paper III-D) and the scan readers."""

from __future__ import annotations

import gzip
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from fleetmap.scenarios.laser import LaserParams, simulate_scan
from fleetmap.shared.config import ExtractionParams
from fleetmap.shared.core import extraction
from fleetmap.shared.core.extraction import _returns, clusters, extract_segments, range_noise, split_polyline
from fleetmap.shared.core.geometry import lengths, point_segment_distance
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.logs import read_carmen, read_ranges_jsonl

CORNER = np.array([[3.0, -4.0, 3.0, 2.0], [3.0, 2.0, -3.0, 2.0]])


def scan_of(walls: np.ndarray, noise: float = 0.0, seed: int = 0) -> RangeScan:
    return simulate_scan(walls, (0.0, 0.0, 0.0), LaserParams(noise=noise), np.random.default_rng(seed))


def test_a_noiseless_corner_gives_touching_segments_on_the_walls(monkeypatch: pytest.MonkeyPatch) -> None:
    # The paper's polyline: both walls, and a short cut across the corner between two beams.
    monkeypatch.setattr(extraction, "LINE_FIT", False)
    seg = extract_segments(scan_of(CORNER))
    assert len(seg) == 3 and lengths(seg)[1] < 0.1
    np.testing.assert_allclose(seg[:-1, 2:4], seg[1:, 0:2], atol=1e-9)
    np.testing.assert_allclose(seg[0, [0, 2]], [3.0, 3.0], atol=1e-6)
    np.testing.assert_allclose(seg[2, [1, 3]], [2.0, 2.0], atol=1e-6)


def test_line_fit_puts_the_corner_where_the_walls_cross() -> None:
    seg = extract_segments(scan_of(CORNER, noise=0.005, seed=2))
    assert len(seg) == 2
    np.testing.assert_allclose(seg[0, 2:4], seg[1, 0:2], atol=1e-9)
    assert math.hypot(seg[0, 2] - 3.0, seg[0, 3] - 2.0) < 0.01


@pytest.mark.parametrize("line_fit", [False, True])
def test_every_point_is_within_kappa_of_its_segments(line_fit: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    scan = scan_of(CORNER, noise=0.005, seed=3)
    monkeypatch.setattr(extraction, "LINE_FIT", line_fit)
    params = ExtractionParams()
    seg = extract_segments(scan, params)
    a = scan.angle_min + np.arange(len(scan.ranges)) * scan.angle_increment
    ok = np.isfinite(scan.ranges)
    pts = np.column_stack([scan.ranges[ok] * np.cos(a[ok]), scan.ranges[ok] * np.sin(a[ok])])
    d = point_segment_distance(pts[:, None, :], seg[None, :, :]).min(axis=1)
    # The paper's polylines pass within kappa of every point; fitted lines within 2 kappa.
    assert d.max() <= (2 if line_fit else 1) * params.kappa + 1e-9


def test_line_fit_keeps_a_noisy_wall_in_one_piece(monkeypatch: pytest.MonkeyPatch) -> None:
    wall = np.array([[2.0, -3.0, 2.0, 3.0]])
    # 1.5 cm noise (or 5 cm range quantisation, as in the aces log) puts readings beyond kappa.
    fitted = extract_segments(scan_of(wall, noise=0.015, seed=1))
    monkeypatch.setattr(extraction, "LINE_FIT", False)
    plain = extract_segments(scan_of(wall, noise=0.015, seed=1))
    assert len(plain) > 3  # the paper's split cuts at every reading beyond kappa
    assert len(fitted) == 1
    assert abs(fitted[0, 0] - 2.0) < 0.01 and abs(fitted[0, 2] - 2.0) < 0.01
    assert lengths(fitted)[0] > 5.8


@pytest.mark.parametrize("sigma", [0.0, 0.01, 0.03])
def test_range_noise_reads_the_laser_noise_off_one_scan(sigma: float) -> None:
    # A middle point's distance from its neighbours' chord is N(0, 1.5 sigma^2) across a wall
    # seen head-on: its median is 0.83 sigma. A room's corners do not move the median.
    room = np.array([[3.0, -4.0, 3.0, 3.0], [3.0, 3.0, -3.0, 3.0], [-3.0, -4.0, 3.0, -4.0]])
    noise = range_noise(*_returns(scan_of(room, noise=sigma, seed=4), 20.0))
    assert noise == pytest.approx(0.83 * sigma, rel=0.2, abs=1e-6)


def test_a_noisy_lasers_wall_stays_one_segment_with_kappa_from_its_noise() -> None:
    # 3 cm of range noise (edmonton's laser shows about 2.6 cm) is beyond what line fitting at
    # kappa = 2.5 cm merges: the wall falls into short pieces whose directions are off by degrees.
    wall = np.array([[2.0, -3.0, 2.0, 3.0]])
    scan = scan_of(wall, noise=0.03, seed=5)
    fixed = extract_segments(scan, ExtractionParams(kappa_noise_factor=0.0))
    from_noise = extract_segments(scan, ExtractionParams())  # kappa_noise_factor = 3 by default
    assert len(fixed) > 4
    assert len(from_noise) <= 2 and lengths(from_noise).max() > 4.0
    # A laser of 1 cm noise (the simulator's) keeps kappa: the same segments either way.
    room = np.array([[3.0, -4.0, 3.0, 3.0], [3.0, 3.0, -3.0, 3.0], [-3.0, -4.0, 3.0, -4.0]])
    for seed in range(4):
        clean = scan_of(room, noise=0.01, seed=seed)
        np.testing.assert_array_equal(
            extract_segments(clean, ExtractionParams()), extract_segments(clean, ExtractionParams(kappa_noise_factor=0))
        )


def test_segments_run_counter_clockwise_with_the_sensor_on_their_left() -> None:
    seg = extract_segments(scan_of(CORNER, noise=0.01))
    cross = (seg[:, 2] - seg[:, 0]) * (0 - seg[:, 1]) - (seg[:, 3] - seg[:, 1]) * (0 - seg[:, 0])
    assert (cross > 0).all()
    bearings = np.arctan2(seg[:, 1], seg[:, 0])
    assert (np.diff(bearings) > 0).all()


def test_no_return_beams_and_far_ranges_are_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    r = np.full(181, 2.0)
    holes = [(10, 20, np.nan), (30, 40, 0.0), (50, 60, 100.0), (70, 80, 9.0)]  # 100 > range_max, 9 > max_range
    for lo, hi, value in holes:
        r[lo:hi] = value
    scan = RangeScan(0.0, -math.pi / 2, math.radians(1), 81.9, r)
    monkeypatch.setattr(extraction, "LINE_FIT", False)
    seg = extract_segments(scan, ExtractionParams(max_range=8.0))
    pts = seg.reshape(-1, 2)
    np.testing.assert_allclose(np.hypot(pts[:, 0], pts[:, 1]), 2.0, atol=1e-9)
    beam = np.round((np.arctan2(pts[:, 1], pts[:, 0]) + math.pi / 2) / math.radians(1)).astype(int)
    for lo, hi, _ in holes:
        assert not ((beam >= lo) & (beam < hi)).any()
    # Each of the five runs of returns is covered from its first beam to its last.
    assert set(beam) >= {0, 9, 20, 29, 40, 49, 60, 69, 80, 180}


def test_clusters_break_where_consecutive_points_are_tau_apart() -> None:
    pts = np.array([[0, 0], [0.1, 0], [0.2, 0], [0.6, 0], [0.7, 0]], dtype=float)
    assert [len(c) for c in clusters(pts, 0.2)] == [3, 2]


def test_split_adds_the_farthest_point_until_within_kappa() -> None:
    pts = np.array([[0, 0], [1, 0.01], [2, 0.5], [3, 0.0]], dtype=float)
    assert split_polyline(pts, 0.025) == [0, 1, 2, 3]
    assert split_polyline(pts, 1.0) == [0, 3]


def _flaser_line(ranges: list[float], stamp: float) -> str:
    return f"FLASER {len(ranges)} {' '.join(map(str, ranges))} 1 2 0.5 1 2 0.5 {stamp} host {stamp}\n"


def test_carmen_reader_reads_flaser_rlaser_and_robotlaser1_plain_and_gz(tmp_path: Path) -> None:
    ranges = [2.0] * 181
    robot = (
        "ROBOTLASER1 0 -1.5707963 3.1415926 0.0174533 81.9 0.01 0 181 "
        + " ".join(["3.0"] * 181)
        + " 0 0 0 0 0 0 0 0 0 0 0 0 42.5 host 42.5\n"
    )
    text = (
        "# comment\nODOM 0 0 0 0 0 0 1 host 1\n"
        + _flaser_line(ranges, 10.0)
        + _flaser_line(ranges, 11.0).replace("FLASER", "RLASER")
        + robot
    )
    plain = tmp_path / "log.clf"
    plain.write_text(text)
    packed = tmp_path / "log.clf.gz"
    with gzip.open(packed, "wt") as fh:
        fh.write(text)
    for path in (plain, packed):
        scans = list(read_carmen(path, range_max=81.9))
        assert [s.stamp for s in scans] == [10.0, 11.0, 42.5]
        assert math.isclose(scans[0].angle_min, -math.pi / 2)
        assert math.isclose(scans[0].angle_min + 180 * scans[0].angle_increment, math.pi / 2)
        assert scans[2].ranges[0] == 3.0 and math.isclose(scans[2].angle_increment, 0.0174533)
        assert scans[0].odom == (1.0, 2.0, 0.5)


@pytest.mark.parametrize("beams, step_degrees", [(181, 1.0), (180, 1.0), (361, 0.5), (360, 0.5)])
def test_a_flaser_lines_beams_are_a_lasers_steps_from_the_right(
    tmp_path: Path, beams: int, step_degrees: float
) -> None:
    # An odd count spans -90..+90 degrees inclusive; an even one cannot at a laser's step, and
    # takes 180/n degree steps from -90 as GMapping does, which corrected the logs we score with
    # (docs/decisions/006-real-lasers-extraction-and-refusal.md).
    path = tmp_path / "log.clf"
    path.write_text(_flaser_line([2.0] * beams, 1.0))
    (scan,) = read_carmen(path)
    assert math.isclose(scan.angle_min, -math.pi / 2)
    assert math.isclose(scan.angle_increment, math.radians(step_degrees))


def test_a_cut_or_inconsistent_carmen_line_is_skipped_with_one_warning_naming_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # a logger that crashed mid-line, and a line that declares 181 ranges and holds 300
    path = tmp_path / "bad.clf"
    good = [_flaser_line([2.0] * 181, float(t)) for t in range(3)]
    overfull = f"FLASER 181 {' '.join(['2.0'] * 300)} 1 2 0.5 1 2 0.5 9.0 host 9.0\n"
    path.write_text(good[0] + overfull + good[1] + good[2] + "FLASER 181 1.0 2.0")
    with caplog.at_level(logging.WARNING):
        scans = list(read_carmen(path))
        again = list(read_carmen(path))  # read twice (a source does): still one warning a line
    assert [s.stamp for s in scans] == [s.stamp for s in again] == [0.0, 1.0, 2.0]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2, warnings
    assert "bad.clf:2" in warnings[0] and "declares 181 ranges but holds" in warnings[0]
    assert "bad.clf:5" in warnings[1] and "cut short" in warnings[1]


def test_a_carmen_log_whose_laser_lines_are_all_bad_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "bad.clf"
    path.write_text("FLASER 181 1.0 2.0\nFLASER x\n")
    with pytest.raises(BadInput, match=r"bad.clf: none of its 2 laser lines can be read"):
        list(read_carmen(path))


def test_carmen_reader_rejects_a_file_without_laser_lines(tmp_path: Path) -> None:
    path = tmp_path / "odom.clf"
    path.write_text("ODOM 0 0 0 0 0 0 1 host 1\n")
    with pytest.raises(BadInput, match="not a CARMEN laser log"):
        list(read_carmen(path))


def test_ranges_jsonl_reader_accepts_null_as_no_return_and_names_bad_fields(tmp_path: Path) -> None:
    good = {"stamp": 1.5, "angle_min": -1.0, "angle_increment": 0.01, "range_max": 8.0, "ranges": [1.0, None, 2.0]}
    path = tmp_path / "scans.jsonl"
    path.write_text(json.dumps(good) + "\n\n" + json.dumps({**good, "angle_increment": "x"}) + "\n")
    reader = read_ranges_jsonl(path)
    first = next(reader)
    assert first.stamp == 1.5 and math.isnan(first.ranges[1])
    with pytest.raises(BadInput, match=r"scans.jsonl:3: field 'angle_increment'"):
        next(reader)
