"""Benchmark: a scenario session without processes or a bus (run on demand, not in CI).

Every robot's agent runs on its scans; their messages go, in stamp order, through one merger
(:class:`fleetmap.merger.engine.Merger`), which takes a step every ``--step`` scenario seconds; the
session is then scored exactly as ``fleetmap run`` scores a live one (:mod:`fleetmap.report`). The
result depends on nothing but the scenario and the config, so two versions of the code can be
compared run for run. A live session's merger falls behind when integration is slow, so its
figures (relocalization scans above all) can only be worse than these.

Also printed, per robot, from the agents alone: epochs, scans left unplaced, and scans placed more
than 0.3 m or 3 degrees from where the truth puts them in their epoch (a wrong local map).

    python benchmarks/offline.py                       # every bundled scenario
    python benchmarks/offline.py office-events --step 0.5
    python benchmarks/offline.py --write-results       # and write its result (benchmarks/results/)
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

from fleetmap.agents.agent import Agent
from fleetmap.merger.engine import Merger
from fleetmap.scenarios import load_scenario, robot_stream
from fleetmap.scenarios.fleet import Scenario
from fleetmap.scenarios.loader import list_scenarios
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import FleetEvent, Message, decode
from results import markdown_table, write_result

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.report import SessionLog, build_report, make_truth, summary_table

WRONG_M, WRONG_DEG = 0.3, 3.0


AgentRun = tuple[str, int, int, int, float]
"""A robot, its epochs, its scans left unplaced and placed wrongly, and its agent's seconds."""


def run_agents(
    name: str, scenario: Scenario, config: FleetmapConfig
) -> tuple[list[tuple[float, int, Message]], list[AgentRun]]:
    """Every robot's agent on its scans, a line each printed: their messages (stamp, robot's number, message)."""
    messages: list[tuple[float, int, Message]] = []
    agents: list[AgentRun] = []
    for n, robot in enumerate(scenario.robot_ids):
        agent = Agent(robot, config)
        truth: dict[int, Transform2D] = {}
        frames: dict[int, Transform2D] = {}
        unplaced = wrong = 0
        start = time.perf_counter()
        for s in [*robot_stream(scenario, robot), None]:  # (None: the end; what waited comes then)
            if s is None:
                stamp, out = math.inf, agent.finish()
            else:
                truth[s.index] = s.pose
                stamp, out = s.stamp, agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
            for m in out:
                messages.append((stamp, n, m))
                if isinstance(m, FleetEvent) and m.kind == "epoch":
                    detail = json.loads(m.detail)
                    frames[detail["epoch"]] = truth[detail["first_scan"]]
            for index, epoch, pose in agent.tracked:  # (the log's first scan waits for the second)
                if pose is None:
                    unplaced += 1
                    continue
                frame = frames.setdefault(epoch, truth[index])
                dt, dr = pose.distance(frame.inverse().compose(truth[index]))
                wrong += dt > WRONG_M or math.degrees(dr) > WRONG_DEG
        seconds = time.perf_counter() - start
        agents.append((robot, agent.counts.epochs, unplaced, wrong, seconds))
        print(
            f"{name} {robot}: epochs {agent.counts.epochs}, unplaced {unplaced}, placed wrongly {wrong}, "
            f"agent {seconds:.1f} s",
            flush=True,
        )
    return messages, agents


def run_merger(
    messages: list[tuple[float, int, Message]],
    config: FleetmapConfig,
    step: float,
    start_poses: dict[str, Transform2D] | None = None,
) -> tuple[SessionLog, float]:
    """The agents' messages in stamp order through one merger taking a step every ``step`` seconds
    (given the robots' ``start_poses``, if any); its seconds."""
    messages.sort(key=lambda x: (x[0], x[1]))
    keys = FleetKeys()
    merger = Merger(keys, config, start_poses=start_poses)
    log = SessionLog()
    start = time.perf_counter()
    due = step

    def take_step() -> None:
        for o in merger.step():
            log.add(decode(o.payload))

    for stamp, _, m in messages:
        while stamp >= due and math.isfinite(stamp):
            take_step()
            due += step
        log.add(m)
        merger.take(m)
    take_step()
    while merger.has_work:  # what a live merger does after the robots stop
        take_step()
    return log, time.perf_counter() - start


def run(name: str, config: FleetmapConfig, step: float) -> tuple[list[AgentRun], dict[str, Any], float]:
    """One scenario, printed as it goes: its agents' lines, its report and the merger's seconds."""
    scenario = load_scenario(name)
    messages, agents = run_agents(name, scenario, config)
    log, seconds = run_merger(messages, config, step)
    print(f"{name}: merger {seconds:.1f} s")
    report = build_report(log, make_truth(scenario))
    print(summary_table(report), flush=True)
    return agents, report, seconds


ROBOTS_EXPLAINED = (
    "Every bundled scenario without processes or a bus: each robot's agent on its scans, their messages in "
    "stamp order through one merger taking a step every `--step` scenario seconds, scored as `fleetmap run` "
    "scores a live session. Per robot, from its agent alone: epochs, scans left unplaced, scans placed more "
    f"than {WRONG_M} m or {WRONG_DEG:g} deg from where the truth puts them in their epoch, and the agent's "
    "seconds; from the session's report: whether its latest epoch is in the global map's largest component, "
    "and the error of its last pose."
)
SCENARIOS_EXPLAINED = (
    "Per scenario: robots placed, the global map's error against the true walls (mean, 95th percentile, and "
    "laid best on the walls first), its coverage of the walls the robots could see, its components, the "
    "local maps merged wrongly, each kidnap (scans and seconds to relocalize, and the pose error then), and "
    "the merger's seconds."
)

ROBOTS_HEADER = ["scenario", "robot", "epochs", "unplaced", "placed wrongly", "agent", "placed", "pose error"]
HEADER = [
    "scenario",
    "robots placed",
    "map error mean",
    "p95",
    "aligned",
    "coverage",
    "components",
    "maps merged wrongly",
    "kidnaps",
    "merger",
]


def _m(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f} m"


def _kidnap(k: dict[str, Any]) -> str:
    if not k["relocalized"]:
        return f"{k['robot']} at {k['time']:.1f} s: NOT relocalized"
    done = f"{k['scans_to_relocalize']} scans, {k['seconds_to_relocalize']:.1f} s"
    return f"{k['robot']} at {k['time']:.1f} s: {done}, error {_m(k['pose_error_m'])}"


def robot_cells(name: str, agent: AgentRun, report: dict[str, Any]) -> list[str]:
    robot, epochs, unplaced, wrong, seconds = agent
    r = report["robots"].get(robot, {})
    error = f"{r['error_m']:.3f} m, {r['error_deg']:.2f} deg" if "error_m" in r else "-"
    placed = "yes" if r.get("placed") else "no"
    return [name, robot, str(epochs), str(unplaced), str(wrong), f"{seconds:.1f} s", placed, error]


def scenario_cells(name: str, report: dict[str, Any], seconds: float) -> list[str]:
    coverage = "n/a" if report["coverage"] is None else f"{100 * report['coverage']:.1f} %"
    wrong = report.get("maps_merged_wrongly")
    return [
        name,
        f"{report['robots_placed']} / {report['robots_total']}",
        _m(report["map_error_mean_m"]),
        _m(report["map_error_p95_m"]),
        _m(report.get("map_error_aligned_mean_m")),
        coverage,
        str(len(report["components"])),
        "n/a" if wrong is None else f"{len(wrong)}" + (f" ({', '.join(wrong)})" if wrong else ""),
        "; ".join(_kidnap(k) for k in report["kidnaps"]) or "-",
        f"{seconds:.1f} s",
    ]


def tables(runs: list[tuple[str, list[AgentRun], dict[str, Any], float]]) -> str:
    """The agents' lines and the reports as two markdown tables, each after its paragraph."""
    robots = [robot_cells(name, a, report) for name, agents, report, _ in runs for a in agents]
    scenarios = [scenario_cells(name, report, seconds) for name, _, report, seconds in runs]
    return "\n\n".join(
        [
            ROBOTS_EXPLAINED,
            markdown_table(ROBOTS_HEADER, robots),
            SCENARIOS_EXPLAINED,
            markdown_table(HEADER, scenarios),
        ]
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="*", help=f"bundled names (default: all of {', '.join(list_scenarios())})")
    ap.add_argument("--step", type=float, default=1.0, help="scenario seconds between merger steps")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    add_config_arguments(ap, ["extraction", "integration", "merge", "tracking"])
    args = ap.parse_args()
    config = config_from_args(args)
    runs = [(name, *run(name, config, args.step)) for name in args.scenarios or list_scenarios()]
    if args.write_results:
        write_result(
            "offline", "Scenarios without processes or a bus (`benchmarks/offline.py`)", tables(runs), config=config
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
