"""Benchmark: the time of one integration against the segments of its two maps (run on demand).

Why ``merge.max_submap_segments`` bounds the time of one integration: two partial maps cut from
aces' scans placed at their corrected poses (the second moved by a known transform), N segments
each, integrated pose-free; seconds per N (median of ``--repeat`` runs) and seconds per thousand
segments.

    python benchmarks/integration_size.py --write-results
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import integrate
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.io.logs import read_carmen
from results import write_result
from tracking import data_folder


def segments_of_aces(count: int) -> np.ndarray:
    """The first ``count`` segments of aces' scans, each placed at its corrected pose."""
    log = data_folder() / "corrected" / "aces-corrected.log.gz"
    parts, total = [], 0
    for scan in read_carmen(log, 50.0):
        assert scan.odom is not None
        part = Transform2D(*scan.odom).apply(extract_segments(scan))
        parts.append(part)
        total += len(part)
        if total >= count:
            break
    return np.concatenate(parts)[:count]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="250,500,1000,2000,4000,5000")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--write-results", action="store_true")
    args = ap.parse_args()
    sizes = [int(n) for n in args.sizes.split(",")]
    pool = segments_of_aces(max(sizes) * 5 // 4 + 1)
    moved = Transform2D(0.7, -0.4, 0.3)
    lines = ["| segments per map | seconds (median) | seconds per 1,000 segments |", "|---|---|---|"]
    for n in sizes:
        a = SegmentMap(pool[:n].copy(), ordered=False)
        b = SegmentMap(moved.apply(pool[n // 4 : n // 4 + n]), ordered=False)
        times = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            integrate(a, b)
            times.append(time.perf_counter() - start)
        t = statistics.median(times)
        lines.append(f"| {n} | {t:.2f} | {1000 * t / n:.2f} |")
        print(lines[-1], flush=True)
    body = "\n".join(lines)
    if args.write_results:
        write_result(
            "integration-size",
            "One integration against map size (`benchmarks/integration_size.py`)",
            body,
            config=FleetmapConfig(),
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
