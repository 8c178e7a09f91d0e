"""benchmarks/tracking.py: each broken clock's row is judged against its own log's true clock, and
the rows that started an epoch are named (issue 48's bounds, said under the table)."""

from __future__ import annotations

import pytest

from tests.helpers import benchmark_tool

pytestmark = pytest.mark.slow  # importing the tool imports the agents and the benchmarks (2 s): CI runs it


@pytest.fixture(scope="module")
def tool():  # type: ignore[no-untyped-def]
    return benchmark_tool("tracking")


def row(tool, name: str, clock: str, odometry: bool, within: float, epochs: int = 1):  # type: ignore[no-untyped-def]
    return tool.LogResult(name, clock, odometry, 100, 50, 50, (within, within), 0.05, 0.5, epochs, 3.0, 6.0)


def test_a_broken_clock_is_judged_against_its_own_logs_true_clock_with_the_same_people(tool) -> None:  # type: ignore[no-untyped-def]
    rows = [
        row(tool, "aces", "true", True, 0.90),
        row(tool, "aces", "true, 5 people", True, 0.80),
        row(tool, "aces", "burst, 2 draws (88.0-89.0 %)", True, 0.885),  # 1.5 under: a miss
        row(tool, "aces", "drop, 5 people, 2 draws (79.0-80.0 %)", True, 0.795),  # 0.5 under its own
        row(tool, "aces", "repeat", False, 0.70),  # no true row without odometry: not judged
        row(tool, "fr079", "true", True, 0.99, epochs=3),
        row(tool, "fr079", "skew", True, 0.97),
        tool.not_run("orebro", "burst: no clock to break", True),
    ]
    said = tool.against_true_clock(rows)
    assert said.startswith("Against the true clock: 2 of 3 broken-clock rows more than 1 point under it: ")
    assert "aces burst, odometry on (-1.5)" in said
    assert "fr079 skew, odometry on (-2.0)" in said
    assert "drop" not in said and "repeat" not in said
    assert said.endswith("Rows that started an epoch beyond their first: 1: fr079 true, odometry on (2).")


def test_rows_all_within_say_none(tool) -> None:  # type: ignore[no-untyped-def]
    rows = [row(tool, "mit-csail", "true", False, 0.99), row(tool, "mit-csail", "jitter", False, 0.985)]
    said = tool.against_true_clock(rows)
    assert said == (
        "Against the true clock: 0 of 1 broken-clock rows more than 1 point under it. "
        "Rows that started an epoch beyond their first: 0."
    )
