"""Shared fixtures: the real datasets (skipped where they are not on this machine)."""

from __future__ import annotations

import gzip
import os
from pathlib import Path

import pytest


def data_dir() -> Path | None:
    candidates = [os.environ.get("FLEETMAP_DATA"), Path(__file__).resolve().parents[2] / "shared" / "data"]
    for c in candidates:
        if c and (Path(c) / "relations").is_dir():
            return Path(c)
    return None


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
