"""Benchmark: the live fleet end to end (run on demand, not in CI).

For N = 1, 4 and 16 robots (the first N of the department-16 scenario: sixteen robots on the
Section V loop, from sixteen places, both ways round), a real session runs: router, merger,
recorder and N agent processes on loopback, agents at ``--speed`` times real time (1: 5 Hz
scans). From the recording it prints:

- scans per second through the bus (Scan messages recorded / the time between first and last),
- the merger's end-to-end latency: from a local map version's arrival at the recorder to the
  arrival of the merger step that integrated it (median and 95th percentile; versions superseded
  before the merger took them are not counted, which is the point of its coalescing),
- the time the merger needed after the last scan to integrate every local map,
- the recorder's throughput (all messages and bytes over the session),
- the CPU time of each kind of process (its children included: the merger's integration
  workers count as the merger's), sampled from /proc, as a share of one core over the session.

With ``--secure``, each fleet also runs with authentication and access control
(``fleetmap secure``) and over mutual TLS, and the table gives their throughput and latency
against the open fleet's.

    python benchmarks/live.py                 # 1, 4 and 16 robots
    python benchmarks/live.py --robots 4 --speed 8
    python benchmarks/live.py --robots 4 --speed 1 --secure --write-results
    python benchmarks/live.py --robots 16 --speed 1 --runs 3 --executor inline,local
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
from fleetmap.scenarios import load_scenario
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.io.recording import RecordingReader
from results import write_section

from fleetmap.report import merge_latencies
from fleetmap.runner import Session

MODES = {"open": {}, "auth": {"secure": True}, "tls": {"secure": True, "tls": True}}
"""How the fleet's sessions meet: open, logged in with access control, and that over mutual TLS."""


def fleet_scenario(n: int):  # type: ignore[no-untyped-def]
    base = load_scenario("department-16")
    if n > len(base.robots):
        raise SystemExit(f"--robots: department-16 has {len(base.robots)} robots, asked for {n}")
    return dataclasses.replace(base, name=f"department-16-first{n}", robots=base.robots[:n], events=())


ROLES = ("merger", "agent", "record", "router")
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


def measure(n: int, speed: float, out: Path, mode: str = "open", executor: str = "local") -> dict[str, float | str]:
    session = Session(
        fleet_scenario(n),
        out,
        FleetmapConfig(),
        speed=speed,
        fleet="bench",
        progress=False,
        merger_options=("--executor", executor),
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
            last = m.log_time
    latency = merge_latencies(timed)
    span = (max(scans) - min(scans)) / 1e9 if len(scans) > 1 else float("nan")
    catch_up = (last - max(scans)) / 1e9 if scans else float("nan")
    return {
        "robots": n,
        "mode": mode,
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
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", default="1,4,16")
    ap.add_argument("--speed", type=float, default=1000.0, help="scenario speed (1000: as fast as they can)")
    ap.add_argument("--secure", action="store_true", help="also with authentication and with mutual TLS")
    ap.add_argument("--executor", default="local", help="the merger's executors to compare (comma-separated)")
    ap.add_argument("--runs", type=int, default=1, help="sessions of each kind (a live merger's steps vary)")
    ap.add_argument("--write-results", action="store_true", help="write the table into benchmarks/RESULTS.md")
    args = ap.parse_args()
    modes = list(MODES) if args.secure else ["open"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(x) for x in args.robots.split(",")):
            for mode in modes:
                for executor in args.executor.split(","):
                    for run in range(args.runs):
                        r = measure(n, args.speed, Path(tmp) / f"n{n}-{mode}-{executor}-{run}", mode, executor)
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
    body = "\n".join(lines)
    print()
    print(body)
    if args.write_results:
        if args.secure:
            write_section("live-secure", "The live fleet with logins and TLS (`benchmarks/live.py --secure`)", body)
        else:
            write_section("live", "The live fleet (`benchmarks/live.py`)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
