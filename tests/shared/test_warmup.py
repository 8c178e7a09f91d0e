"""The compiled loops built once by the process that starts the others (decision record 073)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest


def _run(code_or_args: list[str], cache: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    return subprocess.run(
        [sys.executable, *code_or_args], capture_output=True, text=True, timeout=600, check=False, env=env
    )


def _cache(cache: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in cache.rglob("*.nbi")}


@pytest.mark.slow  # compiles every loop in a fresh cache, then maps 360 real scans (about 20 s)
def test_after_the_warm_up_mapping_a_real_log_compiles_nothing(csail_start: Path, tmp_path: Path) -> None:
    cache = tmp_path / "numba"
    warmed = _run(["-c", "from fleetmap.shared.core.warmup import warm; warm()"], cache)
    assert warmed.returncode == 0, warmed.stderr
    before = _cache(cache)
    assert len(before) == 8, sorted(before)  # one index for each compiled loop
    # tracking (nearest cells, the beam test, pose-free integration), merging (the grid score,
    # matched pairs, refinement) and the occupancy grid (the beam march), in two processes
    done = _run(
        ["-m", "fleetmap", "map", str(csail_start), "--out", str(tmp_path / "map"), "--split", "2",
         "--no-return-reading", "81.91", "--no-progress"],
        cache,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "map" / "map.pgm").is_file()
    # a loop called with argument types the warm-up did not give would be compiled again and its
    # index written anew: every process would pay for it on a new machine
    assert _cache(cache) == before
