"""The agent's tracking on a real laser log, scored with the log's own relations."""

from __future__ import annotations

import itertools
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from fleetmap.agents.agent import Agent
from fleetmap.agents.pose_free import stepped
from fleetmap.scenarios.clocks import break_clock
from fleetmap.scenarios.crowd import walk_people
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Transform2D, wrap_scalar
from fleetmap.shared.core.motion import CHI2_3DOF_99
from fleetmap.shared.io.logs import read_carmen
from fleetmap.shared.io.messages import LocalMap, Scan
from fleetmap.shared.io.sources import CarmenSource

from fleetmap.config_args import preset
from fleetmap.mapping import Piece, map_logs, read_inputs
from tests.helpers import steps_between_off, steps_off, tracked

TURN = (1134865028.0, 1134865040.0)
"""mit-csail's last turn (about 90 degrees a second), where one scan's odometry is 14 degrees off."""


@pytest.mark.slow  # tracks half of a real log (about 30 s)
def test_a_fast_turn_whose_odometry_is_off_is_tracked_within_the_logs_relations(datasets: Path) -> None:
    # The odometry's own uncertainty on the turn is 20 degrees, and the registration started from
    # it found no minimum; the constant-velocity prediction 14 degrees away, skipped as "within
    # the odometry's uncertainty", does. Skipped, the scan slid from the robot standing still into
    # a minimum 3.5 degrees off, and the turn's scans came out 2-4 degrees apart.
    piece = read_inputs([str(datasets / "mit-csail" / "mit-csail.clf.gz")], 2, range_max=81.91)[1]
    agent = Agent(piece.robot, FleetmapConfig(), odometry=piece.has_odometry)
    poses: dict[int, Transform2D] = {}
    for s in piece.scans:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        if agent.epoch_pose is not None and TURN[0] <= s.stamp <= TURN[1]:
            poses[round(s.stamp * 1e4)] = agent.epoch_pose
    errors = []
    for t1, t2, x, y, _z, _r, _p, yaw in np.loadtxt(datasets / "relations" / "mit-csail.relations"):
        a, b = poses.get(round(t1 * 1e4)), poses.get(round(t2 * 1e4))
        if a is None or b is None:
            continue
        e = Transform2D(x, y, yaw).inverse().compose(a.inverse().compose(b))
        errors.append(
            (
                round(float(t1), 1),
                round(float(t2), 1),
                round(math.hypot(e.x, e.y), 3),
                round(math.degrees(abs(e.theta)), 2),
            )
        )
    assert len(errors) >= 20, "the turn's relations were not tracked"
    off = [e for e in errors if e[2] >= 0.10 or e[3] >= 2.0]
    assert not off, f"relations off on the turn (t1, t2, m, deg): {off}"


@pytest.mark.slow  # maps 400 scans of a real log twice (about 40 s)
def test_a_real_log_restamped_in_bursts_maps_as_one_component_within_5cm_of_its_true_clock(
    datasets: Path, tmp_path: Path
) -> None:
    # Groups of 2-4 scans stamped within 2 ms, the odometry read at those stamps (issue 48): the
    # tracker took the stamps at their word and started an epoch every few scans.
    source = CarmenSource(datasets / "mit-csail" / "mit-csail.clf.gz", range_max=81.91, stop=400)
    scans = list(source)
    maps = {}
    for clock in ("true", "burst"):
        given = list(break_clock(scans, clock, seed=7))
        piece = Piece("csail", str(source.path), given, True, {s.index: s.stamp for s in given})
        maps[clock] = (piece, map_logs([piece], tmp_path / clock, preset("offline")))
    piece, burst = maps["burst"]
    [robot] = burst.report["map"]["robots"]
    assert robot["epochs"] == 1 and robot["scans_placed"] == len(scans)
    assert burst.report["map"]["components"] == 1
    assert robot["clock"]["stamps_trusted"] is False, "report.json says the stamps were not the scans' times"
    assert robot["clock"]["bursts"] > 0 and robot["clock"]["odometry_spread"] > 0, "and that they came in bursts"
    assert maps["true"][1].report["map"]["robots"][0]["clock"]["stamps_trusted"] is True
    # the same scan's pose in both maps, where its broken stamp names it alone
    true_piece, true_map = maps["true"]
    by_stamp = {stamp: pose for _, stamp, _, pose in true_map.poses}
    true_pose = {index: by_stamp[stamp] for index, stamp in true_piece.stamps.items() if stamp in by_stamp}
    counts = Counter(piece.stamps.values())
    index_of = {stamp: index for index, stamp in piece.stamps.items() if counts[stamp] == 1}
    off = []
    for _, stamp, _, pose in burst.poses:
        if stamp in index_of:
            off.append(pose.distance(true_pose[index_of[stamp]])[0])
    assert len(off) >= 0.8 * len(scans)
    assert max(off) < 0.05, f"{sum(d >= 0.05 for d in off)} scans 5 cm or more apart, the worst {max(off):.3f} m"


@pytest.mark.slow  # tracks 60 real scans (about 2 s)
def test_a_log_with_a_scan_a_metre_does_not_slide_along_its_corridors(datasets: Path) -> None:
    # aces logged with a scan about every metre: on some scans the odometry's and the velocity's
    # fits turn alike but lie 1.3-1.5 m apart along a corridor, which the walls leave free; the
    # better-scoring one was taken, and the scan came out a metre off its neighbours
    path = datasets / "corrected" / "aces-corrected.log.gz"
    piece = read_inputs([str(path)], 1)[0]
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]  # the corrected poses, by scan
    agent = Agent(piece.robot, FleetmapConfig(), odometry=piece.has_odometry)
    poses: dict[int, Transform2D] = {}
    for s in piece.scans[:60]:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    errors = {}
    for i in range(59):
        if i in poses and i + 1 in poses:
            error = truth[i].inverse().compose(truth[i + 1]).inverse().compose(poses[i].inverse().compose(poses[i + 1]))
            errors[i] = round(math.hypot(error.x, error.y), 2)
    assert len(errors) >= 55
    assert max(errors.values()) < 0.5, errors


@pytest.mark.slow  # tracks 120 scans of a real log, searching wide windows (about 10 s)
def test_a_sparse_log_without_odometry_is_placed_where_the_walls_support_it_best(datasets: Path) -> None:
    # freiburg-101-corrected without odometry: a scan every 2.6 s, so constant velocity predicts a
    # window metres wide; registered from the prediction alone, scans 2, 3 and 12 settled 1.1-1.7 m
    # from their true steps, in minima nearest a guess
    agent, poses, off = _first_scans_without_odometry(datasets / "corrected" / "freiburg-101-corrected.log.gz", 120)
    assert agent.counts.epochs == 1
    assert sorted(poses) == list(range(120)), f"unplaced: {sorted(set(range(120)) - set(poses))}"
    assert not off, f"steps 0.3 m or more off their truth (m, deg), by scan: {off}"


@pytest.mark.slow  # tracks 120 scans of a real log, searching wide windows (about 5 s)
def test_a_turn_into_new_space_without_odometry_is_placed_where_a_turned_start_finds_it(datasets: Path) -> None:
    # acapulco-corrected without odometry: at scan 77 the robot stops turning (30 degrees a scan
    # for two scans, then 6) and drives into space its submap barely holds; constant velocity
    # turns on, 23 degrees off, and its fit fails. Starts turned across the heading found the
    # true pose (0.04 m off), but at half the robot's typical score it was refused, and scans
    # 77-85 started a false epoch
    path = datasets / "corrected" / "acapulco-corrected.log.gz"
    agent, poses, off = _first_scans_without_odometry(path, 120, max_deg=3.0, range_max=math.inf)
    assert agent.counts.epochs == 1
    assert 77 in poses and 78 in poses
    assert not off, f"steps 0.3 m or 3 degrees or more off their truth (m, deg), by scan: {off}"


@pytest.mark.slow  # tracks 26 scans of a real log, searching wide windows (about 5 s)
def test_scans_with_too_little_wall_to_be_placed_start_no_epoch_without_odometry(datasets: Path) -> None:
    # freiburg-campus-corrected without odometry, scans 1040-1065: the robot crosses open ground,
    # and 1051-1059 see 0.1-0.5 m of wall each, less than any fit must match. Held as scans that
    # fit nowhere, they started ten epochs, each from a scan its successors could not fit on
    path = datasets / "corrected" / "freiburg-campus-corrected.log.gz"
    agent = Agent("r1", FleetmapConfig(), odometry=False)
    published: dict[int, Scan] = {}
    for s in CarmenSource(path, start=1040, stop=1066, range_max=math.inf):
        published |= {m.index: m for m in agent.add_scan(s.index, s.stamp, s.scan, s.odometry) if isinstance(m, Scan)}
    assert agent.counts.epochs == 1
    assert all(published[i].pose is None and published[i].epoch == 0 for i in range(1051, 1060))


@pytest.mark.slow  # tracks 25 scans of a real log, searching wide windows (about 3 s)
def test_a_weak_fit_of_the_motion_models_gives_way_to_a_reacquired_one_that_outscores_it(datasets: Path) -> None:
    # edmonton-corrected without odometry, scans 75-100: scan 94 turns 18 degrees a metre on;
    # constant velocity's fit scores 1.86 (0.5 m off), under the robot's typical floor (5.03), and
    # so does the scan re-acquired by pose-free integration (4.49, 0.1 m off). Kept because the
    # re-acquired fit was not typical, the weak one was searched about and slid 1.4 m on
    agent, poses, off = _first_scans_without_odometry(
        datasets / "corrected" / "edmonton-corrected.log.gz", 100, start=75
    )
    assert agent.counts.epochs == 1
    assert 94 in poses and 93 in poses
    assert not off, f"steps 0.3 m or more off their truth (m, deg), by scan: {off}"


@pytest.mark.slow  # tracks 25 scans of a real log, searching wide windows (about 3 s)
def test_a_corridor_whose_doors_repeat_is_tracked_where_the_prediction_weighs_its_minima(datasets: Path) -> None:
    # orebro-corrected without odometry, scans 105-130: a corridor logged a scan a metre, whose
    # doors repeat about every two metres. The prediction's window holds two minima that support
    # the scan alike (scan 111: 9.28 m of wall at the prediction, 9.30 two metres back); taken by
    # score alone, scans 111, 117 and 121 were placed 1.9-2.4 m back and the next ones forward
    path = datasets / "corrected" / "orebro-corrected.log.gz"
    agent, poses, off = _first_scans_without_odometry(path, 130, range_max=math.inf, start=105, max_m=0.5)
    assert agent.counts.epochs == 1
    assert sorted(poses) == list(range(105, 130)), f"unplaced: {sorted(set(range(105, 130)) - set(poses))}"
    assert not off, f"steps 0.5 m or more off their truth (m, deg), by scan: {off}"


def _first_scans_without_odometry(
    path: Path,
    stop: int,
    max_deg: float = math.inf,
    range_max: float | None = None,
    start: int = 0,
    max_m: float = 0.3,
) -> tuple[Agent, dict[int, Transform2D], dict[int, tuple[float, float]]]:
    """A corrected log's scans ``[start:stop]`` (its first ``stop``, by default) tracked as one robot
    without odometry (its beams read up to ``range_max``: the log's own, by default): the agent, the
    placed scans' epoch poses by index, and the steps between consecutive placed scans ``max_m``
    or ``max_deg`` degrees or more off the corrected poses' (m, deg), by the later scan."""
    agent = Agent("r1", FleetmapConfig(), odometry=False)
    poses: dict[int, Transform2D] = {}
    source = (
        CarmenSource(path, start=start, stop=stop)
        if range_max is None
        else CarmenSource(path, start=start, stop=stop, range_max=range_max)
    )
    for s in source:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    off = {}
    for i in range(start, stop - 1):
        if i in poses and i + 1 in poses:
            error = truth[i].inverse().compose(truth[i + 1]).inverse().compose(poses[i].inverse().compose(poses[i + 1]))
            if math.hypot(error.x, error.y) >= max_m or abs(math.degrees(error.theta)) >= max_deg:
                off[i + 1] = (round(math.hypot(error.x, error.y), 2), round(math.degrees(error.theta), 1))
    return agent, poses, off


def _tracked_stretch(path: Path, start: int, stop: int) -> tuple[list[Transform2D], dict[int, Transform2D]]:
    """A corrected log's scans ``[start:stop]`` tracked as one robot, in one epoch: the corrected
    poses (by scan) and the tracked ones."""
    agent = Agent("r1", FleetmapConfig())
    poses: dict[int, Transform2D] = {}
    for s in CarmenSource(path, start=start, stop=stop):
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    assert agent.counts.epochs == 1
    return [Transform2D(*s.odometry) for s in read_carmen(path)], poses


@pytest.mark.slow  # tracks 28 real scans (about 3 s)
def test_a_registration_the_coarse_stage_carries_off_is_taken_from_the_fine_stage_at_its_prediction(
    datasets: Path,
) -> None:
    # freiburg-101-corrected from scan 73 (where the log cut in 4 starts its second robot): scan
    # 93, a metre and 24 degrees from scan 92, is predicted right by its odometry, but the
    # registration's coarse stage matched its walls to their neighbours a metre away and it settled
    # 7 degrees and 0.23 m off; the rest of the robot's track bent with it (38 wrong relations)
    truth, poses = _tracked_stretch(datasets / "corrected" / "freiburg-101-corrected.log.gz", 73, 101)
    errors = {}
    for i in range(73, 100):
        error = truth[i].inverse().compose(truth[i + 1]).inverse().compose(poses[i].inverse().compose(poses[i + 1]))
        errors[i + 1] = (round(math.hypot(error.x, error.y), 3), round(math.degrees(error.theta), 1))
    off = {i: e for i, e in errors.items() if e[0] >= 0.10 or abs(e[1]) >= 2.0}
    assert not off, f"steps off their truth (m, deg), by scan: {off}"


@pytest.mark.slow  # tracks a real log of 440 scans (about 4 s)
def test_readings_spread_within_bursts_never_turn_the_odometry_round(datasets: Path) -> None:
    # aces-corrected stamped in bursts: a burst's readings but its last are spread between two
    # readings, and a turn in place spread as a share of the burst's drive read as steps the walls
    # contradicted, or stops; judged as measurements they turned the odometry's sign, and the robot
    # was placed driving backwards down corridors (scans 199-200, 271, 361-364: up to 5.5 m)
    path = datasets / "corrected" / "aces-corrected.log.gz"
    agent = Agent("r1", FleetmapConfig())
    poses: dict[int, Transform2D] = {}
    for s in break_clock(CarmenSource(path), "burst"):
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    agent.finish()
    poses.update({index: pose for index, _, pose in agent.tracked if pose is not None})
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    backwards = {}
    for i in range(len(truth) - 1):
        if i not in poses or i + 1 not in poses:
            continue
        true, placed = truth[i].inverse().compose(truth[i + 1]), poses[i].inverse().compose(poses[i + 1])
        length = math.hypot(true.x, true.y)
        along = (true.x * placed.x + true.y * placed.y) / length if length > 0.5 else 0.0
        if along < -0.3:
            backwards[i + 1] = round(along, 2)
    assert agent.counts.epochs == 1
    assert not backwards, f"steps placed backwards (m along the true step), by scan: {backwards}"


@pytest.mark.slow  # tracks 800 scans of a real log (about 10 s)
def test_an_odometry_reading_over_a_sigma_off_is_searched_across_two_sigma(datasets: Path) -> None:
    # freiburg-079-corrected's fourth quarter: scan 4386's odometry is 8 degrees off with a sigma
    # of 7; searched over one sigma, no turned start was tried, and an atypical fit 10 degrees off
    # was taken (the robot's loop then closed 11 degrees off: 819 wrong relations cut in 4)
    truth, poses = _tracked_stretch(datasets / "corrected" / "freiburg-079-corrected.log.gz", 3594, 4400)
    turned = {}
    for i in range(4380, 4400):
        error = truth[4380].inverse().compose(truth[i]).inverse().compose(poses[4380].inverse().compose(poses[i]))
        turned[i] = round(math.degrees(error.theta), 1)
    assert all(abs(t) < 3.0 for t in turned.values()), f"heading off scan 4380's, by scan: {turned}"


@pytest.mark.slow  # tracks a stretch of a real log (about 3 s)
def test_a_robot_reversing_down_a_corridor_on_odometry_without_its_sign_is_placed_where_it_went(
    datasets: Path,
) -> None:
    # freiburg-079-corrected's odometry adds up the wheels' speed without its sign (as fr079's own
    # does, but with no speed in the log to tell): from scan 1372 the robot reverses 2.5 m down a
    # corridor while its odometry drives forward, and the walls there cannot say which way it went
    path = datasets / "corrected" / "freiburg-079-corrected.log.gz"
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    _, poses = track_stretch(path, 1340, 1400)
    moved = truth[1372].inverse().compose(truth[1395])
    assert moved.x < -2.0  # backwards, in the robot's own frame
    error = moved.inverse().compose(poses[1372].inverse().compose(poses[1395]))
    assert math.hypot(error.x, error.y) < 0.2, f"{math.hypot(error.x, error.y):.2f} m off"


@pytest.mark.slow  # tracks 20 scans of a real log (about 2 s)
def test_a_robot_whose_wheels_measured_a_turn_is_not_placed_where_it_would_have_stood(datasets: Path) -> None:
    # csail-corrected cut in 8: robot 2 starts at scan 51 and turns 62 degrees into new space at
    # its third scan. The odometry's fit matched too little wall to be good, and a start where
    # the robot stood found 1.8 m of wall 104 degrees from the turn the wheels measured: its
    # first two scans came out 104-111 degrees from the rest of its chain.
    path = datasets / "corrected" / "csail-corrected.log.gz"
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    agent, poses = track_stretch(path, 51, 71)
    assert agent.counts.epochs == 1
    off = []
    for i, j in itertools.combinations(sorted(poses), 2):
        relation = truth[i].inverse().compose(truth[j])
        if math.hypot(relation.x, relation.y) > 2.0:
            continue  # (the benchmark's relations: scans within 2 m)
        error = relation.inverse().compose(poses[i].inverse().compose(poses[j]))
        if math.hypot(error.x, error.y) > 1.0 or abs(math.degrees(error.theta)) > 10.0:
            off.append((i, j, round(math.degrees(error.theta))))
    assert len(poses) >= 18 and not off, f"wrong relations (scan, scan, degrees off): {off}"


@pytest.mark.slow  # tracks 40 scans of a real log (about 2 s)
def test_a_robot_that_turned_in_place_drives_on_the_way_its_wheels_say(datasets: Path) -> None:
    # freiburg-campus-corrected cut in 4: robot 4 starts at scan 1506, turns in place at scans
    # 1521-1526 (its first stop: either sign of the odometry as likely), then drives a metre a
    # scan along a row of posts. A 7 cm step read as the other sign, the odometry's reversed
    # prediction settled on the posts 2 m back, and eight scans went backwards: 8 m off.
    poses, truth = campus_stretch(datasets, 1506, 1546)
    steps = [(i, truth[i].inverse().compose(truth[i + 1])) for i in range(1506, 1545) if i in poses and i + 1 in poses]
    errors = {i: relation.inverse().compose(poses[i].inverse().compose(poses[i + 1])) for i, relation in steps}
    off = {i: round(math.hypot(e.x, e.y), 2) for i, e in errors.items() if math.hypot(e.x, e.y) > 0.3}
    assert len(poses) >= 36 and not off, f"steps off (scan: metres): {off}"


@pytest.mark.slow  # tracks 44 scans of a real log (about 3 s)
def test_a_fit_a_post_from_where_the_wheels_say_is_refused_where_the_scans_returns_side_with_the_wheels(
    datasets: Path,
) -> None:
    # freiburg-campus-corrected, scans 218-262: a wall and a row of posts about a metre apart, a
    # scan a metre. The walls fitted scans 231 and 244 a post from where the odometry said, beyond
    # its 99 % gate (0.65 and 0.49 m off the step; 10 steps off in all), and the scan pair's returns
    # side with the wheels: the odometry carries them (docs/decisions/088)
    poses, truth = campus_stretch(datasets, 218, 262)
    errors = {
        i: truth[i - 1].inverse().compose(truth[i]).inverse().compose(poses[i - 1].inverse().compose(poses[i]))
        for i in range(219, 262)
        if i - 1 in poses and i in poses
    }
    off = {i: round(math.hypot(e.x, e.y), 2) for i, e in errors.items() if math.hypot(e.x, e.y) > 0.3}
    assert len(errors) >= 40, "the stretch was not tracked"
    assert not {231, 244} & set(off) and len(off) <= 7, f"steps off (scan: metres): {off}"


@pytest.mark.slow  # tracks 30 scans of a real log (about 2 s)
def test_where_the_odometry_fits_nothing_the_other_motion_models_are_weighed_by_the_walls(datasets: Path) -> None:
    # freiburg-campus-corrected, scan 1168: the robot slows to 0.64 m and turns 4 degrees, its
    # odometry reads 13 degrees, and the walls refuse its fit. Constant velocity (1.1 m ahead) and
    # standing still are the models left, equally unsure of the step (1.5 m, 177 degrees): the walls
    # fit the scan near where the robot stood at twice the score of the velocity's fit 1.5 m ahead,
    # which was taken for being tried first, 0.85 m off
    poses, truth = campus_stretch(datasets, 1140, 1170)
    errors = {
        i: truth[i].inverse().compose(truth[i + 1]).inverse().compose(poses[i].inverse().compose(poses[i + 1]))
        for i in range(1160, 1169)
    }
    off = {i: round(math.hypot(e.x, e.y), 2) for i, e in errors.items() if math.hypot(e.x, e.y) > 0.3}
    assert not off, f"steps off (scan: metres): {off}"


@pytest.mark.slow  # tracks 35 scans of a real log (about 3 s)
def test_a_turn_in_place_the_walls_cannot_place_is_measured_by_the_scans_returns(datasets: Path) -> None:
    # freiburg-campus-corrected, scans 1168-1182: the robot turns about 110 degrees in place among
    # posts and hedges. Its scans hold under a metre of wall each, the walls place none, and the
    # robot is carried; by its odometry, which over-reads the turn (13-16 degrees a step for 7-8),
    # the heading ended 20 degrees off and stayed 12 off. The scans' returns measure each step
    # (docs/decisions/083): the turn comes out within a few degrees
    poses, truth = campus_stretch(datasets, 1148, 1183)
    turned = truth[1166].inverse().compose(truth[1182])
    tracked = poses[1166].inverse().compose(poses[1182])
    assert abs(math.degrees(turned.theta)) > 90.0  # (the stretch is the turn)
    off = turned.inverse().compose(tracked)
    assert abs(math.degrees(off.theta)) < 3.0 and math.hypot(off.x, off.y) < 0.5, off


@pytest.mark.slow  # tracks 16 scans of a real log (about 2 s)
def test_down_a_corridor_logged_a_scan_every_metres_the_scans_own_integration_measures_the_step(
    datasets: Path,
) -> None:
    # orebro-corrected, scans 22-37, no odometry: a corridor logged a scan every 1-3 m. Constant
    # velocity is a guess 1.5 m wide there, and registration from it slid to where the robot had
    # stood (2-4.5 m short a step at scans 27-36); the velocity it measured then predicted the next
    # step short too. Each scan integrated on the one before measures the step (the pivot method's).
    # One pair is wrong and valid: 27 -> 28 integrates 1.7 m behind the robot, its value 12.45
    # against 9.46 where the robot drove, 3 m ahead, and nothing in the two scans says otherwise
    path = datasets / "corrected" / "orebro-corrected.log.gz"
    agent, poses = track_stretch(path, 22, 38, odometry=False)
    truth = [Transform2D(*s.odometry) for s in itertools.islice(read_carmen(path), 38)]
    assert agent.counts.epochs == 1
    off = {}
    for i in range(26, 37):
        assert i in poses and i + 1 in poses, f"scan {i} or {i + 1} not placed"
        step = truth[i].inverse().compose(truth[i + 1])
        error = step.distance(poses[i].inverse().compose(poses[i + 1]))[0]
        if error > 0.3:
            off[i] = round(error, 2)
    assert set(off) <= {27}, f"steps off (scan: metres): {off}"


@pytest.mark.slow  # tracks a real log of 237 scans with people in view (about 15 s)
def test_a_step_the_scan_pair_measured_carries_the_robot_where_people_hide_the_walls(datasets: Path) -> None:
    # orebro-corrected with five people walking past its robot (odometry on 18 of its 237 scans):
    # where the people hide the walls the submap's fit is no evidence either way, but the scan still
    # integrates on the one before. Its step carries the robot, as odometry would have; dropped, the
    # robot was predicted by constant velocity, fitted nothing for five scans and started over.
    # A new epoch is a conclusion: only where nothing the robot saw links the first scan it holds
    # to the last it placed (at 59 it enters a room, the people hide 58's view, and no pair of
    # 56-58 with 59-66 integrates right: record 048)
    path = datasets / "corrected" / "orebro-corrected.log.gz"
    scans = list(walk_people(CarmenSource(path, range_max=math.inf), 5))
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    agent = Agent("r1", FleetmapConfig())
    epochs: dict[int, tuple[int, Transform2D]] = {}
    for s in scans:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        epochs.update({index: (epoch, pose) for index, epoch, pose in agent.tracked if pose is not None})
    firsts = [i for i in sorted(epochs) if i - 1 in epochs and epochs[i][0] != epochs[i - 1][0]]
    config = FleetmapConfig()
    segments = {s.index: extract_segments(s.scan, config.extraction) for s in scans}
    for first in firsts:
        last = max(i for i in epochs if i < first and epochs[i][0] != epochs[first][0])
        step = stepped(segments[last], segments[first], 10.0, config.integration)
        assert step is None, f"a new epoch at scan {first}, though it integrates on scan {last}"
    assert len(firsts) <= 2, f"new epochs at scans {firsts}"
    steps = [i for i in range(len(truth) - 1) if i in epochs and i + 1 in epochs and epochs[i][0] == epochs[i + 1][0]]
    assert len(steps) > 0.9 * (len(truth) - 1), f"{len(steps)} of {len(truth) - 1} steps placed"
    errors = [
        truth[i].inverse().compose(truth[i + 1]).distance(epochs[i][1].inverse().compose(epochs[i + 1][1]))[0]
        for i in steps
    ]
    assert np.median(errors) < 0.10, np.median(errors)


@pytest.mark.slow  # tracks 61 scans of a real log (about 5 s)
def test_the_step_is_measured_from_a_scan_the_walls_placed_not_one_carried(datasets: Path) -> None:
    # orebro-corrected from scan 119 (the second robot when the log is cut in two): scan 171 is
    # carried (the walls placed nothing). Scan 172 integrated on it takes the corridor turned
    # round (135 degrees against the true -46, valid within the robot's reach, and the submap's
    # walls bear it out at a typical score), and the robot was tracked 180 degrees off from there.
    # Integrated on scan 170, the last scan the walls placed, it is right
    off = orebro_steps_off(datasets, 119, 180, 150)
    assert not off, f"steps off (scan: metres, degrees): {off}"


@pytest.mark.slow  # tracks 21 scans of a real log (about 3 s)
def test_a_weak_fit_from_a_turned_start_does_not_overrule_the_step_the_scan_pair_measured(datasets: Path) -> None:
    # orebro-corrected from scan 45: scan 59 turns 30 degrees into a room a second after 58, its
    # odometry chain broken there. The scan pair measures the turn within 0.15 m and a degree, but
    # the submap holds only 2 m of the room's wall, too little to place the scan. A start turned
    # 92 degrees from it found 2.7 m of wall (a typical fit here finds 4 m or more), and was taken:
    # the rest of the map ran turned by as much (a loop of relations 30 m and 90 degrees wrong)
    off = orebro_steps_off(datasets, 45, 66, 58)
    assert not off, f"steps off (scan: metres, degrees): {off}"


@pytest.mark.slow  # tracks 32 scans of a real log, searching turned windows (about 5 s)
def test_a_turn_a_metre_aside_without_odometry_is_found_by_a_window_searched_at_every_heading(datasets: Path) -> None:
    # orebro-corrected from scan 190 (no wheel reading from 212 on): scan 216 is 1.9 m on and 24
    # degrees round from 215, where constant velocity put it 1.2 m short, its heading unknown. No
    # start turned at the prediction reached the fit at the true step (score 2.6, the robot's
    # usual 3.8); one turned 128 degrees fitted at 1.6 and was taken, and the log's end ran turned
    # round (mapped whole, 15 relations 20-24 m and 150 degrees wrong)
    off = orebro_steps_off(datasets, 190, 222, 210)
    assert not off, f"steps off (scan: metres, degrees): {off}"


@pytest.mark.slow  # tracks 34 scans of a real log, people drawn on the whole of it (about 10 s)
def test_a_scan_no_start_placed_is_searched_at_every_heading_before_it_is_held(datasets: Path) -> None:
    # acapulco-corrected, a scan in ten dropped, five people walking past, no odometry, from scan
    # 280: after a dropped scan the robot turned 60 degrees one way where constant velocity, over
    # the gap, turned it 36 the other; its fit at the true pose is typical (4.17, the robot's
    # floor 3.68), but no start reached it (turned starts search only the predicted position,
    # 2.6 m off). Scans 300-308 were held unplaced; tracked whole, the clock was then doubted
    # and 305 placed 5.2 m and 30 degrees off
    path = datasets / "corrected" / "acapulco-corrected.log.gz"
    scans = list(walk_people(list(CarmenSource(path, range_max=math.inf)), 5))
    given = [s for s in break_clock(scans, "drop", seed=0) if 280 <= s.index < 320]
    agent, poses = tracked(given, odometry=False)
    truth = [Transform2D(*s.odometry) for s in read_carmen(path)]
    assert agent.counts.epochs == 1
    assert [s.index for s in given if s.index not in poses] == []
    off = steps_between_off(truth, poses, itertools.pairwise(s.index for s in given))
    assert not off, f"steps off (scan: metres, degrees): {off}"


@pytest.mark.slow  # tracks 24 scans of a real log, searching their windows (about 3 s)
def test_a_fit_slid_down_a_corridor_whose_beams_pass_through_its_walls_loses_to_the_one_they_bear_out(
    datasets: Path,
) -> None:
    # orebro-corrected from scan 178 (the fourth robot when the log is cut in four; no wheel
    # reading): scan 198 is 2.4 m on, constant velocity put it 1 m on (1.55 m wide). The fit at the
    # true step matched 5.7 m of the scan, the one 1.8 m short 4.0 m while its beams passed through
    # 1.8 m of the submap's walls; weighed by score and prediction alone they tied, the slid one
    # was taken and 199 slid as far again (a corridor 3.6 m short: 13 wrong relations)
    off = orebro_steps_off(datasets, 178, 202, 190)
    assert not off, f"steps off (scan: metres, degrees): {off}"


def orebro_steps_off(datasets: Path, start: int, stop: int, first: int) -> dict[int, tuple[float, float] | str]:
    """orebro-corrected's scans ``start:stop`` tracked as one robot with its odometry (one epoch):
    the steps between consecutive scans from ``first`` on 0.3 m or 3 degrees or more off its
    corrected poses' (m, deg), or not placed, by the later scan."""
    path = datasets / "corrected" / "orebro-corrected.log.gz"
    agent, poses = track_stretch(path, start, stop)
    assert agent.counts.epochs == 1
    truth = [Transform2D(*s.odometry) for s in itertools.islice(read_carmen(path), stop)]
    scans = range(first, stop)
    off: dict[int, tuple[float, float] | str] = {}
    for i in scans[1:]:
        if i - 1 not in poses or i not in poses:
            off[i] = "not placed"
            continue
        dt, dr = truth[i - 1].inverse().compose(truth[i]).distance(poses[i - 1].inverse().compose(poses[i]))
        if dt > 0.3 or math.degrees(dr) > 3.0:
            off[i] = (round(dt, 2), round(math.degrees(dr), 1))
    return off


@pytest.mark.slow  # tracks 70 scans of a real log (about 2 s)
def test_a_campus_stretch_with_little_wall_in_view_is_tracked_as_one_epoch(datasets: Path) -> None:
    # freiburg-campus-corrected, scans 880-950 (about 3 s): outdoors, a scan a metre, most beams
    # returning nothing and consecutive scans sharing 0-0.3 m of wall. The walls say nothing
    # against the odometry there, only nothing for it: the robot is carried by its odometry, not
    # kidnapped (this stretch started 18 epochs when every scan that fitted nothing counted
    # towards a kidnap)
    poses, truth = campus_stretch(datasets, 880, 950)
    assert len(poses) >= 60, f"{len(poses)} of 70 scans placed"
    first = min(poses)
    off = {
        i: round(truth[first].inverse().compose(truth[i]).distance(poses[first].inverse().compose(p))[0], 2)
        for i, p in poses.items()
    }
    assert max(off.values()) < 3.0, off  # about 70 m driven, odometry's drift where nothing fixes the pose


def campus_stretch(datasets: Path, start: int, stop: int) -> tuple[dict[int, Transform2D], list[Transform2D]]:
    """The epoch poses of :func:`track_stretch` on freiburg-campus-corrected, tracked as one epoch,
    and the log's corrected poses up to ``stop``."""
    path = datasets / "corrected" / "freiburg-campus-corrected.log.gz"
    agent, poses = track_stretch(path, start, stop)
    assert agent.counts.epochs == 1
    return poses, [Transform2D(*s.odometry) for s in itertools.islice(read_carmen(path), stop)]


def track_stretch(path: Path, start: int, stop: int, odometry: bool = True) -> tuple[Agent, dict[int, Transform2D]]:
    """Scans ``start:stop`` of a SLAM-corrected log through an agent (with its odometry unless not
    ``odometry``): the agent, and the epoch poses of the scans it placed, by index."""
    return tracked(itertools.islice(CarmenSource(path, range_max=math.inf), start, stop), odometry)


@pytest.mark.slow  # tracks 400 scans of a real log twice (about 10 s)
def test_people_walking_past_a_real_robot_are_no_kidnap_and_cost_no_relation(datasets: Path) -> None:
    # A laser in a lab sees people as well as walls: eight people walking past mit-csail's robot
    # (fleetmap.scenarios.crowd), their legs hiding the walls behind them, in most scans
    scans = list(CarmenSource(datasets / "mit-csail" / "mit-csail.clf.gz", range_max=81.91, stop=400))
    crowded = list(walk_people(scans, 8, seed=3))
    hidden = [int(np.sum(a.scan.ranges != b.scan.ranges)) for a, b in zip(scans, crowded, strict=True)]
    assert np.mean(np.array(hidden) > 0) > 0.8, "people in view of most scans"
    relations = np.loadtxt(datasets / "relations" / "mit-csail.relations")
    within = {}
    for name, given in (("alone", scans), ("people", crowded)):
        agent = Agent("r1", FleetmapConfig())
        poses: dict[int, Transform2D] = {}
        for s in given:
            agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
            poses.update({round(scans[i].stamp * 1e4): pose for i, _, pose in agent.tracked if pose is not None})
        assert agent.counts.epochs == 1, name
        assert len(poses) == len(scans), f"{name}: every scan placed"
        errors = []
        for t1, t2, x, y, _z, _roll, _pitch, yaw in relations:
            a, b = poses.get(round(t1 * 1e4)), poses.get(round(t2 * 1e4))
            if a is not None and b is not None:
                dt, dr = a.inverse().compose(b).distance(Transform2D(x, y, yaw))
                errors.append(dt < 0.10 and math.degrees(dr) < 2.0)
        assert len(errors) > 200
        within[name] = float(np.mean(errors))
    assert within["people"] >= within["alone"] - 0.01, within


@pytest.mark.slow  # tracks 40 scans of a real log (about 4 s)
def test_a_link_across_a_corridor_whose_walls_leave_the_step_open_covers_its_error(datasets: Path) -> None:
    # orebro-corrected, scans 0-40, as `fleetmap map` tracks it: down a corridor logged a scan every
    # 1-3 m, scan 29's window holds minima metres apart along it that the walls support alike, and
    # the tracker may take the wrong one (it slid 4.7 m). The link that spans it must say so: its
    # covariance is the window's spread over those minima, not the peak's curvature (a few cm), so
    # the back end can weigh it against cross-robot evidence (docs/decisions/048)
    path = datasets / "corrected" / "orebro-corrected.log.gz"
    agent, _ = track_stretch(path, 0, 40)
    truth = [Transform2D(*s.odometry) for s in itertools.islice(read_carmen(path), 40)]
    maps = {(m.epoch, m.submap): m for m in agent.republish() if isinstance(m, LocalMap)}
    uncovered = {}
    for (epoch, number), submap in maps.items():
        previous = maps.get((epoch, number - 1))
        if submap.link is None or previous is None:
            continue
        link, true = submap.link.transform, truth[previous.frame_scan].inverse().compose(truth[submap.frame_scan])
        error = np.array([link.x - true.x, link.y - true.y, wrap_scalar(link.theta - true.theta)])
        mahalanobis2 = float(error @ np.linalg.solve(np.reshape(submap.link.covariance, (3, 3)), error))
        if mahalanobis2 > CHI2_3DOF_99:
            uncovered[(previous.frame_scan, submap.frame_scan)] = round(mahalanobis2, 1)
    assert len(maps) >= 6, f"{len(maps)} submaps"
    assert not uncovered, f"links whose error is outside their covariance's 99 % (scans: Mahalanobis^2): {uncovered}"


@pytest.mark.slow  # tracks 100 scans of a real log (about 4 s)
def test_a_turn_without_odometry_is_placed_by_the_scan_pairs_fit_whatever_it_scores(datasets: Path) -> None:
    # freiburg-101-corrected without odometry: scans 60 and 93 end turns, and the scan pair's step
    # fitted each within 0.03 m, but scored under half the robot's typical fit (little of a turned
    # scan is on the submap yet) and was dropped; constant velocity's fit, worse, placed them
    # 0.17-0.23 m and 7 degrees off. The pair's fit stays the first of the fits (record 060)
    path = datasets / "corrected" / "freiburg-101-corrected.log.gz"
    agent, poses = tracked(CarmenSource(path, range_max=math.inf, stop=100), odometry=False)
    truth = [Transform2D(*s.odometry) for s in itertools.islice(read_carmen(path), 100)]
    assert agent.counts.epochs == 1
    off = steps_off(truth, poses, range(50, 100), 0.1, 2.0)
    assert not off, f"steps off by more than 0.1 m or 2 degrees (m, deg): {off}"
