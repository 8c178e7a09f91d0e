"""fleetmap map's agents in worker processes: the same map (and files) as in line, and a worker that fails or
dies is an error in the caller, not a run that waits for ever."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from fleetmap.shared.config import FleetmapConfig

from fleetmap.agent_processes import AgentProcesses
from fleetmap.config_args import preset
from fleetmap.mapping import MapResult, Piece, map_logs


@pytest.fixture(scope="module")
def pieces(csail_pieces: list[Piece]) -> list[Piece]:
    """360 real scans (mit-csail) as two robots."""
    return csail_pieces


def _order(pieces: list[Piece]) -> list[tuple[int, int]]:
    timeline = sorted((s.stamp - p.scans[0].stamp, n, i) for n, p in enumerate(pieces) for i, s in enumerate(p.scans))
    return [(n, i) for _, n, i in timeline]


@pytest.mark.slow
def test_agents_in_worker_processes_map_as_agents_in_line(
    pieces: list[Piece], csail_in_line: tuple[MapResult, Path], tmp_path: Path
) -> None:
    in_line = csail_in_line[0]
    apart = map_logs(pieces, tmp_path / "apart", preset("offline"), tracking_processes=2)
    assert len(in_line.poses) > 300
    assert apart.poses == in_line.poses
    # the session's files, written by a process of their own beside the key scans' refinement
    for name in ("global_map.json", "map.pgm", "map.yaml"):
        assert (tmp_path / "apart" / name).read_bytes() == (csail_in_line[1] / name).read_bytes(), name
    assert (tmp_path / "apart" / "global_map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for a, b in zip(apart.report["map"]["robots"], in_line.report["map"]["robots"], strict=True):
        assert (a["robot"], a["epochs"], a["scans_placed"], a["clock"]) == (
            b["robot"],
            b["epochs"],
            b["scans_placed"],
            b["clock"],
        )


@pytest.mark.slow  # starts worker processes (about 1 s)
def test_a_worker_that_fails_raises_its_error_in_the_caller(pieces: list[Piece]) -> None:
    broken = [replace(pieces[0], scans=[replace(s, scan=None) for s in pieces[0].scans]), pieces[1]]
    with AgentProcesses(broken, _order(broken), FleetmapConfig(), 2) as agents, pytest.raises(AttributeError):
        for _ in agents:
            pass


@pytest.mark.slow  # starts and kills worker processes (about 2 s)
def test_a_worker_that_dies_is_a_clear_error_not_a_wait(pieces: list[Piece]) -> None:
    with AgentProcesses(pieces, _order(pieces), FleetmapConfig(), 1) as agents:
        process = agents._workers[0][0]
        process.kill()
        process.join(timeout=30)
        with pytest.raises(RuntimeError, match=r"tracking worker .* ended"):
            for _ in agents:
                pass
