"""Every benchmark script starts: its imports load and its command line parses (``--help``).

The benchmarks run on demand, not in CI (`benchmarks/regenerate.py` reruns them all, for about two
hours); a script that no longer imports, or whose options clash, would fail there, hours in. Each
is run here as a user runs it, ``python benchmarks/NAME.py --help``, in a process of its own.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # a python process per script, each importing the mapping (2 s): CI runs it

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py") if 'if __name__ == "__main__"' in p.read_text())


def test_the_benchmarks_folder_has_its_scripts() -> None:
    assert {"relations.py", "tracking.py", "live.py", "regenerate.py"} <= set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_benchmark_script_starts_and_says_its_usage(script: str) -> None:
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), "--help"],
        cwd=BENCHMARKS.parent,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, f"{script} --help exited {done.returncode}: {done.stderr[-2000:]}"
    assert "usage:" in done.stdout, f"{script} --help printed no usage: {done.stdout[:500]}"
