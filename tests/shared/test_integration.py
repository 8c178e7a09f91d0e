"""INTEGRATE (paper III): known transforms recovered from geometry alone."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from fleetmap.shared.config import IntegrationParams, tuned
from fleetmap.shared.core import candidates, transformation_value, validity
from fleetmap.shared.core.candidates import find_transformations, pairs_consecutive, pairs_histogram
from fleetmap.shared.core.geometry import Transform2D, lengths
from fleetmap.shared.core.integration import Window, integrate
from fleetmap.shared.core.mapgrid import with_viewpoints
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.transformation_value import matched_pairs, prepare, refused, transformation_values
from fleetmap.shared.core.validity import is_valid
from fleetmap.shared.core.work import Work
from fleetmap.shared.errors import BadInput

from tests.helpers import OMNI, ROOM, pose_pair, scan_map, set_constant

TRANS_TOL = 0.02
ROT_TOL = math.radians(0.5)


def room_pairs(n: int, seed: int) -> list[tuple[SegmentMap, SegmentMap, Transform2D]]:
    """n pairs of 360-degree scans of ROOM, 1 cm noise, any rotation, shifts up to 3 m."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a, t = pose_pair(rng)
        b = Transform2D(*a).compose(t)
        out.append(
            (
                scan_map(ROOM, a, OMNI, seed=2 * k + seed),
                scan_map(ROOM, (b.x, b.y, b.theta), OMNI, seed=2 * k + 1 + seed),
                t,
            )
        )
    return out


PAIRS = room_pairs(8, seed=11)


@pytest.mark.parametrize("case", range(len(PAIRS)))
def test_auto_recovers_the_transform_within_2cm_and_half_a_degree(case: int) -> None:
    a, b, truth = PAIRS[case]
    r = integrate(a, b)
    dt, dr = r.transform.distance(truth)
    assert dt < TRANS_TOL and dr < ROT_TOL, f"error {dt:.3f} m {math.degrees(dr):.2f} deg"
    assert r.valid
    assert r.value > 0.3 * min(a.total_length, b.total_length)


def test_rotations_span_the_whole_circle_and_shifts_reach_3m() -> None:
    thetas = [t.theta for _, _, t in room_pairs(30, seed=5)]
    shifts = [math.hypot(t.x, t.y) for _, _, t in room_pairs(30, seed=5)]
    assert min(thetas) < -2.5 and max(thetas) > 2.5 and max(shifts) > 2.4


@pytest.mark.parametrize("heuristic", ["all", "consecutive", "random", "histogram"])
def test_each_heuristic_recovers_most_transforms(heuristic: str) -> None:
    ok = 0
    for a, b, truth in PAIRS[:6]:
        dt, dr = integrate(a, b, heuristic=heuristic).transform.distance(truth)
        ok += dt < TRANS_TOL and dr < ROT_TOL
    assert ok >= 5, f"{heuristic}: {ok}/6"


def test_all_finds_a_superset_of_the_consecutive_transformations() -> None:
    a, b, _ = PAIRS[0]
    p = IntegrationParams(consecutive_touching_only=True)
    cons = find_transformations(a, b, "consecutive", p)
    everything = find_transformations(a, b, "all", p)
    assert len(cons) > 0 and len(everything) > len(cons)
    # Every consecutive transformation is among all's (same angle pairs, same arithmetic).
    d = np.abs(cons[:, None, :] - everything[None, :, :]).max(axis=2).min(axis=1)
    assert d.max() < 1e-9


def test_consecutive_pairs_follow_the_variant() -> None:
    seg = np.array([[0, 0, 1, 0], [1, 0, 1, 1], [1.5, 1, 2.5, 1], [2.5, 1, 2.6, 1.05]], dtype=float)
    m = SegmentMap(seg, ordered=True, oriented=True)
    touching = pairs_consecutive(m, IntegrationParams(consecutive_touching_only=True))
    assert list(zip(*touching, strict=True)) == [(0, 1), (2, 3)]
    improved = pairs_consecutive(m, IntegrationParams(segment_length_percentage=20))
    # The last segment is shorter than 20 % of the longest: it forms no angle.
    assert list(zip(*improved, strict=True)) == [(0, 1), (1, 2)]


def test_histogram_pairs_principal_with_normal_direction_segments() -> None:
    seg = np.array([[0, 0, 4, 0], [0, 1, 3, 1], [0, 0, 0, 2], [1, 1, 2, 2]], dtype=float)
    p, q = pairs_histogram(seg, IntegrationParams(nslots=18))
    assert sorted(zip(p.tolist(), q.tolist(), strict=True)) == [(0, 2), (1, 2)]


def test_random_heuristic_is_reproducible_with_its_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    a, b, _ = PAIRS[1]
    one = find_transformations(a, b, "random", IntegrationParams())
    two = find_transformations(a, b, "random", IntegrationParams())
    set_constant(monkeypatch, candidates, "SEED", candidates.SEED + 1)
    other = find_transformations(a, b, "random", IntegrationParams())
    np.testing.assert_array_equal(one, two)
    assert len(one) > 0 and not (len(one) == len(other) and np.array_equal(one, other))


def test_a_transformation_that_crosses_two_long_walls_is_refused() -> None:
    s1 = np.array([[0.0, -1.0, 0.0, 1.0]])
    s2 = np.array([[-1.0, 0.0, 1.0, 0.0]])
    prep = prepare(s1, s2, True, IntegrationParams())
    crossing = np.array([[0.0, 0.0, 0.0]])
    corner = np.array([[1.0, 1.0, 0.0]])  # s2 moved to end where s1 ends: they touch, not cross
    assert refused(prep, crossing, IntegrationParams())[0]
    assert not refused(prep, corner, IntegrationParams())[0]
    assert transformation_values(prep, crossing, IntegrationParams())[0] == -1.0


def wall_turned(x: float, degrees: float) -> np.ndarray:
    """A 1 m wall across the x axis at ``x``, turned by ``degrees`` about its middle."""
    h = 0.5 * np.array([math.sin(math.radians(degrees)), math.cos(math.radians(degrees))])
    return np.array([[x + h[0], -h[1], x - h[0], h[1]]])


@pytest.mark.parametrize("x, refuses", [(2.0, True), (17.0, False)])
def test_a_far_wall_seen_turned_does_not_refuse_between_scans_but_a_near_one_does(
    x: float, refuses: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The same 1 m wall seen by two scans, its line turned 25 degrees in one (a far wall is fixed by a
    # few sparse points): its ends lie 0.21 m either side of the other's line. Near the sensor that
    # is a crossing; 17 m away it is within what the sparse points can tell (REFUSE_RANGE_SLOPE).
    p = IntegrationParams()
    at = np.zeros((1, 3))
    scans = prepare(wall_turned(x, 0.0), wall_turned(x, 25.0), True, p, scan1=True, scan2=True)
    maps = prepare(wall_turned(x, 0.0), wall_turned(x, 25.0), True, p)
    assert refused(scans, at, p)[0] == refuses
    assert refused(maps, at, p)[0]  # partial maps keep the paper's margin: no sensor to be far from
    set_constant(monkeypatch, transformation_value, "REFUSE_RANGE_SLOPE", 0.0)  # the paper's margin
    assert refused(prepare(wall_turned(x, 0.0), wall_turned(x, 25.0), True, p, True, True), at, p)[0]


def test_early_stop_keeps_the_best_transformation() -> None:
    a, b, _truth = PAIRS[2]
    p = IntegrationParams()
    t = find_transformations(a, b, "histogram", p)
    prep = prepare(a.segments, b.segments, True, p)
    full = transformation_values(prep, t, p)
    best = float(full.max())
    pruned = transformation_values(prep, t, p, best_known=0.9 * best)
    assert int(np.argmax(pruned)) == int(np.argmax(full)) and pruned.max() == best
    assert (pruned == -1).sum() > (full == -1).sum()  # some hopeless candidates were dropped


@pytest.mark.parametrize("oriented", [True, False])
def test_one_transformations_matched_pairs_are_the_same_whether_found_in_one_pass_or_by_rotation(
    oriented: bool,
) -> None:
    # A refinement asks the same two maps for one transformation's pairs dozens of times: after
    # SORT_AFTER asks they come from the pairs sorted by rotation, and must be the very pairs (in
    # the same order, so the sums that follow are the same to the bit) a first ask finds.
    a, b, truth = PAIRS[3]
    p = IntegrationParams()
    rng = np.random.default_rng(11)
    near = truth.as_array() + np.column_stack(
        [rng.normal(0, 0.05, 30), rng.normal(0, 0.05, 30), rng.normal(0, 0.02, 30)]
    )
    anywhere = np.column_stack([rng.uniform(-3, 3, 30), rng.uniform(-3, 3, 30), rng.uniform(-4, 4, 30)])
    asked = prepare(a.segments, b.segments, oriented, p)
    matched = 0
    for t in np.vstack([near, anywhere, near]):
        fresh = matched_pairs(prepare(a.segments, b.segments, oriented, p), t, p)
        again = matched_pairs(asked, t, p)
        for x, y in zip(fresh, again, strict=True):
            assert np.array_equal(x, y)
        matched += len(fresh[0])
    assert "by_rotation" in asked.cache and matched > 100


def test_maps_of_different_places_give_an_invalid_integration() -> None:
    a = scan_map(ROOM, (4.5, 4.5, 0.3), OMNI, seed=1)
    corridor = np.array([[0, 0, 9, 0], [9, 1.8, 0, 1.8], [3, 0, 3, -1], [6, 1.8, 6, 3]], dtype=float)
    b = scan_map(corridor, (4.5, 0.9, 0.0), OMNI, seed=2)
    assert not integrate(a, b).valid


def test_unoriented_maps_are_integrated_too() -> None:
    a, b, truth = PAIRS[3]
    flip = b.segments[:, [2, 3, 0, 1]].copy()
    flip[::2] = b.segments[::2]  # half the segments drawn the other way
    r = integrate(SegmentMap(a.segments), SegmentMap(flip))
    dt, dr = r.transform.distance(truth)
    assert dt < TRANS_TOL and dr < ROT_TOL


@pytest.mark.parametrize(
    "segments, message",
    [
        (np.zeros((0, 4)), "empty"),
        (np.array([[0.0, 0.0, np.nan, 1.0]]), "NaN or infinite"),
        (np.array([[1.0, 1.0, 1.0, 1.0]]), "zero-length"),
    ],
)
def test_bad_maps_are_refused_with_a_clear_error(segments: np.ndarray, message: str) -> None:
    good = PAIRS[0][0]
    with pytest.raises(BadInput, match=message):
        integrate(good, SegmentMap(segments))


def test_two_partial_maps_need_the_map_rule_a_scan_the_scan_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    wall = np.array([[0.0, 0.0, 30.0, 0.0], [0.0, 3.0, 30.0, 3.0]])
    map1, map2 = SegmentMap(wall, ordered=False), SegmentMap(wall + 0.5, ordered=False)
    scan = SegmentMap(wall * [0.2, 1, 0.2, 1], ordered=True)  # 12 m of wall
    p = IntegrationParams()

    def valid(value: float, violation: float, runner_up: float, a: SegmentMap, large: bool = True) -> bool:
        return is_valid(value, violation, runner_up, a, map2, p, large)

    # Between maps: 8 m at least (the paper's right merges ~10 m, wrong ~5 m) ...
    assert valid(12.0, 0.0, 0.0, map1) and not valid(6.0, 0.0, 0.0, map1)
    # ... at most 10 % in the other's seen free space, and no rival within 50 % on the large path
    assert not valid(12.0, 2.0, 0.0, map1)
    # ... or, from 16 m of matched wall on (a large overlap, whose shared walls two maps place a
    # little apart), at most 15 %
    assert valid(20.0, 2.6, 0.0, map1) and not valid(12.0, 1.5, 0.0, map1) and not valid(20.0, 3.4, 0.0, map1)
    assert not valid(12.0, 0.0, 7.0, map1) and valid(12.0, 0.0, 7.0, map1, large=False)
    # A scan on a map is judged by the scan rule: 6 m is half of what the scan saw.
    assert valid(6.0, 0.0, 0.0, scan)
    # Maps that carry their scans' viewpoints must each have been seen from 5 places at least.
    from fleetmap.shared.core.mapgrid import with_viewpoints

    def seen_from(m: SegmentMap, n: int) -> SegmentMap:
        return with_viewpoints(
            m, np.column_stack([np.arange(n, dtype=float), np.zeros((n, 2)), -np.ones(n), np.ones(n)])
        )

    assert valid(12.0, 0.0, 0.0, seen_from(map1, 5)) and not valid(12.0, 0.0, 0.0, seen_from(map1, 4))
    # Without the strong tier, 10 % at any value.
    set_constant(monkeypatch, validity, "VALID_STRONG_MAP_VALUE", 0.0)
    assert not valid(20.0, 2.6, 0.0, map1)


def test_an_ambiguous_match_names_its_rivals_and_a_window_chooses_among_them() -> None:
    # Two consecutive scans of the department hallway (r1, scans 17 and 18): the match one metre
    # further along scores 0.92 of the right one.
    from fleetmap.scenarios import load_scenario, robot_stream
    from fleetmap.shared.config import ExtractionParams
    from fleetmap.shared.core.extraction import extract_segments

    from tests.helpers import sparse

    stream = list(itertools.islice(robot_stream(load_scenario(sparse("department")), "r1"), 17, 19))
    a, b = (SegmentMap(extract_segments(s.scan, ExtractionParams()), ordered=True, oriented=True) for s in stream)
    true = stream[0].pose.inverse().compose(stream[1].pose)
    r = integrate(a, b)
    assert not r.valid, "the pair is ambiguous"
    assert is_valid(r.value, r.violation, 0.0, a, b, IntegrationParams()), "... and valid but for that"
    assert r.transform.distance(true)[0] < 0.05
    rival, score = r.rivals[0]
    assert rival.distance(true)[0] > 0.5 and score == r.runner_up
    at_rival = integrate(a, b, window=Window(rival, 0.3, 0.1))
    assert at_rival.transform.distance(rival)[0] < 0.1
    at_truth = integrate(a, b, window=Window(true, 0.3, 0.1))
    assert at_truth.valid, "inside the window the right match has no rival"
    dt, dr = at_truth.transform.distance(true)
    assert dt < 0.05 and dr < math.radians(1.0)


def test_a_wall_two_maps_place_a_little_apart_does_not_refuse_their_merge_and_changes_nothing_else() -> None:
    # Two robots' local maps of a hall with rooms off it, each seen from six places: the second
    # robot's map has the hall's long wall 0.25 m inward (its scan-to-scan errors added up
    # differently). Seen at a grazing angle, that wall lies metres inside the first map's seen
    # free space; within map_free_space_clearance of the first map's own wall, it is that wall
    # and does not refuse the merge. Only the validity changes: the choice, the value, the
    # violation in the score and the rivals are the same.
    walls = np.array(
        [
            [0, 0, 30, 0], [30, 0, 30, 3], [30, 3, 22, 3], [22, 3, 22, 8], [22, 8, 17, 8], [17, 8, 17, 3],
            [17, 3, 9, 3], [9, 3, 9, 6], [9, 6, 4, 6], [4, 6, 4, 3], [4, 3, 0, 3], [0, 3, 0, 0],
        ],
        dtype=float,
    )  # fmt: skip
    a = with_viewpoints(
        SegmentMap(walls, ordered=False, oriented=True),
        np.array([[x, 1.5, 0.0, -math.pi / 2, math.pi / 2] for x in (1, 3, 5, 7, 9, 11)]),
    )
    apart = walls.copy()
    apart[0, [1, 3]] = 0.25
    t = Transform2D(2.0, -1.0, 0.4)
    views = np.array([[x, 1.5, 0.0, -math.pi / 2, math.pi / 2] for x in (14, 16, 18, 20, 22, 24)])
    views[:, 0:2] = t.inverse().apply_points(views[:, 0:2])
    views[:, 2] = -t.theta
    b = with_viewpoints(SegmentMap(t.inverse().apply(apart), ordered=False, oriented=True), views)
    cleared = integrate(a, b)
    every_wall = integrate(a, b, tuned(IntegrationParams(), map_free_space_clearance=0.0))
    assert cleared.valid and not every_wall.valid
    dt, dr = cleared.transform.distance(t)
    assert dt <= 0.3 and dr <= math.radians(1)
    assert cleared.transform == every_wall.transform and cleared.value == every_wall.value
    assert cleared.runner_up == every_wall.runner_up and cleared.rivals == every_wall.rivals
    assert cleared.violation == every_wall.violation == every_wall.solid_violation > 0.1 * every_wall.value
    assert cleared.solid_violation <= 0.1 * cleared.value


def test_a_map_whose_own_walls_cross_integrates_with_itself_at_the_identity() -> None:
    # Walls fused from many views cross each other at a junction (a wall overshooting through
    # another): the paper's refusal of crossing walls (Algorithm 4, steps 6-8) read them as a
    # contradiction at every transformation, the identity too
    room = np.array(
        [
            [0.0, 0.0, 8.0, 0.0],
            [8.0, 0.0, 8.0, 6.0],
            [8.0, 6.0, 0.0, 6.0],
            [0.0, 6.0, 0.0, 0.0],
            [3.0, -1.0, 3.0, 3.5],  # a partition fused through the wall it meets
            [5.0, 2.0, 9.0, 2.0],  # and another through the east wall
            [1.0, 4.5, 2.5, 4.5],
        ]
    )
    m = SegmentMap(room, ordered=False, oriented=False)
    found = integrate(m, m)
    assert found.valid and found.value > 0.9 * float(lengths(room).sum())
    assert math.hypot(found.transform.x, found.transform.y) < 0.01 and abs(found.transform.theta) < 1e-3


def test_an_integration_within_its_work_budget_is_the_same_and_one_unit_short_is_exhausted_not_valid() -> None:
    # (about 0.6 s: one room pair integrated three times)
    a, b, _ = PAIRS[0]
    free = integrate(a, b)
    assert free.valid and free.work > 0 and not free.exhausted
    enough = integrate(a, b, work=Work(free.work))
    assert (enough.transform, enough.value, enough.valid, enough.work) == (free.transform, free.value, True, free.work)
    short = integrate(a, b, work=Work(free.work - 1))
    assert short.exhausted and not short.valid and short.value == 0.0 and short.work < free.work
    assert short.transform == Transform2D.identity()


def test_two_large_strewn_maps_stop_at_the_budget_before_their_costly_stages() -> None:
    # Two submaps of 5,000 segments strewn over 40 m (what a robot may send the merger): about
    # 20 s to integrate whole on one core; within a budget of 20 M units they stop at it (a few ms)
    rng = np.random.default_rng(9)

    def strewn() -> SegmentMap:
        start, heading = rng.uniform(-20.0, 20.0, (5000, 2)), rng.uniform(0.0, 2 * math.pi, 5000)
        end = start + rng.uniform(0.2, 3.0, 5000)[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
        return SegmentMap(np.column_stack([start, end]), ordered=False)

    found = integrate(strewn(), strewn(), work=Work(20_000_000))
    assert found.exhausted and not found.valid and found.work <= 20_000_000
