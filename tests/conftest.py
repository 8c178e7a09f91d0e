"""Shared fixtures: the real datasets (skipped where they are not on this machine)."""

from __future__ import annotations

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
