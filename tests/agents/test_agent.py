"""The agent's tracking front end on simulated robots scanning at 5 Hz with drifting odometry: what
it publishes, how close its poses and submaps stay to the truth, and when it starts a new epoch."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace

import numpy as np
import pytest
from fleetmap.agents.agent import Agent
from fleetmap.scenarios import load_scenario, map_error, robot_stream
from fleetmap.scenarios.laser import LaserParams, simulate_scan
from fleetmap.shared.config import FleetmapConfig, TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.messages import FleetEvent, LocalMap, Scan, decode
from fleetmap.shared.io.sources import SourceScan

from tests.agents.conftest import blocked, epoch_events, kidnap_index, run, source_scans


def submaps(messages, epoch=None):
    return [m for m in messages if isinstance(m, LocalMap) and (epoch is None or m.epoch == epoch)]


def track(robot_stream_, agent):
    """Run ``agent`` on a simulated stream; the largest distance (m) and turn (deg) of a placed
    scan from where the truth puts it relative to its epoch's first scan, and the messages."""
    frames: dict[int, Transform2D] = {}
    worst = (0.0, 0.0)
    messages = []
    for s in robot_stream_:
        messages += agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
        pose = agent.epoch_pose
        if pose is None:
            continue
        frame = frames.setdefault(agent.epoch, s.pose.compose(pose.inverse()))
        dt, dr = pose.distance(frame.inverse().compose(s.pose))
        worst = (max(worst[0], dt), max(worst[1], math.degrees(dr)))
    return worst, messages + agent.finish()


@pytest.fixture(scope="module")
def office_r3():
    return list(robot_stream(load_scenario("office"), "r3"))


@pytest.fixture(scope="module")
def office_r3_run(office_r3):
    return track(office_r3, Agent("r3"))


def test_every_scan_is_published_once_in_order_with_its_readings_pose_and_odometry(r2_stream):
    messages = run(Agent("r2"), source_scans(r2_stream))
    scans = [m for m in messages if isinstance(m, Scan)]
    assert [s.index for s in scans] == [s.index for s in r2_stream]
    for sent, simulated in zip(scans, r2_stream, strict=True):
        assert sent.robot == "r2" and sent.epoch == 0 and len(sent.segments) > 0
        np.testing.assert_array_equal(sent.ranges.ranges, simulated.scan.ranges.astype(np.float32))
        assert sent.odometry == simulated.odometry and sent.submap is not None and sent.pose is not None
        assert decode(sent.to_msgpack()).pose == sent.pose  # every message is valid on the wire
    # the first scan is the frame of the epoch's first submap
    assert (scans[0].submap, scans[0].pose) == (0, Transform2D())


@pytest.mark.slow  # tracks a whole simulated path
def test_a_robot_with_drifting_odometry_is_tracked_within_5cm_over_its_whole_path(office_r3, office_r3_run):
    (worst_m, worst_deg), messages = office_r3_run
    assert worst_m < 0.05 and worst_deg < 0.5, (worst_m, worst_deg)
    assert epoch_events(messages) == []
    # the odometry alone drifts by decimetres over the same path: the tracking corrects it
    first, last = office_r3[0], office_r3[-1]
    true = first.pose.inverse().compose(last.pose)
    odometry = first.odometry.inverse().compose(last.odometry)
    assert odometry.distance(true)[0] > 0.3


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_without_odometry_constant_velocity_tracks_the_robot_too(office_r3):
    # (along the office corridor, constant velocity is all that fixes the robot's progress: the
    # error there grows to 4-5 cm, where odometry's stays at 1-2)
    config = replace(FleetmapConfig(), tracking=TrackingParams(odometry="off"))
    (worst_m, worst_deg), messages = track(office_r3, Agent("r3", config))
    assert worst_m < 0.08 and worst_deg < 0.5, (worst_m, worst_deg)
    assert all(m.odometry is not None for m in messages if isinstance(m, Scan)), "still recorded"


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_without_odometry_a_robot_that_starts_down_a_corridor_is_not_placed_as_standing(department):
    # department's r3 sets off along a corridor whose walls fix nothing along it; its second scan,
    # predicted as standing still at its first's pose, was registered there and every later scan
    # followed: the whole track 3.5 m short. Until two placed scans measure it, the robot may be
    # driving at any speed it can
    config = replace(FleetmapConfig(), tracking=TrackingParams(odometry="off"))
    (worst_m, worst_deg), _ = track(list(robot_stream(department, "r3")), Agent("r3", config))
    assert worst_m < 0.15 and worst_deg < 1.0, (worst_m, worst_deg)


def test_submaps_are_bounded_overlap_chain_by_links_and_are_final_once(office_r3, office_r3_run):
    _, messages = office_r3_run
    params = TrackingParams()
    by_submap: dict[int, list[LocalMap]] = {}
    for m in submaps(messages):
        by_submap.setdefault(m.submap, []).append(m)
    assert len(by_submap) >= 5, "the path is cut into several submaps"
    truth = {s.index: s.pose for s in office_r3}
    origin = {0: Transform2D()}
    for k, versions in sorted(by_submap.items()):
        assert [v.version for v in versions] == list(range(len(versions)))
        finals = [v for v in versions if v.final]
        assert finals == versions[-1:], "published final once, as its last version"
        last = versions[-1]
        views = np.asarray(last.viewpoints)
        path = float(np.hypot(*np.diff(views[:, 0:2], axis=0).T).sum())
        assert path <= params.submap_length + 0.5, (k, path)
        if k > 0:
            assert last.link is not None and last.link.submap == k - 1
            origin[k] = origin[k - 1].compose(last.link.transform)
        # every scan the submap placed is where the truth puts it, chained from the epoch's frame
        for index, pose in zip(last.scan_indices, last.scan_poses, strict=True):
            true = truth[0].inverse().compose(truth[int(index)])
            dt, dr = origin[k].compose(Transform2D(*pose)).distance(true)
            assert dt < 0.05 and math.degrees(dr) < 0.5, (k, int(index), dt)
    # consecutive submaps overlap: the next begins before the previous one ends
    for k in sorted(by_submap)[1:]:
        before, after = by_submap[k - 1][-1], by_submap[k][-1]
        if len(after.scan_indices):  # (the last one may have placed nothing yet)
            assert min(after.scan_indices) == max(before.scan_indices) + 1
        first_view = np.asarray(after.viewpoints)[0]
        previous_views = origin[k - 1].inverse().compose(origin[k]).apply_points(first_view[None, 0:2])
        assert np.hypot(*(np.asarray(before.viewpoints)[:, 0:2] - previous_views).T).min() < 1e-6
    # every scan is placed by exactly one submap
    placed = sorted(int(i) for v in by_submap.values() for i in v[-1].scan_indices)
    assert placed == [s.index for s in office_r3]
    # the walls of a submap are one segment per stretch of wall, on the true walls
    world = load_scenario("office").world.walls
    for k, versions in by_submap.items():
        walls = truth[0].compose(origin[k]).apply(np.asarray(versions[-1].segments))
        assert map_error(walls, world).p95 < 0.05, k


def test_a_carried_robot_starts_a_new_epoch_within_a_few_scans(carried, carried_stream, carried_run):
    kidnap = kidnap_index(carried_stream)
    messages = carried_run.messages
    [(said_at, event)] = [(i, m) for i, out in carried_run.steps for m in out if isinstance(m, FleetEvent)]
    [detail] = epoch_events(messages)
    assert event.robot == "r1" and detail["epoch"] == 1 and detail["first_scan"] == kidnap
    assert said_at <= kidnap + TrackingParams().kidnap_after, "within kidnap_after scans"
    # the old epoch's submaps are finished before the event; the new epoch says where it comes from
    old, new = submaps(messages, 0), submaps(messages, 1)
    assert old[-1].final and messages.index(old[-1]) < messages.index(event) < messages.index(new[0])
    assert {(m.previous_epoch_link.epoch, m.previous_epoch_link.transform) for m in new} == {(0, None)}
    # the new epoch's frame is the first scan after the kidnap: its map fits the walls from there
    frame = next(s for s in carried_stream if s.index == kidnap)
    walls = carried.world.walls
    assert map_error(frame.pose.apply(np.asarray(new[-1].segments)), walls).mean < 0.03
    assert {m.epoch for m in messages if isinstance(m, Scan) and m.index > said_at} == {1}


def test_a_featureless_corridor_keeps_odometrys_estimate_along_it():
    # Two walls 2 m apart, 80 m long; the laser (8 m) sees no end. The odometry reads 5 % long.
    walls = np.array([[-40.0, -1.0, 40.0, -1.0], [40.0, 1.0, -40.0, 1.0]])
    laser = LaserParams()
    rng = np.random.default_rng(1)
    scans = []
    for k in range(40):
        x, y = 0.3 * k, 0.02 * math.sin(0.3 * k)
        scan = simulate_scan(walls, (x, y, 0.0), laser, rng, stamp=0.2 * k)
        scans.append(SourceScan(k, 0.2 * k, scan, Transform2D(1.05 * x, 0.0, 0.0)))
    agent = Agent("r1")
    for s in scans:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
    pose = agent.epoch_pose
    assert pose.x == pytest.approx(1.05 * 0.3 * 39, abs=0.02), "along the corridor, odometry's estimate"
    assert pose.y == pytest.approx(0.02 * math.sin(0.3 * 39), abs=0.02) and abs(pose.theta) < math.radians(0.5)
    assert agent.counts.epochs == 1


def test_scans_with_no_return_break_nothing(r2_stream):
    empty = [replace(s, scan=replace(s.scan, ranges=np.full_like(s.scan.ranges, np.inf))) for s in r2_stream[4:10]]
    stream = [*r2_stream[:4], *empty, *r2_stream[10:]]
    (worst_m, _), messages = track(stream, Agent("r2"))
    assert epoch_events(messages) == [] and worst_m < 0.05
    scans = [m for m in messages if isinstance(m, Scan)]
    assert [len(m.segments) for m in scans][4:10] == [0] * 6 and all(m.pose is None for m in scans[4:10])
    assert all(m.pose is not None for m in scans[10:])


def test_a_person_blocking_the_laser_for_a_moment_is_no_kidnap(r2_stream):
    stream = [*r2_stream[:5], *(blocked(s) for s in r2_stream[5:8]), *r2_stream[8:]]
    (worst_m, _), messages = track(stream, Agent("r2"))
    assert epoch_events(messages) == [] and worst_m < 0.05


def test_odometry_that_is_not_a_number_or_jumps_is_ignored_with_a_warning(r2_stream, caplog):
    broken = list(r2_stream)
    broken[6] = replace(broken[6], odometry=Transform2D(math.nan, 0.0, 0.0))
    broken[9] = replace(broken[9], odometry=broken[9].odometry.compose(Transform2D(50.0, 0.0, 0.0)))
    with caplog.at_level(logging.WARNING, logger="fleetmap.agents.tracker"):
        (worst_m, _), messages = track(broken, Agent("r2"))
    assert worst_m < 0.05 and epoch_events(messages) == []
    warned = " ".join(r.getMessage() for r in caplog.records)
    assert "not a finite number" in warned and "jumped" in warned
    sent = [m for m in messages if isinstance(m, Scan)]
    assert sent[6].odometry is None, "a reading that is not a number is not published either"


def test_republish_gives_the_latest_version_of_every_submap_and_finish_the_finals(r2_stream):
    agent = Agent("r2")
    messages = []
    for s in source_scans(r2_stream):
        messages += agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
    latest = {(m.epoch, m.submap): m for m in submaps(messages)}
    again = agent.republish()
    assert [m.to_msgpack() for m in again] == [latest[(m.epoch, m.submap)].to_msgpack() for m in again]
    assert {(m.epoch, m.submap) for m in again} == set(latest)
    finals = agent.finish()
    assert finals and all(m.final and m.pose is None for m in finals)
    assert agent.finish() == []


def test_the_same_scans_give_byte_identical_messages(r2_stream):
    scans = source_scans(r2_stream[:8])
    first = [m.to_msgpack() for m in run(Agent("r2"), scans)]
    second = [m.to_msgpack() for m in run(Agent("r2"), scans)]
    assert first == second and len(first) > 8


def test_the_pivot_front_end_is_selectable_and_publishes_one_local_map_per_epoch(sparse_r2_stream):
    config = replace(FleetmapConfig(), tracking=TrackingParams(front_end="pivot"))
    messages = run(Agent("r2", config), source_scans(sparse_r2_stream[:6]))
    maps = submaps(messages)
    assert maps and all(m.submap == 0 and m.link is None and m.scan_indices is None for m in maps)
    assert maps[-1].scans >= 5


@pytest.mark.parametrize(
    ("tracking", "named"),
    [({"publish_every": 0}, "publish_every"), ({"kidnap_after": 0}, "kidnap_after")],
)
def test_bad_parameters_are_refused_by_name(tracking, named):
    with pytest.raises(BadInput, match=named):
        Agent("r1", replace(FleetmapConfig(), tracking=TrackingParams(**tracking)))
    with pytest.raises(BadInput, match="robot"):
        Agent("R1")


def test_an_epochs_event_says_why(carried_run):
    [detail] = [json.loads(m.detail) for m in carried_run.messages if isinstance(m, FleetEvent)]
    assert "fit neither the submap" in detail["reason"]


@pytest.mark.slow  # a robot's 118 scans (about 2 s): CI runs it with the slow ones
def test_without_odometry_a_corridor_that_fixes_nothing_along_it_leaves_the_robots_speed_unknown():
    # department-16's r4 sets off without odometry down a corridor whose walls fix nothing along
    # it. Its first step, placed where the standing prior put it, measured its speed as 0, and it
    # was placed 0.3 m short every scan until three epochs had begun, with no kidnap. A step is
    # as sure as its placement: along that corridor, as unsure as the prior, the speed unmeasured.
    config = replace(FleetmapConfig(), tracking=TrackingParams(odometry="off"))
    agent = Agent("r4", config)
    stream = list(robot_stream(load_scenario("department-16"), "r4"))
    for s in stream:
        agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
    assert agent.counts.epochs == 1, "no epoch where no kidnap was"
    assert agent.counts.placed == len(stream), "every scan placed"
