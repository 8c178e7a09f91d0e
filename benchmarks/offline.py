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
"""

from __future__ import annotations

import argparse
import json
import math
import time

from fleetmap.agents.agent import Agent
from fleetmap.merger.engine import Merger
from fleetmap.scenarios import load_scenario, robot_stream
from fleetmap.scenarios.loader import list_scenarios
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import FleetEvent, LocalMap, Message, decode

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.report import SessionLog, build_report, make_truth, summary_table

WRONG_M, WRONG_DEG = 0.3, 3.0


def run(name: str, config: FleetmapConfig, step: float) -> None:
    scenario = load_scenario(name)
    keys = FleetKeys()
    messages: list[tuple[float, int, Message]] = []
    for n, robot in enumerate(scenario.robot_ids):
        agent = Agent(robot, config)
        truth: dict[int, Transform2D] = {}
        frames: dict[int, Transform2D] = {}
        unplaced = wrong = 0
        start = time.perf_counter()
        for s in robot_stream(scenario, robot):
            truth[s.index] = s.pose
            out = agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
            for m in out:
                messages.append((s.stamp, n, m))
                if isinstance(m, FleetEvent) and m.kind == "epoch":
                    detail = json.loads(m.detail)
                    frames[detail["epoch"]] = truth[detail["first_scan"]]
            pose = agent.epoch_pose
            if pose is None:
                unplaced += 1
                continue
            frame = frames.setdefault(agent.epoch, s.pose)
            dt, dr = pose.distance(frame.inverse().compose(s.pose))
            wrong += dt > WRONG_M or math.degrees(dr) > WRONG_DEG
        messages += [(math.inf, n, m) for m in agent.finish()]
        print(
            f"{name} {robot}: epochs {agent.counts.epochs}, unplaced {unplaced}, placed wrongly {wrong}, "
            f"agent {time.perf_counter() - start:.1f} s",
            flush=True,
        )
    messages.sort(key=lambda x: (x[0], x[1]))
    merger = Merger(keys, config)
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
        key = keys.localmap(m.robot) if isinstance(m, LocalMap) else keys.prefix
        merger.receive(key, m.to_msgpack())
    take_step()
    while merger.has_work:  # what a live merger does after the robots stop
        take_step()
    print(f"{name}: merger {time.perf_counter() - start:.1f} s")
    print(summary_table(build_report(log, make_truth(scenario))), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="*", help=f"bundled names (default: all of {', '.join(list_scenarios())})")
    ap.add_argument("--step", type=float, default=1.0, help="scenario seconds between merger steps")
    add_config_arguments(ap, ["extraction", "integration", "merge", "tracking"])
    args = ap.parse_args()
    config = config_from_args(args)
    for name in args.scenarios or list_scenarios():
        run(name, config, args.step)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
