"""The grid index that ranks large maps' candidate transformations (fleetmap.shared.core.mapgrid)."""

from __future__ import annotations

import math
import multiprocessing

import numpy as np
from fleetmap.shared.core import mapgrid
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.mapgrid import RANK_ROTATION_STEP, grid_scores, map_index, ranking_scores
from fleetmap.shared.core.segmap import SegmentMap

# An L-shaped room with a pillar: walls facing every way, no symmetry.
WALLS = np.array(
    [
        [0.0, 0.0, 8.0, 0.0],
        [8.0, 0.0, 8.0, 3.0],
        [8.0, 3.0, 4.0, 3.0],
        [4.0, 3.0, 4.0, 6.0],
        [4.0, 6.0, 0.0, 6.0],
        [0.0, 6.0, 0.0, 0.0],
        [1.5, 1.5, 2.5, 1.5],
        [2.5, 1.5, 2.5, 2.5],
    ]
)


def _index(segments: np.ndarray) -> object:
    return map_index(SegmentMap(segments, ordered=False, oriented=True), 0.1, 0.2, 0.2, 0.02)


def test_ranking_puts_the_true_transformation_first_and_scores_it_as_the_grid_score_does() -> None:
    true = Transform2D(1.3, -0.7, 4 * RANK_ROTATION_STEP)
    a = _index(WALLS)
    b = _index(true.inverse().apply(WALLS))
    rng = np.random.default_rng(5)
    others = np.column_stack(
        [rng.uniform(-3, 3, 200), rng.uniform(-3, 3, 200), rng.integers(-720, 720, 200) * RANK_ROTATION_STEP]
    )
    t = np.vstack([others[:100], true.as_array(), others[100:]])
    ranked = ranking_scores(a, b, t)
    assert int(np.argmax(ranked)) == 100
    # On rotations the ranking does not round, it is the grid score: matched wall less wall in free space.
    hit, free = grid_scores(a, b, t)
    assert np.allclose(ranked, hit - free, atol=1e-9)
    # The true transformation matches (almost) all the walls, both ways.
    total = float(np.hypot(WALLS[:, 2] - WALLS[:, 0], WALLS[:, 3] - WALLS[:, 1]).sum())
    assert ranked[100] > 0.9 * total


def test_ranking_scores_are_whole_samples_and_do_not_depend_on_the_candidates_order() -> None:
    # Each sample that lands on a wall counts its spacing, one in free space twice that against:
    # a score is a whole number of half spacings, summed exactly, so equal alignments tie exactly
    # (the stable sort keeps the candidates' order) whatever a BLAS does with float sums, and a
    # replay on another machine ranks the same. The candidates are scored by rotation group: a
    # candidate's score must not depend on the others beside it, nor on their order.
    a = _index(WALLS)
    b = _index(Transform2D(0.4, 0.2, 0.3).apply(WALLS))
    rng = np.random.default_rng(9)
    turn = np.where(np.arange(600) % 2 == 0, 0.3, rng.uniform(-math.pi, math.pi, 600))
    t = np.column_stack([rng.uniform(-2, 2, 600), rng.uniform(-2, 2, 600), turn])
    samples = b.coarse
    half = 0.5 * float(samples.weight[0])
    scores = mapgrid._ranking_lookups(a, samples, t)
    counts = np.round(scores / half)
    assert np.array_equal(scores, counts * half)
    assert len(set(scores.tolist())) < len(scores)  # there are ties to break
    assert np.array_equal(mapgrid._ranking_lookups(a, samples, t[:9]), scores[:9])
    shuffled = rng.permutation(len(t))
    assert np.array_equal(mapgrid._ranking_lookups(a, samples, t[shuffled]), scores[shuffled])


def _forked_scores(args: tuple[object, object, np.ndarray]) -> np.ndarray:
    a, b, t = args
    return ranking_scores(a, b, t)  # type: ignore[arg-type]


def test_both_directions_side_by_side_give_the_same_scores_and_a_forked_worker_gets_them_too(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # Many candidates: the two directions of a grid score run on two threads. The scores must be
    # the serial ones to the bit, and a worker forked after the parent's thread pool started
    # (the merge benchmark's pool) must score too, not wait forever on a thread it does not have.
    a = _index(WALLS)
    b = _index(Transform2D(0.4, 0.2, 0.3).apply(WALLS))
    rng = np.random.default_rng(3)
    n = 2 * mapgrid.PARALLEL_FROM
    t = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(-math.pi, math.pi, n)])
    parallel = ranking_scores(a, b, t)
    parallel_parts = grid_scores(a, b, t)
    monkeypatch.setattr(mapgrid, "PARALLEL_FROM", 10 * n)
    assert np.array_equal(parallel, ranking_scores(a, b, t))
    for got, serial in zip(parallel_parts, grid_scores(a, b, t), strict=True):
        assert np.array_equal(got, serial)
    monkeypatch.undo()
    if "fork" not in multiprocessing.get_all_start_methods():
        return
    with multiprocessing.get_context("fork").Pool(1) as pool:
        forked = pool.map_async(_forked_scores, [(a, b, t)]).get(timeout=60)[0]
    assert np.array_equal(forked, parallel)


def test_only_long_walls_in_seen_free_space_count_as_solid() -> None:
    # A furnished room seen from one viewpoint, and the same room mapped again later: a chair (a
    # 0.3 m segment) now stands where the first visit saw the floor free. The chair moved; the room
    # did not: it is no ground to refuse the alignment. A 1.6 m wall there would be.
    seen = mapgrid.with_viewpoints(
        SegmentMap(WALLS, ordered=False, oriented=True), np.array([[3.0, 1.0, 0.0, -math.pi, math.pi]])
    )
    chair = np.array([[2.85, 4.5, 3.15, 4.5]])
    wall = np.array([[2.2, 4.0, 3.8, 4.0]])
    here = np.zeros((1, 3))

    def violation(extra: np.ndarray, solid: bool) -> float:
        later = SegmentMap(np.vstack([WALLS, extra]), ordered=False, oriented=True)
        a, b = map_index(seen, 0.1, 0.2, 0.2, 0.02, 0.8), map_index(later, 0.1, 0.2, 0.2, 0.02, 0.8)
        return float(grid_scores(a, b, here, fine=True, solid=solid)[1][0])

    assert violation(chair, solid=False) >= 0.2  # every wall: the chair counts (the score)
    assert violation(chair, solid=True) == 0.0  # solid walls only: it does not
    assert violation(wall, solid=True) >= 1.4  # a long wall does


def test_a_wall_mapped_a_little_apart_is_not_in_seen_free_space_but_one_well_inside_is() -> None:
    # A 20 m corridor seen from near one end: far down it, the laser meets the walls at a grazing
    # angle. Another robot's map of the same corridor has the wall 0.25 m closer (its scan-to-scan
    # errors added up differently): far down, that is a metre along the ray, beyond any range
    # margin, so without clearance it lies in the seen free space. It is the same wall: it does not
    # count against the alignment's validity (it still lowers its score). A wall 1 m inside the
    # corridor is not, and counts.
    corridor = np.array([[0.0, 2.0, 20.0, 2.0], [20.0, 2.0, 20.0, -2.0], [20.0, -2.0, 0.0, -2.0]])
    seen = mapgrid.with_viewpoints(
        SegmentMap(corridor, ordered=False, oriented=True), np.array([[1.0, 0.0, 0.0, -math.pi / 2, math.pi / 2]])
    )
    here = np.zeros((1, 3))

    def violation(wall_y: float, clearance: float, solid: bool = True) -> float:
        other = SegmentMap(np.array([[6.0, wall_y, 20.0, wall_y]]), ordered=False, oriented=True)
        # The walls' reach as integration sets it (segment_distance_threshold * point_distance_tolerance).
        a = map_index(seen, 0.1, 0.075, 0.2, 0.02, clearance=clearance)
        b = map_index(other, 0.1, 0.075, 0.2, 0.02)
        return float(grid_scores(a, b, here, fine=True, solid=solid)[1][0])

    assert violation(1.75, clearance=0.0) >= 5.0  # metres of the same wall, "seen through"
    assert violation(1.75, clearance=0.3) == 0.0  # what refuses an alignment: nothing
    assert violation(1.75, clearance=0.3, solid=False) >= 5.0  # the score still counts it
    assert violation(1.0, clearance=0.3) >= 10.0  # a wall where the corridor was seen free


def test_distinct_viewpoints_skips_one_near_a_kept_one_across_a_cell_border_and_keeps_one_turned() -> None:
    # 0.45 and 0.55 lie in two cells of VIEWPOINT_SPACING (0.5 m), 0.1 m apart: the second adds nothing
    vp = np.array(
        [
            [0.45, 0.0, 0.0, -1.0, 1.0],
            [0.55, 0.0, 0.05, -1.0, 1.0],  # near the first, hardly turned: skipped
            [0.55, 0.0, 1.0, -1.0, 1.0],  # near it, turned a radian: kept
            [1.2, 0.0, 0.0, -1.0, 1.0],  # 0.75 m from the first: kept
            [-0.04, 0.0, 0.0, -1.0, 1.0],  # 0.49 m behind the first, in the cell before the one beside it
        ]
    )
    kept = mapgrid.distinct_viewpoints(vp)
    assert kept[:, 0].tolist() == [0.45, 0.55, 1.2]
    assert kept[:, 2].tolist() == [0.0, 1.0, 0.0]
