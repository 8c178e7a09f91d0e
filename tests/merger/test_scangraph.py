"""Key scans registered on the submaps they revisit: merged submaps a few centimetres off, and the
placed scans' poses refined back to where their scans say."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from fleetmap.merger.engine import Merger
from fleetmap.merger.scangraph import (
    SCAN_KEY_ROTATION,
    SCAN_KEY_SPACING,
    IntegrationEdge,
    KeyScan,
    follow_key_scans,
    is_key,
    refine_key_scans,
)
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.tracking import SAMPLE_SPACING, sample_segments
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import Scan

# an L-shaped room, counter-clockwise: every wall's left side is the room
CORNERS = [(0.0, 0.0), (10.0, 0.0), (10.0, 4.0), (6.0, 4.0), (6.0, 7.0), (0.0, 7.0)]
ROOM = np.array([[*CORNERS[i], *CORNERS[(i + 1) % len(CORNERS)]] for i in range(len(CORNERS))])
TRACKING = TrackingParams()


def seen_from(pose: Transform2D) -> np.ndarray:
    """The room's walls that face a laser at ``pose`` (world), in the laser's frame."""
    d = ROOM[:, 2:4] - ROOM[:, 0:2]
    left = np.column_stack([-d[:, 1], d[:, 0]])
    middle = 0.5 * (ROOM[:, 0:2] + ROOM[:, 2:4])
    facing = ((np.array([pose.x, pose.y]) - middle) * left).sum(axis=1) > 0
    return pose.inverse().apply(ROOM[facing])


def key(robot: str, index: int, submap: str, frame: Transform2D, truth: Transform2D) -> KeyScan:
    """A key scan taken at ``truth`` (world), placed by tracking exactly in its submap at ``frame``."""
    samples = sample_segments(seen_from(truth), SAMPLE_SPACING)
    return KeyScan(robot, 0, index, submap, frame.inverse().compose(truth), samples)


@pytest.mark.parametrize("with_a_lie", [False, True])
def test_key_scans_a_merge_left_centimetres_off_go_back_to_where_their_scans_say(with_a_lie: bool) -> None:
    """With ``with_a_lie``, one more key scan of b was taken 0.3 m and 3 degrees from where its
    tracking says (a slip): its fit pulls, and the others stay where their scans say."""
    a_frame = Transform2D(0.0, 0.0, 0.0)
    b0 = Transform2D(2.0, 1.0, 0.3)
    link = Transform2D(2.5, 0.5, 0.4)
    b1 = b0.compose(link)
    a_truth = [
        Transform2D(2.2, 1.3, 0.0),
        Transform2D(4.0, 2.0, 0.2),
        Transform2D(3.0, 4.5, 1.0),
        Transform2D(7.5, 2.0, 0.0),
    ]
    b0_truth = [Transform2D(2.0, 1.0, 0.3), Transform2D(3.5, 2.0, 0.5), Transform2D(4.2, 2.4, 0.6)]
    b1_truth = [b1, Transform2D(3.2, 5.0, 1.4), Transform2D(7.0, 2.2, -0.2)]
    keys = [key("a", i, "a/0/0", a_frame, t) for i, t in enumerate(a_truth)]
    keys += [key("b", i, "b/0/0", b0, t) for i, t in enumerate(b0_truth)]
    keys += [key("b", 10 + i, "b/0/1", b1, t) for i, t in enumerate(b1_truth)]
    if with_a_lie:
        said, taken = Transform2D(5.0, 2.6, 0.7), Transform2D(5.25, 2.45, 0.75)
        lie = key("b", 5, "b/0/0", b0, taken)
        keys.append(KeyScan("b", 0, 5, "b/0/0", b0.inverse().compose(said), lie.samples))
    # the merge put b's submaps a few centimetres and a degree off, and its integration says the same
    merged = {
        "a/0/0": a_frame,
        "b/0/0": b0.compose(Transform2D(0.05, -0.04, 0.015)),
        "b/0/1": b1.compose(Transform2D(-0.04, 0.05, -0.02)),
    }
    walls = {k: f.inverse().apply(ROOM) for k, f in (("a/0/0", a_frame), ("b/0/0", b0), ("b/0/1", b1))}
    wrong = merged["b/0/0"]
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    refined = refine_key_scans(
        keys,
        merged,
        "a/0/0",
        walls,
        {"b/0/1": ("b/0/0", link)},
        [IntegrationEdge("a/0/0", "b/0/0", wrong, noise, noise)],
        TRACKING,
    )
    assert refined.constraints >= 4
    for k, truth in zip(keys[len(a_truth) : len(a_truth) + 6], b0_truth + b1_truth, strict=True):
        before = merged[k.submap].compose(k.pose)
        after = refined.poses[(k.robot, k.index)]
        assert math.hypot(before.x - truth.x, before.y - truth.y) > 0.03  # the merge left it off ...
        assert math.hypot(after.x - truth.x, after.y - truth.y) < 0.01  # ... and it is back
        assert abs(math.remainder(after.theta - truth.theta, 2 * math.pi)) < math.radians(0.3)
    anchor = refined.poses[("a", 0)]
    assert (anchor.x, anchor.y, anchor.theta) == pytest.approx((2.2, 1.3, 0.0), abs=1e-9)

    # a scan between two key scans follows the one before it
    between = Transform2D(3.9, 2.3, 0.55)
    placed = {("b", 1): ("b/0/0", merged["b/0/0"].compose(b0.inverse().compose(between)))}
    followed = follow_key_scans(placed, keys, refined.poses, merged)[("b", 1)]
    assert math.hypot(followed.x - between.x, followed.y - between.y) < 0.01


def test_without_a_revisit_nothing_moves() -> None:
    """A robot's key scans that revisit no other submap keep the merge's poses (its chain holds
    them; nothing joins them to the anchor but the integration they came with)."""
    frame = Transform2D(1.0, 1.0, 0.0)
    keys = [key("a", 0, "a/0/0", frame, frame), key("a", 1, "a/0/0", frame, Transform2D(2.5, 1.2, 0.1))]
    poses = {"a/0/0": frame}
    refined = refine_key_scans(keys, poses, "a/0/0", {"a/0/0": frame.inverse().apply(ROOM)}, {}, [], TRACKING)
    assert refined.constraints == 0
    for k in keys:
        p, q = refined.poses[(k.robot, k.index)], frame.compose(k.pose)
        assert (p.x, p.y, p.theta) == pytest.approx((q.x, q.y, q.theta), abs=1e-9)


def test_a_key_scan_every_metre_or_turn() -> None:
    assert is_key(None, Transform2D())
    assert not is_key(Transform2D(), Transform2D(0.5, 0.0, 0.1))
    assert is_key(Transform2D(), Transform2D(SCAN_KEY_SPACING, 0.0, 0.0))
    assert is_key(Transform2D(), Transform2D(0.0, 0.0, -SCAN_KEY_ROTATION))


def test_a_mapping_merger_keeps_one_scan_per_metre_of_each_submap_off_the_scan_key() -> None:
    keys = FleetKeys("test")
    merger, live = Merger(keys, keep_key_scans=True), Merger(keys)
    wall = np.array([[1.0, -1.0, 1.0, 1.0]])
    for i in range(30):  # 3 m at 0.1 m a scan, in submap 0
        scan = Scan("r1", 0, i, 0.1 * i, wall, submap=0, pose=Transform2D(0.1 * i, 0.0, 0.0))
        merger.receive(keys.scan("r1"), scan.to_msgpack())
        live.receive(keys.scan("r1"), scan.to_msgpack())
    assert merger.stats.key_scans == 3  # at 0, 1.0 and 2.0 m
    assert live.stats.key_scans == 0  # a live merger that never refines keeps none
    # a scan of submap 1, one not placed, one on another key: only the first is kept
    merger.receive(keys.scan("r1"), Scan("r1", 0, 30, 3.0, wall, submap=1, pose=Transform2D()).to_msgpack())
    merger.receive(keys.scan("r1"), Scan("r1", 0, 31, 3.1, wall).to_msgpack())
    merger.receive(keys.localmap("r1"), Scan("r1", 0, 50, 5.0, wall, submap=2, pose=Transform2D()).to_msgpack())
    assert merger.stats.key_scans == 4 and merger.stats.ignored == 1
