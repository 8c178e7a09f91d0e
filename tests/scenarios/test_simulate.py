"""``fleetmap simulate``: scans, segments and truth written as the contracts say, bad scenarios refused."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fleetmap.scenarios.fleet import plan
from fleetmap.scenarios.loader import load_scenario, read_scenario
from fleetmap.scenarios.metrics import map_error
from fleetmap.shared.config_files import load_config
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.logs import read_ranges_jsonl

from fleetmap.cli import main

WriteScenario = Callable[..., Path]


@pytest.mark.slow  # simulates a whole scenario to files (a few seconds)
def test_simulate_writes_scans_segments_truth_and_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sim"
    assert main(["simulate", "department-events", "--out", str(out)]) == 0
    sc = load_scenario("department-events")
    assert "r4" in capsys.readouterr().out
    truth = json.loads((out / "truth.json").read_text())
    np.testing.assert_allclose(truth["world"]["walls"], sc.world.walls, atol=1e-6)
    assert {e["type"] for e in truth["events"]} == {"join", "leave", "crash", "kidnap"}
    for robot in sc.robots:
        planned = plan(sc, robot.id)
        scans = list(read_ranges_jsonl(out / robot.id / "scans.jsonl"))  # the contract's ranges JSONL
        lines = [json.loads(x) for x in (out / robot.id / "segments.jsonl").read_text().splitlines()]
        poses = [x for x in truth["scans"] if x["robot"] == robot.id]
        assert len(scans) == len(lines) == len(poses) == len(planned)
        assert [s.stamp for s in scans] == [x["stamp"] for x in lines] == [p.stamp for p in planned]
        assert all(set(x) == {"stamp", "segments", "ordered"} and x["ordered"] is True for x in lines)
        # Segments carried into the world by the true pose lie on the true walls.
        world = [
            Transform2D(**p["pose"]).apply(np.array(x["segments"]).reshape(-1, 4))
            for p, x in zip(poses, lines, strict=True)
        ]
        assert map_error(np.vstack(world), sc.world.walls).p95 < 0.03
    assert read_scenario(out / "scenario.toml").robots == sc.robots
    assert load_config(out / "config.toml").extraction.tau == 0.2


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_simulate_segments_are_what_extract_gives_for_the_scans(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    assert main(["simulate", "office", "--out", str(out), "--kappa", "0.03"]) == 0
    extracted = tmp_path / "extracted.jsonl"
    scans = out / "r2" / "scans.jsonl"
    assert (
        main(
            [
                "extract",
                str(scans),
                "--format",
                "ranges-jsonl",
                "--out",
                str(extracted),
                "--config",
                str(out / "config.toml"),
            ]
        )
        == 0
    )
    assert extracted.read_text() == (out / "r2" / "segments.jsonl").read_text()
    assert load_config(out / "config.toml").extraction.kappa == 0.03


def test_a_bad_scenario_exits_2_with_one_line_naming_file_and_field(
    scenario_file: WriteScenario, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = scenario_file(('robot = "r2"', 'robot = "r7"'))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "events[1].robot" in err[0] and "r7" in err[0]
    assert main(["simulate", "nowhere", "--out", str(tmp_path / "o")]) == 2
    assert "unknown scenario" in capsys.readouterr().err
