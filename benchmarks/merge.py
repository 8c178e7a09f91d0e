"""Benchmark: merging local maps whose order is unknown, on real data (run on demand, not in CI).

The paper's four-robot experiment (Fig. 16-17) at a larger scale. For each SLAM-corrected log of
``../shared/data/corrected`` (GMapping output; the corrected poses are the ground truth and are
never given to the algorithms):

1. cut the tour into K consecutive pieces overlapping by a few scans;
2. build each piece's local map from its scans alone (pivot method, no poses);
3. shuffle the local maps and merge them with the map graph (``--order unknown``);
4. compare each placed map's pose (its first scan's frame, in the anchor's frame) with the
   corrected poses.

Prints per dataset and K: maps placed within (0.2 m, 3 deg), placed wrongly (> 1 m or > 10 deg),
unplaced, and the merge time.

    python benchmarks/merge.py                         # every dataset, K = 4 and 8
    python benchmarks/merge.py --datasets aces,csail --k 8
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from fleetmap.merger.graph import MapGraph
from fleetmap.merger.sequence import PivotMapBuilder
from fleetmap.shared.config import FleetmapConfig, add_config_arguments, config_from_args
from fleetmap.shared.extraction import extract_segments
from fleetmap.shared.geometry import Transform2D
from fleetmap.shared.mapfile import SegmentMap
from fleetmap.shared.scans import read_carmen

DATASETS = {
    # name: subsampling step (freiburg-079 is logged every 0.1 m; the others about every metre)
    "aces": 1,
    "acapulco": 1,
    "belgioioso": 1,
    "csail": 1,
    "edmonton": 1,
    "freiburg-079": 5,
    "freiburg-101": 1,
    "freiburg-campus": 1,
    "infinite-corridor": 1,
    "orebro": 1,
}


def data_dir() -> Path:
    env = os.environ.get("FLEETMAP_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass
class Piece:
    scans: list[SegmentMap]
    truth_first: Transform2D


def load_pieces(name: str, k: int, overlap: int, max_scans: int, config: FleetmapConfig) -> list[Piece]:
    scans = list(read_carmen(data_dir() / "corrected" / f"{name}-corrected.log.gz"))[:: DATASETS[name]][:max_scans]
    maps = [SegmentMap(extract_segments(s, config.extraction), ordered=True, oriented=True) for s in scans]
    size = math.ceil(len(scans) / k)
    pieces = []
    for i in range(k):
        lo, hi = i * size, min(len(scans), (i + 1) * size + overlap)
        keep = [j for j in range(lo, hi) if len(maps[j]) > 0]
        if keep:
            odom = scans[keep[0]].odom
            assert odom is not None  # corrected logs carry the SLAM pose on every laser line
            pieces.append(Piece([maps[j] for j in keep], Transform2D(*odom)))
    return pieces


def build_local_map(job: tuple[list[SegmentMap], FleetmapConfig]) -> tuple[SegmentMap, int, float]:
    scans, config = job
    start = time.perf_counter()
    builder = PivotMapBuilder(config.integration)
    placed = sum(builder.add(m).pose is not None for m in scans)
    return builder.map, placed, time.perf_counter() - start


def run(name: str, k: int, args: argparse.Namespace, config: FleetmapConfig, pool: multiprocessing.pool.Pool) -> dict:
    pieces = load_pieces(name, k, args.overlap, args.max_scans, config)
    built = pool.map(build_local_map, [(p.scans, config) for p in pieces])
    keys = [f"{name}/{i}" for i in range(len(pieces))]
    order = list(range(len(pieces)))
    random.Random(args.shuffle_seed).shuffle(order)
    graph = MapGraph(config.integration, config.merge, anchor="largest")
    start = time.perf_counter()
    for i in order:
        graph.add_map(keys[i], built[i][0])
    result = graph.solve()
    seconds = time.perf_counter() - start
    good = wrong = unplaced = 0
    details = []
    comp = result.components[0]
    anchor_truth = pieces[keys.index(comp.anchor)].truth_first
    for i, key in enumerate(keys):
        pose = result.poses.get(key)
        if pose is None or key not in comp.members:
            unplaced += 1
            details.append(f"{i}:-")
            continue
        est = anchor_truth.compose(pose)
        dt, dr = est.distance(pieces[i].truth_first)
        if dt <= 0.2 and math.degrees(dr) <= 3:
            good += 1
        elif dt > 1.0 or math.degrees(dr) > 10:
            wrong += 1
        details.append(f"{i}:{dt:.2f}m/{math.degrees(dr):.1f}d")
    segs = [len(b[0]) for b in built]
    return {
        "dataset": name,
        "k": len(pieces),
        "good": good,
        "wrong": wrong,
        "unplaced": unplaced,
        "merge_s": seconds,
        "build_s": sum(b[2] for b in built),
        "segments": f"{min(segs)}-{max(segs)}",
        "scans_placed": f"{sum(b[1] for b in built)}/{sum(len(p.scans) for p in pieces)}",
        "rejected": len(result.rejected),
        "details": " ".join(details),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default=",".join(DATASETS))
    ap.add_argument("--k", default="4,8", help="numbers of pieces")
    ap.add_argument("--overlap", type=int, default=3, help="scans shared by consecutive pieces")
    ap.add_argument("--max-scans", type=int, default=400, help="scans used per dataset (after subsampling)")
    ap.add_argument("--shuffle-seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2, help="processes building local maps")
    add_config_arguments(ap, ["extraction", "integration", "merge"])
    args = ap.parse_args()
    config = config_from_args(args)
    rows = []
    with multiprocessing.Pool(args.workers) as pool:
        for name in args.datasets.split(","):
            for k in (int(x) for x in args.k.split(",")):
                r = run(name, k, args, config, pool)
                rows.append(r)
                print(
                    f"{name:18s} K={r['k']} good {r['good']} wrong {r['wrong']} unplaced {r['unplaced']} "
                    f"merge {r['merge_s']:.1f} s (local maps {r['segments']} segments, scans placed "
                    f"{r['scans_placed']}, built in {r['build_s']:.0f} s) rejected edges {r['rejected']} "
                    f"| {r['details']}",
                    flush=True,
                )
    print()
    print("| dataset | K | within (0.2 m, 3°) | wrong (> 1 m or > 10°) | unplaced | merge time | local map segments |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['dataset']} | {r['k']} | {r['good']} | {r['wrong']} | {r['unplaced']} | {r['merge_s']:.1f} s "
            f"| {r['segments']} |"
        )
    total = sum(r["k"] for r in rows)
    good = sum(r["good"] for r in rows)
    wrong = sum(r["wrong"] for r in rows)
    print(f"\noverall: {good}/{total} within (0.2 m, 3 deg) ({100 * good / max(total, 1):.1f} %), {wrong} wrong")
    return 0


if __name__ == "__main__":
    sys.exit(main())
