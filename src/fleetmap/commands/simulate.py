"""``fleetmap simulate``: a scenario's scans and ground truth, written for offline scoring."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.scenarios.fleet import Scenario
from fleetmap.scenarios.loader import DEFAULT_SCENARIO, list_scenarios, load_scenario, scenario_to_toml
from fleetmap.scenarios.stream import robot_stream
from fleetmap.scenarios.truth import ground_truth
from fleetmap.shared.config import ExtractionParams
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.errors import BadInput

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a scenario's laser scans and write them with the ground truth",
        description="Simulate every robot of a scenario and write, in OUT: <robot>/scans.jsonl (ranges JSONL), "
        "<robot>/segments.jsonl (as fleetmap extract writes it), truth.json (walls, every scan's true pose, "
        "the events and the visible wall parts), scenario.toml (the resolved scenario) and config.toml (the "
        f"extraction config used). Bundled scenarios: {', '.join(list_scenarios())}.",
    )
    p.add_argument("scenario", nargs="?", default=DEFAULT_SCENARIO, help="a bundled scenario name or a .toml file")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
    add_config_arguments(p, ["extraction"])
    p.set_defaults(func=run)


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise BadInput(str(path), f"cannot write: {exc.strerror}") from None


def _mkdir(path: Path) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise BadInput(str(path), "exists and is not a folder") from None
    except OSError as exc:
        raise BadInput(str(path), f"cannot create the folder: {exc.strerror}") from None


def write_robot(scenario: Scenario, robot_id: str, folder: Path, extraction: ExtractionParams) -> tuple[int, int]:
    """The robot's scans and segments as JSONL files; returns (scans, segments)."""
    scans, segments = [], []
    total = 0
    for s in robot_stream(scenario, robot_id):
        seg = extract_segments(s.scan, extraction)
        total += len(seg)
        scans.append(json.dumps(s.scan.to_json_dict()))
        segments.append(json.dumps({"stamp": s.stamp, "segments": seg.round(6).tolist(), "ordered": True}))
    _mkdir(folder)
    _write(folder / "scans.jsonl", "".join(line + "\n" for line in scans))
    _write(folder / "segments.jsonl", "".join(line + "\n" for line in segments))
    return len(scans), total


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    scenario = load_scenario(args.scenario)
    out = Path(args.out)
    _mkdir(out)
    start = time.perf_counter()
    truth = ground_truth(scenario)
    rows = []
    for robot in scenario.robots:
        n_scans, n_segments = write_robot(scenario, robot.id, out / robot.id, config.extraction)
        events = ", ".join(f"{e.kind}@{e.t:g}" for e in scenario.robot_events(robot.id))
        rows.append((robot.id, n_scans, n_segments, events or "-"))
    _write(out / "truth.json", json.dumps(truth.to_json_dict()) + "\n")
    _write(out / "scenario.toml", scenario_to_toml(scenario))
    _write(out / "config.toml", config.to_toml())
    log.info("simulated %s in %.2f s", scenario.name, time.perf_counter() - start)
    print(f"{scenario.name}: world {scenario.world.name}, {len(scenario.world.walls)} walls -> {out}")
    print(f"{'robot':<10} {'scans':>6} {'segments':>9}  events")
    for rid, n_scans, n_segments, events in rows:
        print(f"{rid:<10} {n_scans:>6} {n_segments:>9}  {events}")
    return 0
