"""Known start poses (Dugarjav & Lee 2015, Section III): robots placed from their first submaps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fleetmap.merger.engine import Merger
from fleetmap.merger.startposes import relative_prior
from fleetmap.shared.config import FleetmapConfig, MergeParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import GlobalMap, LocalMap, RobotPose, decode

KEYS = FleetKeys("test")

ROOMS = {
    "r1": [[0.0, 0.0, 6.0, 0.0], [6.0, 0.0, 6.0, 4.0], [6.0, 4.0, 0.0, 4.0], [0.0, 4.0, 0.0, 1.5]],
    "r2": [[0.0, 0.0, 3.0, 0.0], [3.0, 0.0, 3.0, 7.0], [3.0, 7.0, 1.0, 9.0]],
    "r3": [[0.0, 0.0, 5.0, 1.0], [5.0, 1.0, 5.0, 5.0]],
}
"""Three robots' first submaps, walls that share nothing (no integration places one on another)."""


def _first_submap(robot: str) -> LocalMap:
    return LocalMap(robot, 0, 0, 1.0, np.array(ROOMS[robot]), 5, Transform2D(1.0, 0.5, 0.2))


def test_robots_with_start_poses_are_one_map_from_their_first_submaps() -> None:
    # (about 0.1 s) r1 and r2 start 30 m apart, their maps have met nowhere yet; r3 gave no start pose
    start = {"r1": Transform2D(2.0, 1.0, 0.3), "r2": Transform2D(-25.0, 14.0, -2.0)}
    merger = Merger(KEYS, start_poses=start)
    for robot in ("r1", "r2", "r3"):
        merger.receive(KEYS.localmap(robot), _first_submap(robot).to_msgpack())
    out = [decode(o.payload) for o in merger.step()]
    gmap = next(m for m in out if isinstance(m, GlobalMap))
    placed = gmap.components[0]
    assert set(placed.members) == {"r1/0/0", "r2/0/0"}
    # where their start poses put them, each relative to the other
    found = placed.poses["r1/0/0"].inverse().compose(placed.poses["r2/0/0"])
    dt, dr = found.distance(start["r1"].inverse().compose(start["r2"]))
    assert dt < 1e-6 and dr < 1e-9
    # both robots' poses are given (a robot alone in the largest map would be too; r2 is not alone)
    poses = {m.robot: m for m in out if isinstance(m, RobotPose)}
    assert poses["r1"].pose is not None and poses["r2"].pose is not None
    assert poses["r1"].component == poses["r2"].component == 0
    assert poses["r3"].pose is None


def test_a_restored_merger_keeps_the_start_poses(tmp_path) -> None:  # type: ignore[no-untyped-def]
    start = {"r1": Transform2D(0.0, 0.0, 0.0), "r2": Transform2D(30.0, 0.0, 1.0)}
    merger = Merger(KEYS, start_poses=start)
    for robot in ("r1", "r2"):
        merger.receive(KEYS.localmap(robot), _first_submap(robot).to_msgpack())
    merger.step()
    merger.save_state(tmp_path / "state")
    restored = Merger(KEYS, start_poses=start)
    restored.load_state(tmp_path / "state")
    assert restored.result is not None and set(restored.result.components[0].members) == {"r1/0/0", "r2/0/0"}


def test_the_prior_between_two_start_poses_grows_with_the_hub_s_heading_error() -> None:
    hub, other = Transform2D(1.0, 2.0, 0.5), Transform2D(11.0, 2.0, 0.5)
    t, covariance = relative_prior(hub, other, 1.0, 0.1)
    assert t.distance(hub.inverse().compose(other))[0] < 1e-12
    # 10 m off the hub's heading: 10 m x 0.1 rad more across the line between them than along it
    across = np.array([-math.sin(-0.5), math.cos(-0.5), 0.0])  # the world's y in the hub's frame
    assert across @ covariance @ across == pytest.approx(2.0 + 100.0 * 0.01)
    assert covariance[2, 2] == pytest.approx(2 * 0.01)
    assert np.linalg.eigvalsh(covariance).min() > 0


def test_a_start_pose_without_uncertainty_is_refused_by_name() -> None:
    config = FleetmapConfig(merge=MergeParams(start_pose_sigma_translation=0.0))
    with pytest.raises(BadInput, match="start_pose_sigma_translation"):
        Merger(KEYS, config, start_poses={"r1": Transform2D()})


def test_an_integration_between_two_robots_is_judged_as_a_join_not_let_in_by_their_start_poses() -> None:
    # (about 0.1 s) one valid integration puts r2 5 m from where the start poses say, well within what
    # a 1 m / 5 degree prior allows over 30 m: taken as a loop closure through the start poses, it would
    # move r2 there unjudged (the warehouse: a robot an aisle off); judged as a join, one pair of
    # submaps is not enough to bear it out, and the start poses hold
    from fleetmap.merger.graph import Edge
    from fleetmap.merger.posegraph import PoseGraph
    from fleetmap.merger.startposes import StartFrame
    from fleetmap.shared.core.segmap import SegmentMap

    start = {"r1": Transform2D(0.0, 0.0, 0.0), "r2": Transform2D(30.0, 0.0, 0.0)}
    graph = PoseGraph()
    frame = StartFrame(start, MergeParams())
    for robot in ("r1", "r2"):
        graph.put_map(f"{robot}/0/0", SegmentMap(np.array(ROOMS[robot]), ordered=False, oriented=True))
        frame.enter(graph, f"{robot}/0/0")
    wrong = Edge("r1/0/0", "r2/0/0", Transform2D(25.0, 0.0, 0.0), 30.0, True)
    graph.add_edge(wrong)
    result = graph.solve()
    assert result.poses["r1/0/0"] is not None and result.poses["r2/0/0"] is not None
    found = result.poses["r1/0/0"].inverse().compose(result.poses["r2/0/0"])
    assert found.distance(start["r2"])[0] < 1e-6
    assert wrong.key() in {e.key() for e in result.rejected}
