"""fleetmap's errors cross a process pool whole (the merger's local executor, the benchmarks' pools)."""

from __future__ import annotations

import multiprocessing

import pytest
from fleetmap.shared.errors import BadInput, ConfigError, FleetmapError
from fleetmap.shared.io.messages import BadMessage

ERRORS: list[FleetmapError] = [
    BadInput("aces.clf", "line 12: expected 180 ranges, got 3"),
    ConfigError("merge.far_budget", "expected an integer, got 'many'"),
    BadMessage("fleetmap.LocalMap", "segments", "expected an (n, 4) array"),
    BadMessage("fleetmap.Scan", None, "not msgpack"),
]


def _raise(n: int) -> None:
    raise ERRORS[n]


@pytest.mark.parametrize("n", range(len(ERRORS)))
def test_an_error_raised_in_a_pool_worker_reaches_the_caller_as_itself(n: int) -> None:
    # Pickled by its message alone, a BadMessage could not be rebuilt in the pool's result thread,
    # and the pool then waited for the result for ever (benchmarks/merge.py hung on a bad local map).
    with multiprocessing.get_context("spawn").Pool(1) as pool:  # no fork of a process with threads
        pending = pool.apply_async(_raise, (n,))
        with pytest.raises(type(ERRORS[n])) as raised:
            pending.get(timeout=60)
    assert str(raised.value) == str(ERRORS[n])
    assert isinstance(raised.value, BadInput) and raised.value.reason == ERRORS[n].reason  # type: ignore[attr-defined]
