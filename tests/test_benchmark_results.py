"""Benchmark results as data (``benchmarks/results.py``): what a benchmark's ``--write-results``
writes renders into RESULTS.md, and a result from a checkout with uncommitted changes is refused."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
from fleetmap.shared.config import FleetmapConfig, tuned

RESULTS_PY = Path(__file__).resolve().parent.parent / "benchmarks" / "results.py"
BODY = """`fleetmap map` on aces given 1 and more times.

| log | tours | time (share of log) | against one tour | step time, first / last | mean error |
|---|---|---|---|---|---|
| aces | 1 | 45 s (0.03) | - | 1 / 1 ms | 0.036 m, 0.31 deg |
| aces | 4 | 189 s (0.14) | 4.2x | 2 / 6 ms | 0.039 m, 0.31 deg |"""


def load_results_module() -> ModuleType:
    """benchmarks/results.py as the benchmarks import it (a script beside them, not a package)."""
    spec = importlib.util.spec_from_file_location("benchmark_results", RESULTS_PY)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


results = load_results_module()


def git(root: Path, *args: str) -> str:
    command = ["git", "-c", "user.name=bench", "-c", "user.email=bench@example.org", *args]
    return subprocess.run(command, cwd=root, capture_output=True, text=True, check=True).stdout.strip()


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    """A git checkout with a committed benchmark script, as the benchmarks' own checkout is."""
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "growth.py").write_text("print('growth')\n")
    git(tmp_path, "init", "-q")
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "growth")
    return tmp_path


def write_growth(root: Path) -> Path:
    argv = [str(root / "benchmarks" / "growth.py"), "--copies", "1,4", "--write-results"]
    return results.write_result(
        "growth", "Growth (`benchmarks/growth.py`)", BODY, config=FleetmapConfig(), root=root, argv=argv
    )


def test_a_written_result_renders_into_results_md(checkout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    head = git(checkout, "rev-parse", "HEAD")
    path = write_growth(checkout)
    assert path == checkout / "benchmarks" / "results" / "growth.json"
    result = json.loads(path.read_text())
    assert (result["section"], result["commit"], result["dirty"]) == ("growth", head, False)
    assert result["command"] == "python benchmarks/growth.py --copies 1,4 --write-results"
    canonical = json.dumps(FleetmapConfig().to_dict(), sort_keys=True, separators=(",", ":"))
    assert result["config_hash"] == hashlib.sha256(canonical.encode()).hexdigest()
    assert results.config_hash(tuned(FleetmapConfig(), max_speed=1.0)) != result["config_hash"]
    # the figures are the table's numbers, keyed by column and unit
    rows = result["figures"][0]["rows"]
    assert rows[0] == {
        "log": "aces",
        "tours": 1,
        "time_s": 45,
        "share_of_log": 0.03,
        "against_one_tour": None,
        "step_time_first_ms": 1,
        "last_ms": 1,
        "mean_error_m": 0.036,
        "mean_error_deg": 0.31,
    }
    assert (rows[1]["time_s"], rows[1]["against_one_tour_x"], rows[1]["last_ms"]) == (189, 4.2, 6)

    # the result file itself is not an uncommitted change that stops the render
    assert results.main(["render", "--checkout", str(checkout)]) == 0
    text = (checkout / "benchmarks" / "RESULTS.md").read_text()
    assert f"Every section from commit {head[:7]}." in text
    line = f"`python benchmarks/growth.py --copies 1,4 --write-results` on {result['date']}, commit {head[:7]}, config "
    assert f"<!-- section: growth -->\n## Growth (`benchmarks/growth.py`)\n\n{line}" in text
    assert text.endswith(BODY + "\n")


def test_render_refuses_uncommitted_changes_and_dirty_results(
    checkout: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (checkout / "benchmarks" / "growth.py").write_text("print('growth, changed')\n")
    assert json.loads(write_growth(checkout).read_text())["dirty"] is True

    assert results.main(["render", "--checkout", str(checkout)]) == 2
    assert "uncommitted changes in benchmarks/growth.py" in capsys.readouterr().err

    git(checkout, "commit", "-q", "-am", "growth, changed")  # committed now, but the result was not run on it
    assert results.main(["render", "--checkout", str(checkout)]) == 2
    err = capsys.readouterr().err
    assert "growth.json" in err and "uncommitted changes" in err
    assert not (checkout / "benchmarks" / "RESULTS.md").exists()


def test_a_malformed_result_is_named(checkout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_growth(checkout)
    result = json.loads(path.read_text())
    del result["commit"]
    path.write_text(json.dumps(result))
    assert results.main(["render", "--checkout", str(checkout)]) == 2
    assert f"{path}: field 'commit' missing or not a str" in capsys.readouterr().err


TINY = """import sys
from results import write_result

if __name__ == "__main__":
    write_result("tiny", "Tiny (`benchmarks/tiny.py`)", "| n |\\n|---|\\n| 7 |", config=None)
"""


def test_regenerate_reruns_every_section_at_the_checkout_s_commit_and_renders(tmp_path: Path) -> None:
    bench = tmp_path / "benchmarks"
    bench.mkdir()
    for script in ("results.py", "regenerate.py"):
        (bench / script).write_text((RESULTS_PY.parent / script).read_text())
    (bench / "tiny.py").write_text(TINY)
    (tmp_path / ".gitignore").write_text("__pycache__/\n")  # as the project's own: Python's byte-code is no change
    git(tmp_path, "init", "-q")
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "tiny")
    # a result from an older, changed checkout: what regenerating replaces
    old = results.write_result(
        "tiny", "Tiny", "| n |\n|---|\n| 6 |", config=None, root=tmp_path, argv=[str(bench / "tiny.py")]
    )
    stale = json.loads(old.read_text())
    old.write_text(json.dumps({**stale, "commit": "0" * 40, "dirty": True}))
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "an old result")
    head = git(tmp_path, "rev-parse", "HEAD")

    done = subprocess.run(
        [sys.executable, str(bench / "regenerate.py")], cwd=tmp_path, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(old.read_text())
    assert (result["commit"], result["dirty"], result["figures"][0]["rows"]) == (head, False, [{"n": 7}])
    assert f"Every section from commit {head[:7]}." in (bench / "RESULTS.md").read_text()

    # a checkout with uncommitted changes is refused before anything runs
    (bench / "tiny.py").write_text(TINY + "\n")
    done = subprocess.run(
        [sys.executable, str(bench / "regenerate.py")], cwd=tmp_path, capture_output=True, text=True, check=False
    )
    assert done.returncode == 2 and "uncommitted changes in benchmarks/tiny.py" in done.stderr
