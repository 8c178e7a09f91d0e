"""Robot plans: scans along the path at the set spacing and period, cut and moved by events."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fleetmap.scenarios.fleet import plan, sample_motion, sample_path, scenario_end
from fleetmap.scenarios.loader import list_scenarios, load_scenario, read_scenario
from fleetmap.scenarios.metrics import coverage, visible_walls
from fleetmap.scenarios.odometry import OdometryParams, simulate_odometry

WriteScenario = Callable[..., Path]


def test_scans_are_spaced_along_the_path_and_look_along_it() -> None:
    s = sample_path([(0.0, 0.0), (3.0, 0.0), (3.0, 2.0)], 1.0)
    np.testing.assert_allclose(s.poses[:, :2], [[0, 0], [1, 0], [2, 0], [3, 0], [3, 1], [3, 2]], atol=1e-12)
    np.testing.assert_allclose(s.poses[:, 2], [0, 0, 0, math.pi / 2, math.pi / 2, math.pi / 2])
    assert sample_path([(0.0, 0.0), (1.0, 1.0)], 1.0, heading=2.0).poses[0, 2] == 2.0


def test_a_robot_scans_every_period_from_its_start_until_it_leaves(scenario_file: WriteScenario) -> None:
    sc = read_scenario(scenario_file())
    r2 = plan(sc, "r2")  # starts at 1, period 1, leaves at 5: scans at 1, 2, 3, 4
    assert [s.stamp for s in r2] == [1.0, 2.0, 3.0, 4.0] and [s.index for s in r2] == [0, 1, 2, 3]
    assert r2[1].pose.distance(r2[0].pose)[0] == pytest.approx(0.8)


def test_a_kidnap_teleports_the_robot_at_its_time(scenario_file: WriteScenario) -> None:
    sc = read_scenario(scenario_file())
    r1 = plan(sc, "r1")  # period 0.5, kidnapped at t = 4 to (20, 1.2, 3.14)
    before = [s for s in r1 if s.leg == 0]
    after = [s for s in r1 if s.leg == 1]
    assert before[-1].stamp == 3.5 and after[0].stamp == 4.0 and after[0].index == before[-1].index + 1
    assert (after[0].pose.x, after[0].pose.y, after[0].pose.theta) == pytest.approx((20.0, 1.2, 3.14))
    assert after[-1].pose.x == pytest.approx(12.0, abs=1.0) and len(after) == 9  # 8 m at 1 m spacing
    assert scenario_end(sc) == pytest.approx(after[-1].stamp)


def test_the_default_scenarios_robots_see_enough_of_each_other_to_merge() -> None:
    # Each pair of robots on the department loop shares a long stretch of seen walls.
    sc = load_scenario("department")
    seen = {r.id: visible_walls(sc.world.walls, [s.pose for s in plan(sc, r.id)], sc.laser) for r in sc.robots}
    for a in seen:
        for b in seen:
            if a != b:
                assert coverage(seen[a], seen[b]) > 0.4, (a, b)


@pytest.mark.parametrize("name", [n for n in list_scenarios() if load_scenario(n).kidnaps()])
def test_a_kidnapped_robot_drives_into_what_other_robots_have_seen(name: str) -> None:
    # Relocalization is possible: within 10 scans of the kidnap, most of what the robot sees has
    # been seen by another robot.
    sc = load_scenario(name)
    for kidnap in sc.kidnaps():
        others = [s.pose for r in sc.robots if r.id != kidnap.robot for s in plan(sc, r.id)]
        mapped = visible_walls(sc.world.walls, others, sc.laser)
        after = [s for s in plan(sc, kidnap.robot) if s.stamp >= kidnap.t][:10]
        shared = [coverage(mapped, visible_walls(sc.world.walls, [s.pose], sc.laser)) for s in after]
        assert max(shared) > 0.7, (name, shared)


def test_a_robot_turns_on_the_spot_at_its_turn_rate_scanning_as_it_turns() -> None:
    # 1 m/s (0.2 m every 0.2 s), a quarter turn at 1.5 rad/s: about 1 s on the spot, 5 scans
    s = sample_motion([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)], 0.2, 0.2, 1.5)
    headings = s.poses[:, 2]
    turns = np.abs(np.diff(headings))
    assert turns.max() <= 1.5 * 0.2 + 1e-9, "no turn between two scans beyond the rate"
    on_the_spot = [
        k for k in range(len(s.poses)) if np.allclose(s.poses[k, :2], [1.0, 0.0]) and 0 < headings[k] < math.pi / 2
    ]
    assert len(on_the_spot) == 5
    assert s.poses[-1, :2] == pytest.approx([1.0, 1.0], abs=0.2) and headings[-1] == pytest.approx(math.pi / 2)
    # with no turn rate: the next leg's heading at once, between two scans
    assert sample_motion([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)], 0.2, 0.2, 0.0).poses.shape == (11, 3)


def test_odometry_drifts_a_few_per_cent_and_does_not_see_a_kidnap(scenario_file: WriteScenario) -> None:
    sc = read_scenario(scenario_file())
    planned = plan(sc, "r1")
    odometry = simulate_odometry(planned, OdometryParams(), sc.seed, "r1")
    assert odometry == simulate_odometry(planned, OdometryParams(), sc.seed, "r1"), "seeded"
    kidnap = next(k for k, s in enumerate(planned) if s.leg == 1)
    assert odometry[kidnap] == odometry[kidnap - 1], "carried: the wheels did not turn"
    before = planned[:kidnap]
    true = before[0].pose.inverse().compose(before[-1].pose)
    measured = odometry[0].inverse().compose(odometry[kidnap - 1])
    path = sum(a.pose.distance(b.pose)[0] for a, b in itertools.pairwise(before))
    off = measured.distance(true)[0]
    assert 0.01 * path < off < 0.5 * path, (off, path)
    assert simulate_odometry(planned, OdometryParams(enabled=False), sc.seed, "r1") == [None] * len(planned)
