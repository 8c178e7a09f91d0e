"""A robot's submaps chained into one map per epoch by their links (the merger's view of an epoch)."""

from __future__ import annotations

import numpy as np
from fleetmap.merger.epochs import EpochMaps
from fleetmap.shared.geometry import Transform2D
from fleetmap.shared.messages import LocalMap, SubmapLink

COVARIANCE = (1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-6)
WALL = np.array([[0.0, -1.0, 4.0, -1.0]])
STEP = Transform2D(2.0, 0.0, 0.5)
"""Each submap's frame in the previous one's."""


def submap(k, version=0, stamp=1.0, pose=None, final=False):
    link = SubmapLink(k - 1, STEP, COVARIANCE) if k else None
    views = np.array([[0.0, 0.0, 0.0, -1.5, 1.5]])
    return LocalMap("r1", 0, version, stamp, WALL, 3, pose, None, views, submap=k, final=final, link=link)


def test_an_epochs_submaps_are_placed_by_their_chained_links():
    epochs = EpochMaps()
    for k in range(3):
        assert epochs.put(submap(k, stamp=float(k), pose=Transform2D(0.5, 0.0, 0.0)))
    built = epochs.epoch("r1", 0)
    step = STEP
    assert built.submap_poses == {0: Transform2D(), 1: step, 2: step.compose(step)}
    np.testing.assert_allclose(built.segments[2], step.compose(step).apply(WALL)[0])
    np.testing.assert_allclose(built.viewpoints[1, :3], [2.0, 0.0, 0.5])
    # the robot is where the newest submap says, and the stamp is that message's
    assert built.pose == step.compose(step).compose(Transform2D(0.5, 0.0, 0.0)) and built.stamp == 2.0


def test_a_submap_whose_predecessor_is_missing_waits():
    epochs = EpochMaps()
    epochs.put(submap(0))
    epochs.put(submap(2, pose=Transform2D()))
    built = epochs.epoch("r1", 0)
    assert set(built.submap_poses) == {0} and len(built.segments) == 1
    assert built.pose is None, "the newest pose is in a submap not chained yet"
    assert epochs.epoch("r1", 1) is None


def test_an_older_version_is_not_kept_and_a_finished_submap_leaves_the_pose_to_the_active_one():
    epochs = EpochMaps()
    epochs.put(submap(0, version=2, stamp=3.0, pose=Transform2D(1.0, 0.0, 0.0)))
    assert not epochs.put(submap(0, version=1, stamp=4.0, pose=Transform2D(9.0, 0.0, 0.0)))
    epochs.put(submap(1, version=0, stamp=5.0, pose=Transform2D(0.2, 0.0, 0.0)))
    epochs.put(submap(0, version=3, stamp=5.0, final=True))  # finished: no robot in it
    built = epochs.epoch("r1", 0)
    assert built.pose == Transform2D(2.0, 0.0, 0.5).compose(Transform2D(0.2, 0.0, 0.0))
    assert [m.version for m in epochs.messages()] == [3, 0]
