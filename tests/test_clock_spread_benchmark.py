"""benchmarks/clock_spread.py: a broken clock is judged against its true clock's own spread, and the
rows it draws again are the ones benchmarks/tracking.py lists as misses."""

from __future__ import annotations

import pytest

from tests.helpers import benchmark_tool

pytestmark = pytest.mark.slow  # importing the tool imports the agents and the benchmarks (2 s): CI runs it


@pytest.fixture(scope="module")
def tool():  # type: ignore[no-untyped-def]
    return benchmark_tool("clock_spread")


def test_a_row_clearly_more_than_a_point_under_its_nudged_draws_is_under(tool) -> None:  # type: ignore[no-untyped-def]
    nudged = [88.0, 88.4, 87.8, 88.2, 88.1, 87.9]
    verdict = tool.judge(nudged, [84.9, 85.3, 85.1, 84.7, 85.0, 85.2])
    assert verdict.said == "under" and verdict.gap == pytest.approx(3.0, abs=0.05) and verdict.p < 0.01


def test_a_gap_over_a_point_within_the_draws_spread_is_undecided_and_a_small_one_within(tool) -> None:  # type: ignore[no-untyped-def]
    nudged = [86.7, 87.1, 87.0, 86.7, 87.2, 88.3]
    wide = tool.judge(nudged, [84.3, 87.7, 85.0, 87.4, 85.8, 85.9])  # 1.2 under, draws 3 points apart
    assert wide.said == "undecided" and wide.gap > 1.0 and wide.p > 0.05
    assert tool.judge(nudged, [86.5, 86.9, 86.8, 86.2, 87.0, 86.6]).said == "within"
    assert tool.judge([90.0, 90.0], [88.0, 88.0]).said == "under", "no spread at all: the means decide"


def test_the_misses_are_read_from_the_tracking_verdict_with_their_people_odometry_and_cut(tool) -> None:  # type: ignore[no-untyped-def]
    body = (
        "| table |\n\nAgainst the true clock: 3 of 160 broken-clock rows more than 1 point under it: aces drop, "
        "odometry off (-1.0); corrected/aces drop, 5 people, odometry off (-3.7); corrected/orebro burst, cut in "
        "4, odometry on (-1.1). Rows that started an epoch beyond their first: 1: corrected/freiburg-campus true, "
        "odometry on (5).\n\nBundled scenarios"
    )
    assert tool.misses_of(body) == [
        tool.Row("aces", "drop", 0, False),
        tool.Row("corrected/aces", "drop", 5, False),
        tool.Row("corrected/orebro", "burst", 0, True, 4),
    ]
    none = "Against the true clock: 0 of 160 broken-clock rows more than 1 point under it. Rows that started ..."
    assert tool.misses_of(none) == []
    with pytest.raises(ValueError, match="no verdict"):
        tool.misses_of("| a table without its verdict |")


def test_rows_are_named_as_the_tracking_benchmark_names_them_and_bad_ones_refused(tool) -> None:  # type: ignore[no-untyped-def]
    rows = tool.parse_rows("corrected/edmonton:drop:0:off,aces:burst:5")
    assert rows == [
        tool.Row("corrected/edmonton", "drop", 0, False),
        tool.Row("aces", "burst", 5, True),
        tool.Row("aces", "burst", 5, False),
    ]
    assert rows[1].said() == "aces burst, 5 people, odometry on"
    for bad, why in (("nowhere:drop", "unknown log"), ("aces:nudge", "not a broken clock"), ("aces:drop:x", "count")):
        with pytest.raises(ValueError, match=why):
            tool.parse_rows(bad)
