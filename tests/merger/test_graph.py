"""Map files merged in an unknown order (the pose graph without links, as ``fleetmap merge`` solves
them): cycle checks, components, incremental use of the map graph."""

from __future__ import annotations

import math
import random
from dataclasses import replace

import numpy as np
import pytest
from fleetmap.merger.graph import Edge, MapGraph
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core import validity
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.pivotmap import PivotMapBuilder
from fleetmap.shared.core.segmap import SegmentMap

from tests.helpers import NORTH_LANE, OMNI, ROOM, scan_map, scenario_scans, set_constant

POSES = [(3.0, 4.5, 0.3), (5.0, 5.0, 2.0), (7.0, 4.0, -1.0), (9.0, 4.0, 2.8), (4.5, 7.0, -2.2)]
MAPS = {f"m{k}": scan_map(ROOM, p, OMNI, seed=40 + k) for k, p in enumerate(POSES)}
TRUE = {f"m{k}": Transform2D(*p) for k, p in enumerate(POSES)}


def _solve(order: list[str], **kw: object) -> tuple[PoseGraph, object]:
    g = PoseGraph(anchor="largest", **kw)  # type: ignore[arg-type]
    for key in order:
        g.add_map(key, MAPS[key])
    return g, g.solve()


def _check_against_truth(result: object) -> None:
    comp = result.components[0]  # type: ignore[attr-defined]
    assert set(comp.members) == set(MAPS)
    world = TRUE[comp.anchor]
    for key, pose in comp.poses.items():
        dt, dr = world.compose(pose).distance(TRUE[key])
        assert dt < 0.05 and dr < math.radians(1), f"{key}: {dt:.3f} m {math.degrees(dr):.2f} deg"


def test_every_map_is_placed_right_with_no_order_given() -> None:
    _, result = _solve(list(MAPS))
    _check_against_truth(result)
    assert result.rejected == []  # type: ignore[attr-defined]


@pytest.mark.slow  # builds maps from many scans: run in CI, deselected by -m "not slow"
def test_the_same_maps_in_any_order_give_the_same_poses() -> None:
    _, first = _solve(list(MAPS))
    for seed in range(3):
        order = list(MAPS)
        random.Random(seed).shuffle(order)
        _, other = _solve(order)
        assert other.components[0].anchor == first.components[0].anchor  # type: ignore[attr-defined]
        for key in MAPS:
            dt, dr = other.poses[key].distance(first.poses[key])  # type: ignore[attr-defined]
            assert dt < 0.01 and dr < math.radians(0.1)


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_the_anchor_a_merger_happens_to_get_does_not_move_the_maps_relative_to_each_other() -> None:
    # The same maps; the anchor is the first map to arrive (a restarted merger may get another).
    # Refined over the cycles (the integrations disagree a little, as measured ones do), the
    # maps' poses relative to each other must not depend on it.
    relative = []
    for order in (["m0", "m1", "m2", "m3"], ["m3", "m2", "m1", "m0"], ["m2", "m0", "m3", "m1"]):
        g = PoseGraph(anchor="first")
        for key in order:
            g.add_map(key, MAPS[key])
        comp = g.solve(fuse_maps=False).components[0]
        assert comp.anchor == order[0] and len(comp.members) == 4
        base = comp.poses["m0"].inverse()
        relative.append({k: base.compose(p) for k, p in comp.poses.items()})
    for other in relative[1:]:
        for key in ("m1", "m2", "m3"):
            dt, dr = other[key].distance(relative[0][key])
            assert dt < 1e-4 and dr < 1e-5, f"{key}: {dt:.2e} m {dr:.2e} rad"


def test_an_injected_wrong_edge_is_rejected_by_the_cycle_check() -> None:
    g, _ = _solve(list(MAPS))
    true_edge = g.edge("m0", "m2")
    assert true_edge is not None and true_edge.valid
    # A wrong integration, more confident than any right one: 2 m and 90 degrees off.
    wrong = Edge("m0", "m2", true_edge.transform.compose(Transform2D(2.0, 0.0, math.pi / 2)), 100.0, True)
    g.add_edge(wrong)
    result = g.solve()
    assert any(e.a == "m0" and e.b == "m2" and e.value == 100.0 for e in result.rejected)
    _check_against_truth(result)


@pytest.mark.slow  # builds and merges maps from many scans: run in CI, deselected by -m "not slow"
def test_maps_with_no_overlap_end_up_in_separate_components() -> None:
    g, _ = _solve(list(MAPS))
    # Another building: an L-shaped room with a pillar, 200 m away.
    other = (
        np.array(
            [
                [0, 0, 9, 0],
                [9, 0, 9, 4],
                [9, 4, 4, 4],
                [4, 4, 4, 8],
                [4, 8, 0, 8],
                [0, 8, 0, 0],
                [2, 5, 2.5, 5],
                [2.5, 5, 2.5, 5.5],
                [2.5, 5.5, 2, 5.5],
                [2, 5.5, 2, 5],
                [6, 0, 7, 1.0],
            ],
            dtype=float,
        )
        + 200
    )
    g.add_map("far1", scan_map(other, (202.0, 202.0, 0.0), OMNI, seed=1))
    g.add_map("far2", scan_map(other, (203.0, 201.5, 1.4), OMNI, seed=2))
    result = g.solve()
    groups = sorted(sorted(c.members) for c in result.components)
    assert groups == sorted([sorted(MAPS), ["far1", "far2"]])
    far = result.component_of("far1")
    assert far is not None and far.anchor in ("far1", "far2")


def test_known_pairs_are_not_integrated_again_and_removal_forgets_a_map() -> None:
    g, _ = _solve(list(MAPS)[:3])
    before = {e.key(): e for e in g.edges}
    new = g.add_map("m3", MAPS["m3"])
    assert {e.key() for e in new} == {("m0", "m3"), ("m1", "m3"), ("m2", "m3")}
    assert all(g.edge(*k) == e for k, e in before.items())  # untouched
    g.remove_map("m1")
    assert "m1" not in g and all("m1" not in e.key() for e in g.edges)
    assert set(g.solve().components[0].members) == {"m0", "m2", "m3"}


def test_the_first_anchor_stays_put_as_maps_are_added() -> None:
    g = PoseGraph(anchor="first")
    g.add_map("m2", MAPS["m2"])
    g.add_map("m0", MAPS["m0"])
    pose_m0 = g.solve().poses["m0"]
    for key in ("m1", "m3", "m4"):
        g.add_map(key, MAPS[key])
        result = g.solve()
        assert result.components[0].anchor == "m2"
        dt, dr = result.poses["m0"].distance(pose_m0)  # type: ignore[union-attr]
        assert dt < 0.02 and dr < math.radians(0.3)


def _local_map(scans: list[tuple[float, SegmentMap, Transform2D]]) -> SegmentMap:
    builder = PivotMapBuilder()
    for stamp, m, _ in scans:
        builder.add(m, stamp)
    return builder.map


@pytest.mark.slow  # builds two local maps from 20 simulated scans (about 5 s)
def test_a_lane_map_is_not_merged_a_rack_off_when_free_space_refutes_the_other_aliases(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # NORTH_LANE (a warehouse-events variant): r2 maps the north lane westward from
    # x = 34 m (scans 0-13); r1, carried there, maps it from x = 20 m on (scans 21-26), past the
    # forklift's bay. A rack (3.5 m) off, r1's map matches more wall than where it belongs (it
    # slides over more of r2's) and puts none where r2 saw through; the aliases 10 and 14 m off
    # are refuted by the free space. The right alignment, clean but matching less, must still
    # count as a rival: the lane is ambiguous.
    lane_scans = scenario_scans(NORTH_LANE, "r2", 14)
    r1_scans = scenario_scans(NORTH_LANE, "r1", 28)[21:27]
    lane, part = _local_map(lane_scans), _local_map(r1_scans)
    truth = lane_scans[0][2].inverse().compose(r1_scans[0][2])
    edges = {}
    for refute in (0.0, validity.VALID_REFUTE_VIOLATION):
        with monkeypatch.context() as m:
            set_constant(m, validity, "VALID_REFUTE_VIOLATION", refute)
            g = PoseGraph(IntegrationParams())
            g.add_map("r2/0", lane)
            g.add_map("r1/1", part)
            edges[refute] = g.edge("r2/0", "r1/1")
    with_refuting, without = edges[validity.VALID_REFUTE_VIOLATION], edges[0.0]
    assert with_refuting is not None and without is not None
    assert truth.distance(with_refuting.transform)[0] > 3.0, "the best is the alias a rack off: the test shows nothing"
    assert with_refuting.runner_up < without.runner_up, "no rival was refuted: the test shows nothing"
    # Still ambiguous, so not merged: the right alignment is among the rivals, and scores more
    # than half the best.
    assert not with_refuting.valid and with_refuting.runner_up > 0.5 * with_refuting.value
    assert g.solve().poses["r1/1"] is None


@pytest.mark.slow  # builds two local maps from 27 simulated scans (about 5 s)
def test_an_office_map_is_merged_when_free_space_refutes_its_look_alike_alignments(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # office: r1's last local map (its scans 29-34) and r2's first (scans 0-20). Elsewhere along the
    # corridor r1's map matches 90 % as well, but puts walls where r2's laser saw through: refuted,
    # so the right alignment is unambiguous.
    r1_scans = scenario_scans("office", "r1", 35)[29:]
    r2_scans = scenario_scans("office", "r2", 21)
    truth = r1_scans[0][2].inverse().compose(r2_scans[0][2])
    r1_map, r2_map = _local_map(r1_scans), _local_map(r2_scans)
    for refute, merged in ((validity.VALID_REFUTE_VIOLATION, True), (0.0, False)):
        with monkeypatch.context() as m:
            set_constant(m, validity, "VALID_REFUTE_VIOLATION", refute)
            g = MapGraph(IntegrationParams())
            g.add_map("r1/4", r1_map)
            g.add_map("r2/0", r2_map)
            edge = g.edge("r1/4", "r2/0")
        assert edge is not None and edge.valid == merged, f"refuting at {refute} m: merged {edge and edge.valid}"
        dt, dr = edge.transform.distance(truth)
        assert dt < 0.05 and math.degrees(dr) < 0.5, f"{dt:.3f} m {math.degrees(dr):.2f} deg"


def test_a_new_version_with_the_same_geometry_keeps_its_integrations() -> None:
    # An agent closing an epoch publishes its map once more, only to say the robot left it: the
    # same segments from the same places. Integrating it again would give the same edges.
    g, _ = _solve(["m0", "m1", "m2"])
    before = {e.key(): e for e in g.edges}
    edges = g.add_map("m1", MAPS["m1"], version=1)
    assert {e.key() for e in edges} == {("m0", "m1"), ("m1", "m2")}
    for e in edges:
        kept = before[e.key()]
        versions = (1, kept.versions[1]) if kept.a == "m1" else (kept.versions[0], 1)
        # Not integrated again: the very same edge (its integration time too), at the new version.
        assert g.edge(kept.a, kept.b) == replace(kept, versions=versions)
    # A version whose walls changed is integrated again.
    moved = SegmentMap(MAPS["m1"].segments[:-1], ordered=MAPS["m1"].ordered, oriented=MAPS["m1"].oriented)
    g.add_map("m1", moved, version=2)
    again = [e for e in g.edges if "m1" in e.key()]
    assert len(again) == 2
    assert all(e.versions == ((2, 0) if e.a == "m1" else (0, 2)) for e in again)
    assert all(e.seconds != before[e.key()].seconds for e in again), "not integrated again"


def test_kept_edges_stand_until_integrated_again_and_only_the_repeated_version_moves_on() -> None:
    # The live merger puts a new version in and integrates its pairs over later steps: the old
    # version's edges stand meanwhile (the map stays placed), marked as old.
    g, _ = _solve(["m0", "m1", "m2"])
    before = {e.key(): e for e in g.edges}
    moved = SegmentMap(MAPS["m1"].segments[:-1], ordered=MAPS["m1"].ordered, oriented=MAPS["m1"].oriented)
    assert g.put_map("m1", moved, version=1, keep_edges=True)
    assert {e.key(): e for e in g.edges} == before and not g.is_current("m0", "m1")
    assert g.solve().poses["m1"] is not None
    # Its pair with m0 is integrated again; then a version that repeats the last one's walls
    # moves that edge on, while the edge with m2, still from version 0, stays old.
    assert g.integrate_pair_once("m0", "m1") is not None and g.integrate_pair_once("m0", "m1") is None
    assert g.put_map("m1", moved, version=2, keep_edges=True)
    assert g.is_current("m0", "m1") and not g.is_current("m1", "m2")
    assert g.integrate_pair_once("m1", "m2") is not None and g.is_current("m1", "m2")


def test_a_reversed_edge_says_as_firmly_where_the_other_map_lies() -> None:
    # An edge's information weighs a change of its transform's parameters; the reversed edge's
    # weighs the same change seen from the other map: a corridor left free one way is free the
    # other way too, whatever the turn between the maps.
    rng = np.random.default_rng(5)
    for _ in range(20):
        t = Transform2D(*rng.uniform(-10, 10, 2), rng.uniform(-math.pi, math.pi))
        root = rng.normal(size=(3, 3))
        info = root @ root.T
        edge = Edge("a", "b", t, 20.0, True, information=tuple(info.ravel().tolist()))
        back = edge.reversed()
        assert back.information is not None and back.transform == t.inverse()
        d = rng.normal(scale=1e-4, size=3)
        moved = Transform2D.from_array(back.transform.as_array() + d).inverse()
        change = moved.as_array() - t.as_array()
        change[2] = math.remainder(change[2], 2 * math.pi)
        want = change @ info @ change
        got = d @ np.array(back.information).reshape(3, 3) @ d
        assert got == pytest.approx(want, rel=1e-3)
        assert back.reversed().information == pytest.approx(edge.information)


def test_an_edge_whose_information_is_no_weight_weighs_by_its_value() -> None:
    # Edges come from recordings and state files too: one whose information is NaN or not
    # positive definite must not stop the merge (GTSAM refuses such a noise model); it weighs by
    # value, and every map is placed right.
    g, _ = _solve(list(MAPS))
    edge = g.edge("m0", "m1")
    assert edge is not None and edge.valid
    for bad in ((math.nan,) * 9, (1.0, 0.0, 0.0, 0.0, -1e9, 0.0, 0.0, 0.0, 1.0)):
        g.add_edge(replace(edge, information=bad))
        _check_against_truth(g.solve())
