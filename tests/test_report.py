"""The session report: what it scores, against the scenario's ground truth."""

from __future__ import annotations

import json

import numpy as np
from fleetmap.scenarios import load_scenario
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.messages import Component, FleetEvent, GlobalMap, RobotPose, Scan

from fleetmap.report import SessionLog, build_report, make_truth, summary_table


def test_a_map_merged_wrongly_outside_the_largest_component_is_reported() -> None:
    truth = make_truth(load_scenario("department"))
    assert truth is not None
    log = SessionLog()
    firsts = {("r1", 0): 0, ("r2", 0): 0, ("r3", 0): 0, ("r3", 1): 12}
    for (robot, epoch), first in firsts.items():
        log.add(FleetEvent("epoch", robot, 0.0, json.dumps({"epoch": epoch, "first_scan": first})))

    def frame(robot: str, epoch: int) -> Transform2D:
        pose = truth.scan_pose(robot, firsts[(robot, epoch)])
        assert pose is not None
        return pose

    walls = np.asarray(truth.scenario.world.walls)[:5]
    right = Component(
        "r1/0",
        ("r1/0", "r2/0"),
        {"r1/0": Transform2D(), "r2/0": frame("r1", 0).inverse().compose(frame("r2", 0))},
        frame("r1", 0).inverse().apply(walls),
    )
    # r3's two epochs merged 3.5 m off, in a smaller component: the map error, which scores the
    # largest component only, cannot see it.
    off = frame("r3", 0).inverse().compose(frame("r3", 1)).compose(Transform2D(3.5, 0.0, 0.0))
    wrong = Component("r3/0", ("r3/0", "r3/1"), {"r3/0": Transform2D(), "r3/1": off}, walls)
    log.add(GlobalMap(1, 1.0, (right, wrong)))
    report = build_report(log, truth)
    assert report["maps_merged_wrongly"] == ["r3/1"]
    assert "maps merged wrongly 1 (r3/1)" in summary_table(report)
    # Merged right, it is not listed.
    log.add(GlobalMap(2, 2.0, (right,)))
    assert build_report(log, truth)["maps_merged_wrongly"] == []


def test_a_kidnapped_robot_is_relocalized_only_once_it_is_back_in_the_fleets_map() -> None:
    # A pose of the kidnapped robot's new epoch placed only beside another robot's maps, in a
    # smaller component, is not the robot found again (warehouse-events' r1, placed with the
    # crashed r4 alone, was counted relocalized): only its first pose in the largest component is.
    truth = make_truth(load_scenario("department-events"))
    assert truth is not None
    (kidnap,) = [e for e in truth.scenario.events if e.kind == "kidnap"]
    log = SessionLog()
    period = 0.2
    first_new = None
    for index in range(120):
        stamp = index * period
        epoch = 0 if stamp < kidnap.t else 1
        if epoch == 1 and first_new is None:
            first_new = index
        log.add(Scan(kidnap.robot, epoch, index, stamp, np.zeros((0, 4))))
    assert first_new is not None
    main = Component("r2/0", ("r2/0", "r3/0"), {"r2/0": Transform2D(), "r3/0": Transform2D()}, np.zeros((0, 4)))
    aside = Component(
        f"{kidnap.robot}/1",
        (f"{kidnap.robot}/1", "r4/0"),
        {f"{kidnap.robot}/1": Transform2D(), "r4/0": Transform2D()},
        np.zeros((0, 4)),
    )
    beside = (first_new + 5) * period
    log.add(GlobalMap(1, beside, (main, aside)))
    log.add(RobotPose(kidnap.robot, 1, beside, Transform2D(), 1))
    assert not build_report(log, truth)["kidnaps"][0]["relocalized"]
    # joined to the fleet's map 10 scans later: relocalized then
    back = (first_new + 15) * period
    joined = Component(
        "r2/0",
        (*main.members, f"{kidnap.robot}/1", "r4/0"),
        {**main.poses, f"{kidnap.robot}/1": Transform2D(), "r4/0": Transform2D()},
        np.zeros((0, 4)),
    )
    log.add(GlobalMap(2, back, (joined,)))
    log.add(RobotPose(kidnap.robot, 1, back, Transform2D(), 0))
    (found,) = build_report(log, truth)["kidnaps"]
    assert found["relocalized"] and found["scans_to_relocalize"] == 16, found
