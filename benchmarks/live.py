"""Benchmark: the live fleet end to end (run on demand, not in CI).

For N = 1, 4 and 16 robots (the first N of the department-16 scenario: sixteen robots on the
Section V loop, from sixteen places, both ways round), a real session runs: router, merger,
recorder and N agent processes on loopback, agents at ``--speed`` times real time (1: 5 Hz
scans). From the recording it prints:

- scans per second through the bus (Scan messages recorded / the time between first and last),
- the merger's end-to-end latency: from a local map version's arrival at the recorder to the
  arrival of the merger step that integrated it (median and 95th percentile; versions superseded
  before the merger took them are not counted, which is the point of its coalescing),
- the merger's catch-up: from the last scan's arrival to that of the merger's last step that did
  anything (took a local map version or integrated a pair): the session's end (the runner's
  waits, the merger's idle steps) does not count; 0 where it had nothing left after the last scan,
- the recorder's throughput (all messages and bytes over the session),
- the CPU time of each kind of process (its children included: the merger's integration
  workers count as the merger's), sampled from /proc, as a share of one core over the session.

With ``--ros2``, each fleet also runs with its robots on ROS 2 topics over rmw_zenoh: each robot's
simulated scans and odometry are written as a bag, played by ``fleetmap play --ros2`` under the
robot's namespace and heard by ``fleetmap agent --ros2`` (``Session(ros2=True)``), and the table
sets its figures against the fleet whose agents simulate their own scans (today's path). The CPU
of the ROS 2 path is its agents' (decoding CDR, waiting for odometry) against today's agents'
less the simulation they do themselves (measured here, alone, in this process); the players'
(reading the bag, encoding, publishing: the robot's side) are given apart.

With ``--secure``, each fleet also runs with authentication and access control
(``fleetmap secure``) and over mutual TLS, and the table gives their throughput and latency
against the open fleet's.

    python benchmarks/live.py                 # 1, 4 and 16 robots
    python benchmarks/live.py --robots 4 --speed 8
    python benchmarks/live.py --robots 4 --speed 1 --secure --write-results
    python benchmarks/live.py --robots 16 --speed 1 --runs 3 --executor inline,local
    python benchmarks/live.py --robots 16 --speed 1 --runs 2 --executor inline --ros2 --write-results
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from fleetmap.agents.agent import Agent
from fleetmap.agents.ros2_source import Ros2LiveSource, Ros2Topics
from fleetmap.scenarios import load_scenario
from fleetmap.scenarios.stream import robot_stream
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.messages import BadMessage, MergerStep
from fleetmap.shared.io.messages import decode as decode_message
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.sources import Ros2BagSource
from results import write_result

from fleetmap.report import merge_latencies
from fleetmap.ros2_robots import write_robot_bag
from fleetmap.runner import Session

MODES = {"open": {}, "auth": {"secure": True}, "tls": {"secure": True, "tls": True}}
"""How the fleet's sessions meet: open, logged in with access control, and that over mutual TLS."""


def fleet_scenario(n: int):  # type: ignore[no-untyped-def]
    base = load_scenario("department-16")
    if n > len(base.robots):
        raise SystemExit(f"--robots: department-16 has {len(base.robots)} robots, asked for {n}")
    return dataclasses.replace(base, name=f"department-16-first{n}", robots=base.robots[:n], events=())


ROLES = ("merger", "agent", "record", "router", "play")
TICK = os.sysconf("SC_CLK_TCK")


class CpuSampler(threading.Thread):
    """CPU seconds of the processes under this one, by role (the fleetmap command of the child of
    this process it descends from), sampled from /proc every half second: a process's last sample
    counts (an agent that ends loses at most half a second)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.stop = threading.Event()
        self._ticks: dict[int, tuple[str, int]] = {}

    def run(self) -> None:
        while not self.stop.wait(0.5):
            self.sample()

    def sample(self) -> None:
        parents: dict[int, int] = {}
        ticks: dict[int, int] = {}
        for name in os.listdir("/proc"):
            if not name.isdigit():
                continue
            try:
                with open(f"/proc/{name}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents[int(name)] = int(fields[1])
            ticks[int(name)] = int(fields[11]) + int(fields[12])
        me = os.getpid()
        for pid in ticks:
            top, p = pid, parents.get(pid)
            while p is not None and p != me and p > 1:
                top, p = p, parents.get(p)
            if p != me:
                continue
            role = self._ticks.get(pid, (None, 0))[0] or _role(top)
            if role is not None:
                self._ticks[pid] = (role, ticks[pid])

    def seconds(self) -> dict[str, float]:
        out: dict[str, float] = defaultdict(float)
        for role, t in self._ticks.values():
            out[role] += t / TICK
        return dict(out)


def _role(pid: int) -> str | None:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            argv = fh.read().split(b"\0")
    except OSError:
        return None
    for role in ROLES:
        if role.encode() in argv[3:4]:
            return role
    return None


def simulation_cpu_s(n: int) -> float:
    """CPU seconds the first ``n`` robots' simulation takes alone (today's agents do it themselves)."""
    scenario = fleet_scenario(n)
    start = time.process_time()
    for robot in scenario.robots:
        for _ in robot_stream(scenario, robot.id):
            pass
    return time.process_time() - start


def decoding_cost(n: int) -> dict[str, float]:
    """CPU seconds, in this process alone, of the first ``n`` robots' scans through the ROS 2 source
    (the samples ``fleetmap play`` puts, decoded and paired with their odometry by
    :class:`Ros2LiveSource`) and through the agent's mapping, and of their simulation (what today's
    agents run instead of the decoding)."""
    scenario = fleet_scenario(n)
    attachment = wire.Attachment(1, 0, bytes(wire.GID_SIZE)).pack()
    decode = mapping = 0.0
    scans = 0
    with tempfile.TemporaryDirectory() as tmp:
        for robot in scenario.robots:
            write_robot_bag(scenario, robot.id, Path(tmp) / robot.id)
            bag = Ros2BagSource(Path(tmp) / robot.id)
            topics = Ros2Topics.of(robot.id)
            names = {"/scan": topics.scan, "/odom": topics.odom, "/tf_static": topics.tf_static}
            samples = []
            for topic, _, message in bag.messages(sorted(names)):
                typename = (
                    wire.TF_MESSAGE if topic == "/tf_static" else wire.LASER_SCAN if topic == "/scan" else wire.ODOMETRY
                )
                key = wire.data_key(0, names[topic], typename)
                samples.append((names[topic], key, wire.encode(message, typename), attachment))
            source = Ros2LiveSource(None, topics, threading.Event(), robot.id)
            wire.typestore()  # built once per agent: a fixed cost, not a scan's
            start = time.process_time()
            released = [s for sample in samples for s in source.feed(*sample)]
            decode += time.process_time() - start
            agent = Agent(robot.id, FleetmapConfig(), odometry=True)
            start = time.process_time()
            for s in released:
                agent.add_scan(s.index, s.stamp, s.scan, s.odometry)
            mapping += time.process_time() - start
            scans += len(released)
    return {"scans": scans, "decode_s": decode, "mapping_s": mapping, "simulation_s": simulation_cpu_s(n)}


def last_working_step(messages: list[tuple[bytes, int]]) -> int | None:
    """The log time of the merger's last step that took a local map version or integrated a pair
    (None: no step did)."""
    last = None
    for payload, log_time in messages:
        try:
            message = decode_message(payload)
        except BadMessage:
            continue
        if isinstance(message, MergerStep) and (message.maps or message.integrations):
            last = log_time
    return last


def measure(
    n: int, speed: float, out: Path, mode: str = "open", executor: str = "local", ros2: bool = False
) -> dict[str, float | str]:
    load = os.getloadavg()[0]
    session = Session(
        fleet_scenario(n),
        out,
        FleetmapConfig(),
        speed=speed,
        fleet="bench",
        progress=False,
        merger_options=("--executor", executor),
        ros2=ros2,
        **MODES[mode],
    )
    sampler = CpuSampler()
    sampler.start()
    start = time.monotonic()
    try:
        report = session.run()
    finally:
        sampler.stop.set()
        sampler.join()
    wall = time.monotonic() - start
    cpu = sampler.seconds()
    scans: list[int] = []
    timed: list[tuple[bytes, int]] = []
    poses = total = size = 0
    with RecordingReader(out / "session.mcap") as reader:
        for m in reader.messages():
            total += 1
            size += len(m.payload)
            timed.append((m.payload, m.log_time))
            if m.topic.endswith("/scan"):
                scans.append(m.log_time)
            elif m.topic.endswith("/pose"):
                poses += 1
    latency = merge_latencies(timed)
    span = (max(scans) - min(scans)) / 1e9 if len(scans) > 1 else float("nan")
    worked = last_working_step(timed)
    catch_up = max(0.0, (worked - max(scans)) / 1e9) if scans and worked is not None else float("nan")
    return {
        "robots": n,
        "mode": mode,
        "feed": "ros2" if ros2 else "sim",
        "load": (load + os.getloadavg()[0]) / 2,
        "executor": executor,
        "scans": len(scans),
        "scans_per_s": len(scans) / span if span > 0 else float("nan"),
        "poses_per_s": poses / span if span > 0 else float("nan"),
        "latency_median_s": float(np.median(latency)) if latency else float("nan"),
        "latency_p95_s": float(np.percentile(latency, 95)) if latency else float("nan"),
        "catch_up_s": catch_up,
        "messages": total,
        "messages_per_s": total / wall,
        "mb_per_s": size / wall / 1e6,
        "wall_s": wall,
        "map_error_mean_m": report["map_error_mean_m"] or float("nan"),
        "map_error_aligned_m": report["map_error_aligned_mean_m"] or float("nan"),
        "placed": report["robots_placed"],
        "dropped": report["messages_seen"] - report["messages_recorded"],
        **{f"cpu_{role}": cpu.get(role, 0.0) / wall for role in ROLES},
        **{f"cpu_s_{role}": cpu.get(role, 0.0) for role in ROLES},
    }


def ros2_lines(rows: list[dict[str, float | str]], robots: str) -> list[str]:
    """The ROS 2 path against today's: each session, then the medians' ratios by fleet size."""
    lines = [
        "| robots | robots fed by | executor | scans | latency median | latency p95 | merger catch-up | placed "
        "| CPU s: agents / players / merger / recorder / router | load (1 min) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['robots']} | {'ROS 2 topics' if r['feed'] == 'ros2' else 'own simulation'} | {r['executor']} "
            f"| {r['scans']} | {r['latency_median_s']:.2f} s | {r['latency_p95_s']:.2f} s | {r['catch_up_s']:.1f} s "
            f"| {r['placed']}/{r['robots']} | {r['cpu_s_agent']:.1f} / {r['cpu_s_play']:.1f} / {r['cpu_s_merger']:.1f} "
            f"/ {r['cpu_s_record']:.1f} / {r['cpu_s_router']:.1f} | {r['load']:.1f} |"
        )
    lines += [
        "",
        "ROS 2 against today's path (medians over the sessions of each kind; agents' CPU: the ROS 2 agents' "
        "against today's less the simulation they run, measured alone):",
        "",
        "| robots | latency median (ROS 2 / today) | catch-up (ROS 2 / today) | simulation CPU s | "
        "agents' CPU s (ROS 2 / today less simulation) | ratio |",
        "|---|---|---|---|---|---|",
    ]
    per_scan: list[tuple[int, dict[str, float]]] = []
    for n in (int(x) for x in robots.split(",")):

        def med(feed: str, field: str, n: int = n) -> float:
            return float(np.median([float(r[field]) for r in rows if r["robots"] == n and r["feed"] == feed]))

        cost = decoding_cost(n)
        simulation = cost["simulation_s"]
        today = med("sim", "cpu_s_agent") - simulation
        per_scan.append((n, cost))
        lines.append(
            f"| {n} | {med('ros2', 'latency_median_s'):.2f} s / {med('sim', 'latency_median_s'):.2f} s "
            f"| {med('ros2', 'catch_up_s'):.1f} s / {med('sim', 'catch_up_s'):.1f} s | {simulation:.2f} "
            f"| {med('ros2', 'cpu_s_agent'):.1f} / {today:.1f} | {med('ros2', 'cpu_s_agent') / today:.2f} |"
        )
    lines += [
        "",
        "Per scan, in one process alone (CPU time, so the machine's other load hardly counts): the ROS 2 "
        "source (CDR decoding, the attachment, pairing with odometry) against the agent's mapping of the "
        "same scans, and the simulation today's agents run instead:",
        "",
        "| robots | scans | ROS 2 source ms/scan | mapping ms/scan | source / mapping | simulation ms/scan |",
        "|---|---|---|---|---|---|",
    ]
    for n, cost in per_scan:
        k = 1e3 / cost["scans"]
        lines.append(
            f"| {n} | {cost['scans']:.0f} | {cost['decode_s'] * k:.3f} | {cost['mapping_s'] * k:.2f} "
            f"| {cost['decode_s'] / cost['mapping_s']:.3f} | {cost['simulation_s'] * k:.3f} |"
        )
    lines += [
        "",
        f"CPU s: seconds of CPU over the session, by kind of process (this machine has {os.cpu_count()} cores); "
        "players: `fleetmap play --ros2`, the robots' side. Load: the machine's 1-minute load average over the "
        "session; another CPU-heavy benchmark may have run beside it, so compare the ratios of sessions run in "
        "turn rather than absolute figures.",
    ]
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", default="1,4,16")
    ap.add_argument("--speed", type=float, default=1000.0, help="scenario speed (1000: as fast as they can)")
    ap.add_argument("--secure", action="store_true", help="also with authentication and with mutual TLS")
    ap.add_argument("--ros2", action="store_true", help="also with the robots on ROS 2 topics (play -> agent --ros2)")
    ap.add_argument("--executor", default="local", help="the merger's executors to compare (comma-separated)")
    ap.add_argument("--runs", type=int, default=1, help="sessions of each kind (a live merger's steps vary)")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    ap.add_argument("--out", metavar="DIR", help="keep each session's folder (logs, recording) under DIR")
    args = ap.parse_args()
    modes = list(MODES) if args.secure else ["open"]
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.out or scratch
        for n in (int(x) for x in args.robots.split(",")):
            for mode in modes:
                for executor in args.executor.split(","):
                    for run in range(args.runs):
                        # today's path and the ROS 2 one in turn: the machine's other load falls on both
                        for ros2 in (False, True) if args.ros2 else (False,):
                            where = Path(tmp) / f"n{n}-{mode}-{executor}-{run}{'-ros2' if ros2 else ''}"
                            r = measure(n, args.speed, where, mode, executor, ros2)
                            rows.append(r)
                            print(r, flush=True)
    lines = [
        "| robots | fleet | executor | scans/s | poses/s | latency median | latency p95 | merger catch-up "
        "| recorder msg/s | dropped | placed | map error (aligned) | CPU merger / agents / recorder / router |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['robots']} | {r['mode']} | {r['executor']} | {r['scans_per_s']:.1f} | {r['poses_per_s']:.1f} "
            f"| {r['latency_median_s']:.2f} s | {r['latency_p95_s']:.2f} s | {r['catch_up_s']:.1f} s "
            f"| {r['messages_per_s']:.0f} | {r['dropped']} | {r['placed']}/{r['robots']} "
            f"| {r['map_error_mean_m']:.3f} m ({r['map_error_aligned_m']:.3f} m) "
            f"| {r['cpu_merger']:.2f} / {r['cpu_agent']:.2f} / {r['cpu_record']:.2f} "
            f"/ {r['cpu_router']:.2f} |"
        )
    if args.runs > 1:
        lines += ["", f"Medians over {args.runs} runs:", ""]
        lines += ["| robots | fleet | executor | latency median | latency p95 | catch-up | map error (aligned) |"]
        lines += ["|---|---|---|---|---|---|---|"]
        kinds = sorted({(r["robots"], r["mode"], r["executor"]) for r in rows}, key=lambda k: (k[0], k[1], k[2]))
        for kind in kinds:
            same = [r for r in rows if (r["robots"], r["mode"], r["executor"]) == kind]

            def med(field: str, same: list[dict[str, float | str]] = same) -> float:
                return float(np.median([float(r[field]) for r in same]))

            lines.append(
                f"| {kind[0]} | {kind[1]} | {kind[2]} | {med('latency_median_s'):.2f} s | {med('latency_p95_s'):.2f} s "
                f"| {med('catch_up_s'):.1f} s | {med('map_error_mean_m'):.3f} m ({med('map_error_aligned_m'):.3f} m) |"
            )
    if args.secure:
        lines += ["", "Against the open fleet of the same size (ratio; 1.00: no cost):", ""]
        lines += ["| robots | fleet | scans/s | latency median | recorder msg/s |", "|---|---|---|---|---|"]
        for r in rows:
            base = next(b for b in rows if b["robots"] == r["robots"] and b["mode"] == "open")
            if r is base:
                continue
            lines.append(
                f"| {r['robots']} | {r['mode']} | {r['scans_per_s'] / base['scans_per_s']:.2f} "  # type: ignore[operator]
                f"| {r['latency_median_s'] / base['latency_median_s']:.2f} "  # type: ignore[operator]
                f"| {r['messages_per_s'] / base['messages_per_s']:.2f} |"  # type: ignore[operator]
            )
    lines += [
        "",
        "CPU: seconds of CPU per second of session, by kind of process (1.00: one core; this machine has "
        f"{os.cpu_count()}); poses/s: robot poses the merger published per second of scanning. Map error: the "
        "global map placed in the world by its anchor submap's true pose (report.json's map_error_mean_m); "
        "aligned: laid best on the true walls first (map_error_aligned_mean_m: the map's shape, whatever a "
        "small heading error of the anchor submap turns).",
    ]
    if args.ros2:
        lines = ros2_lines(rows, args.robots)
    body = "\n".join(lines)
    print()
    print(body)
    if args.write_results:
        if args.ros2:
            write_result(
                "live-ros2",
                "The live fleet on ROS 2 topics (`benchmarks/live.py --ros2`)",
                body,
                config=FleetmapConfig(),
            )
        elif args.secure:
            write_result(
                "live-secure",
                "The live fleet with logins and TLS (`benchmarks/live.py --secure`)",
                body,
                config=FleetmapConfig(),
            )
        else:
            write_result("live", "The live fleet (`benchmarks/live.py`)", body, config=FleetmapConfig())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
