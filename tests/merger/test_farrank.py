"""The far search's order: the overlap score ranks a partner that shares part of a submap's walls
first, within a window of the descriptor's order that widens with every try (docs/decisions/031)."""

from __future__ import annotations

import dataclasses

import pytest
from fleetmap.merger.executor import LocalExecutor
from fleetmap.merger.farrank import FAR_SCORED, FarRanking
from fleetmap.merger.outputs import Placement
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.schedule import FAR_CANDIDATES, PairSchedule
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.io.messages import LocalMap

from tests.helpers import true_local_map

QUERY = ("r1", 28, 33)
"""The short last stretch of a robot's tour (the department, scans at their true poses) ..."""
PARTNER = ("r2", 4, 10)
"""... the one stretch of another robot's that drives the same corridor (1.3 m from it) ..."""
OTHERS = [("r2", 12, 18), ("r2", 16, 22), ("r2", 20, 26), ("r2", 24, 30), ("r3", 24, 30), ("r3", 30, 36)]
"""... and stretches 6-16 m away, elsewhere in the building."""


def _key(stretch: tuple[str, int, int]) -> str:
    robot, start, _ = stretch
    return f"{robot}/{start}/0"


@pytest.fixture(scope="module")
def maps() -> dict[str, LocalMap]:
    """The stretches as final submaps."""
    return {
        _key(stretch): dataclasses.replace(true_local_map("department", *stretch)[0], final=True)
        for stretch in (QUERY, PARTNER, *OTHERS)
    }


def _graph_of(maps: dict[str, LocalMap]) -> PoseGraph:
    graph = PoseGraph()
    for key, m in maps.items():
        graph.put_map(key, SegmentMap(m.segments, ordered=False, oriented=True))
    return graph


@pytest.fixture(scope="module")
def graph(maps: dict[str, LocalMap]) -> PoseGraph:
    return _graph_of(maps)


@pytest.mark.slow  # tracks nothing, but builds seven submaps from the department's scans (shared)
def test_the_overlap_score_ranks_the_stretch_that_shares_walls_first(
    graph: PoseGraph, maps: dict[str, LocalMap]
) -> None:
    ranking = FarRanking(graph, MergerStats(), maps)
    scores = {_key(s): ranking.score(_key(QUERY), _key(s)) for s in (PARTNER, *OTHERS)}
    best = max(scores, key=lambda k: scores[k])
    assert best == _key(PARTNER), f"scores {scores}"
    assert scores[best] > 1.5 * max(v for k, v in scores.items() if k != best), f"no clear margin: {scores}"


@pytest.mark.slow  # shares the submaps of the test above
def test_each_try_ranks_more_of_the_descriptors_order_and_scores_each_pair_once(
    graph: PoseGraph, maps: dict[str, LocalMap]
) -> None:
    stats = MergerStats()
    ranking = FarRanking(graph, stats, maps)
    query = _key(QUERY)
    # the descriptor put the partner after every other stretch: beyond the first try's window
    partners = [_key(s) for s in OTHERS] + [_key(PARTNER)]
    assert len(OTHERS) >= FAR_SCORED
    first = ranking.order(query, partners, 1)
    assert first[FAR_SCORED:] == partners[FAR_SCORED:], "beyond the window, the descriptor's order"
    assert sorted(first[:FAR_SCORED]) == sorted(partners[:FAR_SCORED])
    assert stats.far_scored == FAR_SCORED, "one try scores FAR_SCORED pairs"
    later = ranking.order(query, partners, 2)
    assert later[0] == _key(PARTNER), f"the window reached the partner: {later}"
    assert sorted(later) == sorted(partners), "nothing lost, nothing added"
    assert stats.far_scored == len(partners), "pairs scored before are not scored again"
    ranking.order(query, partners, 2)
    assert stats.far_scored == len(partners)


@pytest.mark.slow  # shares the submaps of the tests above, and starts a process pool
def test_a_tries_scores_run_side_by_side_on_the_merger_executor_and_rank_as_in_process(
    graph: PoseGraph, maps: dict[str, LocalMap]
) -> None:
    query = _key(QUERY)
    partners = [_key(s) for s in OTHERS] + [_key(PARTNER)]
    here = FarRanking(graph, MergerStats(), maps)
    executor = LocalExecutor(2)
    try:
        pooled = FarRanking(_graph_of(maps), MergerStats(), maps, executor)
        order = pooled.order(query, partners, 2)
        assert executor.submitted == len(partners), "each pair scored once, in the pool"
        scores = {other: pooled.score(query, other) for other in partners}
        assert executor.submitted == len(partners), "a score known is not asked for again"
    finally:
        executor.close()
    assert order == here.order(query, partners, 2)
    assert scores == {other: here.score(query, other) for other in partners}, "the same scores to the bit"


@pytest.mark.slow  # shares the submaps of the tests above
def test_a_growing_submap_keeps_the_descriptors_order_and_is_not_scored(
    graph: PoseGraph, maps: dict[str, LocalMap]
) -> None:
    # its next version, a few scans on, would need its scores again: live, scoring each version of
    # a fleet's growing submaps fell twenty seconds behind the robots
    query = _key(QUERY)
    partners = [_key(s) for s in OTHERS] + [_key(PARTNER)]
    growing = {**maps, query: dataclasses.replace(maps[query], final=False)}
    stats = MergerStats()
    assert FarRanking(graph, stats, growing).order(query, partners, 5) == partners
    assert stats.far_scored == 0
    # a growing partner is left out of the window, the final ones ranked
    growing = {**maps, _key(PARTNER): dataclasses.replace(maps[_key(PARTNER)], final=False)}
    order = FarRanking(graph, stats, growing).order(query, partners, 5)
    assert order[-1] == _key(PARTNER) and sorted(order) == sorted(partners)
    assert stats.far_scored == len(OTHERS)


@pytest.mark.slow  # shares the submaps of the tests above
def test_a_merger_behind_its_robots_searches_far_in_the_descriptors_order_and_scores_nothing(
    graph: PoseGraph, maps: dict[str, LocalMap]
) -> None:
    # live, scoring 12 partners for each final submap on arrival, in the merger's step, kept a
    # fleet of 16 robots behind (docs/decisions/032)
    query = _key(QUERY)
    arriving = dataclasses.replace(maps[query], epoch=QUERY[1])  # its key, as the graph holds it
    assert arriving.submap_key == query
    placement = Placement.of(graph.solve())
    searched, scored = {}, {}
    for behind in (True, False):
        stats = MergerStats()
        schedule = PairSchedule(graph, dict(maps), FleetmapConfig(), stats, lambda *_: None)
        schedule.behind = behind
        schedule.submap(arriving, True, placement)
        searched[behind] = sorted(b if a == query else a for a, b in schedule.queue)
        scored[behind] = stats.far_scored
    assert scored[True] == 0, "behind, nothing is scored"
    everyone = sorted(k for k in maps if k != query)
    assert scored[False] == min(FAR_SCORED * FAR_CANDIDATES, len(everyone)), "on time, the window is scored"
    ranking = FarRanking(graph, MergerStats(), maps)
    best = sorted(everyone, key=lambda k: -ranking.score(query, k))[:FAR_CANDIDATES]
    assert searched[False] == sorted(best), "on time, the best scored are tried (the window holds them all)"
    assert len(searched[True]) == FAR_CANDIDATES and searched[True] != searched[False]
