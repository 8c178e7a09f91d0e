"""Benchmark: the live fleet end to end (run on demand, not in CI).

For N = 1, 4 and 16 robots (the department scenario's paths, shared out round-robin, each robot
with its own noise), a real session runs: router, merger, recorder and N agent processes on
loopback, agents as fast as they can. From the recording it prints:

- scans per second through the bus (Scan messages recorded / the time between first and last),
- the merger's end-to-end latency: from a local map version's arrival at the recorder to the
  arrival of the merger step that integrated it (median and 95th percentile; versions superseded
  before the merger took them are not counted, which is the point of its coalescing),
- the time the merger needed after the last scan to integrate every local map,
- the recorder's throughput (all messages and bytes over the session).

With ``--secure``, each fleet also runs with authentication and access control
(``fleetmap secure``) and over mutual TLS, and the table gives their throughput and latency
against the open fleet's.

    python benchmarks/live.py                 # 1, 4 and 16 robots
    python benchmarks/live.py --robots 4 --speed 8
    python benchmarks/live.py --robots 4 --speed 1 --secure --write-results
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
from fleetmap.scenarios import load_scenario
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.recording import RecordingReader
from results import write_section

from fleetmap.report import merge_latencies
from fleetmap.runner import Session

MODES = {"open": {}, "auth": {"secure": True}, "tls": {"secure": True, "tls": True}}
"""How the fleet's sessions meet: open, logged in with access control, and that over mutual TLS."""


def fleet_scenario(n: int):  # type: ignore[no-untyped-def]
    base = load_scenario("department")
    robots = tuple(dataclasses.replace(base.robots[i % len(base.robots)], id=f"b{i + 1}", start=0.0) for i in range(n))
    return dataclasses.replace(base, name=f"department-x{n}", robots=robots, events=())


def measure(n: int, speed: float, out: Path, mode: str = "open") -> dict[str, float | str]:
    session = Session(
        fleet_scenario(n), out, FleetmapConfig(), speed=speed, fleet="bench", progress=False, **MODES[mode]
    )
    start = time.monotonic()
    report = session.run()
    wall = time.monotonic() - start
    scans: list[int] = []
    timed: list[tuple[bytes, int]] = []
    total = size = 0
    with RecordingReader(out / "session.mcap") as reader:
        for m in reader.messages():
            total += 1
            size += len(m.payload)
            timed.append((m.payload, m.log_time))
            if m.topic.endswith("/scan"):
                scans.append(m.log_time)
            last = m.log_time
    latency = merge_latencies(timed)
    span = (max(scans) - min(scans)) / 1e9 if len(scans) > 1 else float("nan")
    catch_up = (last - max(scans)) / 1e9 if scans else float("nan")
    return {
        "robots": n,
        "mode": mode,
        "scans": len(scans),
        "scans_per_s": len(scans) / span if span > 0 else float("nan"),
        "latency_median_s": float(np.median(latency)) if latency else float("nan"),
        "latency_p95_s": float(np.percentile(latency, 95)) if latency else float("nan"),
        "catch_up_s": catch_up,
        "messages": total,
        "messages_per_s": total / wall,
        "mb_per_s": size / wall / 1e6,
        "wall_s": wall,
        "map_error_mean_m": report["map_error_mean_m"] or float("nan"),
        "placed": report["robots_placed"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", default="1,4,16")
    ap.add_argument("--speed", type=float, default=1000.0, help="scenario speed (1000: as fast as they can)")
    ap.add_argument("--secure", action="store_true", help="also with authentication and with mutual TLS")
    ap.add_argument("--write-results", action="store_true", help="write the table into benchmarks/RESULTS.md")
    args = ap.parse_args()
    modes = list(MODES) if args.secure else ["open"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(x) for x in args.robots.split(",")):
            for mode in modes:
                r = measure(n, args.speed, Path(tmp) / f"n{n}-{mode}", mode)
                rows.append(r)
                print(r, flush=True)
    lines = [
        "| robots | fleet | scans | scans/s | latency median | latency p95 | merger catch-up | recorder msg/s "
        "| MB/s | placed | map error |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['robots']} | {r['mode']} | {r['scans']} | {r['scans_per_s']:.1f} | {r['latency_median_s']:.2f} s "
            f"| {r['latency_p95_s']:.2f} s | {r['catch_up_s']:.1f} s | {r['messages_per_s']:.0f} | {r['mb_per_s']:.2f} "
            f"| {r['placed']}/{r['robots']} | {r['map_error_mean_m']:.3f} m |"
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
    body = "\n".join(lines)
    print()
    print(body)
    if args.write_results:
        write_section("live", "The live fleet (`benchmarks/live.py`)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
