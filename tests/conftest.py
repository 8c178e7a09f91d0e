"""Shared fixtures: the real datasets (skipped where they are not on this machine)."""

from __future__ import annotations

import gzip
import os
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from fleetmap.mapping import MapResult, Piece


def data_dir() -> Path | None:
    candidates = [os.environ.get("FLEETMAP_DATA"), Path(__file__).resolve().parents[2] / "shared" / "data"]
    for c in candidates:
        if c and (Path(c) / "relations").is_dir():
            return Path(c)
    return None


FLEETS = (
    "tests/live/",
    "tests/shared/test_bus.py",
    "tests/agents/test_process.py",
    "tests/merger/test_executor.py",
    "tests/merger/test_recorder.py",
    "tests/test_agent_processes.py",
)
"""The modules whose slow tests run fleets of processes that wait on each other (zenoh sessions
between processes, worker pools a test kills)."""


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The slow tests that run fleets of processes (:data:`FLEETS`) run one after another on one
    xdist worker: two fleets at once on a two-core machine would each wait on processes the other
    starves. The other slow tests (maps of many scans, a command in a process of its own) share the
    workers with the fast ones: they wait on nothing but their own work."""
    for item in items:
        if item.get_closest_marker("slow") and item.nodeid.startswith(FLEETS):  # (relative to the project)
            item.add_marker(pytest.mark.xdist_group("fleet"))


@pytest.fixture(scope="session")
def datasets() -> Path:
    d = data_dir()
    if d is None:
        pytest.skip("real laser datasets not found (set FLEETMAP_DATA to ../shared/data)")
    return d


CSAIL_SCANS = 360


@pytest.fixture(scope="session")
def csail_start(datasets: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first CSAIL_SCANS laser lines of the mit-csail log (odometry on its FLASER lines)."""
    out = tmp_path_factory.mktemp("csail") / "csail-start.clf"
    lines = []
    with gzip.open(datasets / "mit-csail" / "mit-csail.clf.gz", "rt") as fh:
        for line in fh:
            if line.startswith("FLASER"):
                lines.append(line)
                if len(lines) == CSAIL_SCANS:
                    break
    out.write_text("".join(lines))
    return out


@pytest.fixture(scope="session")
def csail_pieces(csail_start: Path) -> list[Piece]:
    """The CSAIL_SCANS real scans (mit-csail) as two robots, as ``fleetmap map --split 2`` reads them."""
    from fleetmap.mapping import read_inputs

    return read_inputs([str(csail_start)], 2, None, 81.91, None)


@pytest.fixture(scope="session")
def csail_in_line(csail_pieces: list[Piece], tmp_path_factory: pytest.TempPathFactory) -> tuple[MapResult, Path]:
    """``csail_pieces`` mapped in this process alone (the agents in line, the integrations inline),
    and the folder of its outputs: the map every other way of running the same mapping (worker
    processes, a process pool, the command) must give exactly. Mapped once for the whole session."""
    from fleetmap.merger.executor import InlineExecutor

    from fleetmap.config_args import preset
    from fleetmap.mapping import map_logs

    out = tmp_path_factory.mktemp("csail-in-line")
    result = map_logs(csail_pieces, out, preset("offline"), None, InlineExecutor(), tracking_processes=0)
    return result, out
