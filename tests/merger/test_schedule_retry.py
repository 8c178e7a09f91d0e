"""A pair the join puts beyond registration's reach: registered near the join first, and searched by
the paper's integration when that fails (infinite-corridor-c cut in 2: docs/decisions/028), within
the forest's tolerance around the join (docs/decisions/037)."""

from __future__ import annotations

import math

import pytest
from fleetmap.merger.executor import run_pair
from fleetmap.merger.outputs import Placement
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.schedule import PairSchedule
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.tracking import MAX_CORRESPONDENCE, REACH_ROTATION
from fleetmap.shared.io.messages import LocalMap

from tests.helpers import true_local_map
from tests.merger.test_consistency import _HALL_OF_DOORS, _WORLD, _two_robots


def _pair() -> tuple[PoseGraph, dict[str, LocalMap], Transform2D]:
    """Two robots' submaps over one stretch of the department (a perfect agent's), in a pose graph;
    and the second's true pose in the first's frame."""
    graph = PoseGraph()
    submaps: dict[str, LocalMap] = {}
    frames = {}
    for key, robot, start, stop in (("r1/0/0", "r1", 0, 40), ("r2/0/0", "r1", 20, 60)):
        m, frame = true_local_map("department", robot, start, stop)
        graph.put_map(key, SegmentMap(m.segments, ordered=False, oriented=True))
        submaps[key], frames[key] = m, frame
    return graph, submaps, frames["r1/0/0"].inverse().compose(frames["r2/0/0"])


def _schedule(graph: PoseGraph, submaps: dict[str, LocalMap]) -> PairSchedule:
    return PairSchedule(graph, submaps, FleetmapConfig(), MergerStats(), lambda *_: None)


def _integrated(schedule: PairSchedule) -> tuple[tuple[str, str], bool]:
    """The next queued pair integrated as the merger does, and whether it was pose-free."""
    pair, predicted = schedule.next_pair()
    schedule.take(pair)
    job = schedule.job(pair, predicted)
    assert job is not None, f"{pair} queued but due no integration"
    edge = schedule.graph.take(job, run_pair(job, schedule.graph.indexes))
    schedule.registered(pair, edge.valid)
    return pair, predicted is None


@pytest.mark.slow  # one of the fast suite's slowest (about 1 s): CI runs it with the slow ones
def test_a_joined_pair_whose_registration_near_the_join_fails_is_integrated_pose_free_and_found() -> None:
    graph, submaps, truth = _pair()
    schedule = _schedule(graph, submaps)
    pair = ("r1/0/0", "r2/0/0")
    off = truth.compose(Transform2D(3.0, 0.0, math.radians(20.0)))  # where a long way round puts it
    schedule.enqueue(pair, off)
    schedule.wide[pair] = off  # the forest's path between them can have drifted beyond reach
    assert _integrated(schedule) == (pair, False)
    edge = graph.edge(*pair)
    assert edge is not None and not edge.valid, "registered 3 m and 20 degrees off, it should not fit"
    assert pair in schedule.queue, "a failed registration beyond reach must be tried pose-free"
    assert _integrated(schedule) == (pair, True)
    edge = graph.edge(*pair)
    assert edge is not None and edge.valid
    dt, dr = edge.transform.distance(truth)
    assert dt < 0.10 and math.degrees(dr) < 2.0, f"pose-free: {dt:.2f} m, {math.degrees(dr):.1f} deg off"
    assert not schedule.queue, "tried pose-free once"
    assert schedule.stats.retried == 1, "the retry is counted (fleetmap map's join_pairs_retried)"


def test_a_pair_within_reach_whose_registration_fails_is_not_tried_again() -> None:
    graph, submaps, truth = _pair()
    schedule = _schedule(graph, submaps)
    pair = ("r1/0/0", "r2/0/0")
    schedule.enqueue(pair, truth.compose(Transform2D(3.0, 0.0, math.radians(20.0))))
    _integrated(schedule)
    edge = graph.edge(*pair)
    assert edge is not None and not edge.valid
    assert not schedule.queue, "only a pair the join can have put beyond reach is tried again"
    assert schedule.stats.retried == 0


@pytest.mark.parametrize(("heading_sigma", "beyond"), [(0.001, False), (0.05, True)])
def test_the_forest_says_when_two_robots_tied_at_one_end_can_have_drifted_beyond_reach_at_the_other(
    heading_sigma: float, beyond: bool
) -> None:
    # two robots down a hall, tied by two integrations that agree at its start; their far ends lie
    # one link on from the tie on each chain, links whose heading the tracking measured within
    # ``heading_sigma`` (rad): three of 0.05 rad carry them about 9 degrees apart, three of 0.001
    # rad a few centimetres
    graph, _ = _two_robots(
        _WORLD,
        [(0, 0, Transform2D.identity(), 28.0), (1, 1, Transform2D.identity(), 26.0)],
        r2_start=0.5,
        last_link_heading=heading_sigma,
    )
    assert any({"r1/0/0", "r2/0/0"} <= set(c.members) for c in graph.solve().components)
    near = graph.tree_drift("r1/0/0", "r2/0/0")
    far = graph.tree_drift("r1/0/2", "r2/0/2")
    assert near is not None and far is not None
    assert near[0] <= MAX_CORRESPONDENCE and near[1] <= REACH_ROTATION, f"at the tie: {near}"
    assert far[0] > near[0]
    assert (far[0] > MAX_CORRESPONDENCE or far[1] > REACH_ROTATION) is beyond, f"at the far ends: {far}"


_FAR_ENDS = ("r1/0/2", "r2/0/2")


def _hall() -> tuple[PoseGraph, Placement, Transform2D]:
    """Two robots down a hall with a door every 4 m, tied at its start and solved; where the last
    solve puts them, and the far ends' true transform. There the forest's path allows 1.3 m and
    25 degrees."""
    graph, truth = _two_robots(
        _HALL_OF_DOORS,
        [(0, 0, Transform2D.identity(), 28.0), (1, 1, Transform2D.identity(), 26.0)],
        r2_start=0.5,
        last_link_heading=0.1,
    )
    placement = Placement.of(graph.solve())
    return graph, placement, truth[_FAR_ENDS[0]].inverse().compose(truth[_FAR_ENDS[1]])


def _found(schedule: PairSchedule, true: Transform2D) -> None:
    """The queued far ends integrated pose-free, and found valid at the truth."""
    assert _integrated(schedule) == (_FAR_ENDS, True)
    edge = schedule.graph.edge(*_FAR_ENDS)
    assert edge is not None and edge.valid, "within the forest's tolerance the far ends match one way only"
    dt, dr = edge.transform.distance(true)
    assert dt < 0.05 and math.degrees(dr) < 1.0, f"{dt:.2f} m, {math.degrees(dr):.1f} deg off"


def test_a_retried_pair_is_searched_within_the_forests_tolerance_and_found_where_the_whole_hall_looks_alike() -> None:
    # the whole-map search finds the far ends' true alignment but calls it ambiguous (a bay along
    # looks the same); within the tolerance around the join's prediction, only the true one is left
    graph, _, true = _hall()
    pair = _FAR_ENDS
    tolerance = graph.tree_tolerance(*pair)
    assert tolerance is not None and tolerance[0] < 2.0, f"the forest allows {tolerance}: half a bay or more"
    whole = run_pair(graph.pair_job(*pair), graph.indexes).integration
    assert not whole.valid, "the whole hall's search should find a bay along as good"
    schedule = _schedule(graph, {})
    off = true.compose(Transform2D(1.0, 0.0, math.radians(20.0)))  # where the join put it
    schedule.enqueue(pair, off)
    schedule.wide[pair] = off
    schedule.take(pair)
    schedule.registered(pair, False)  # (registration along a hall slides: as if it had failed)
    assert schedule.queue == {pair: None}, "a failed registration beyond reach is searched again"
    _found(schedule, true)


def test_a_loop_beyond_reach_is_searched_around_where_the_solve_puts_it_and_found_in_a_hall_that_repeats() -> None:
    # the far ends queued as a loop of one component (the near search's pair beyond reach, or a
    # loop sweep), around where the last solve puts them
    graph, placement, true = _hall()
    schedule = _schedule(graph, {})
    schedule._queue_loop(_FAR_ENDS[1], _FAR_ENDS[0], placement)
    assert schedule.queue == {_FAR_ENDS: None}, "queued pose-free, one way round"
    window = schedule.windows[_FAR_ENDS]
    assert window.radius < 2.0, f"half a bay or more: {window.radius:.2f} m"
    _found(schedule, true)
