"""Benchmark: pose-free integration of real scan pairs with ground truth (run on demand, not in CI).

For each relation of ``../shared/data/relations`` (aces, fr079, mit-csail; Kümmerle et al. 2009,
Radish), the scans at t1 and t2 are extracted into segments and integrated with no prior; the
result is compared with the relation (the pose at t2 in the frame of t1). Prints, per dataset and
heuristic: success at (0.10 m, 2 deg) and (0.30 m, 5 deg), median errors, median seconds per pair;
how well ``valid`` separates right from wrong integrations; and the time of ``all`` versus ``auto``
on the largest pair.

    python benchmarks/integration.py                      # 300 relations per dataset, all heuristics
    python benchmarks/integration.py --sample 0 --heuristics auto   # every relation, auto only
    python benchmarks/integration.py --write-results      # and write its result (benchmarks/results/)
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from fleetmap.shared.config import FleetmapConfig, IntegrationParams
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import integrate
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.io.logs import read_carmen
from results import markdown_table, write_result

from fleetmap.config_args import add_config_arguments, config_from_args

DATASETS = {
    # name: (log, no-return reading of its FLASER lines)
    "aces": ("aces/aces.clf.gz", 50.0),
    "fr079": ("fr079/fr079.clf.gz", 81.9),
    "mit-csail": ("mit-csail/mit-csail.clf.gz", 81.9),
}


def data_dir() -> Path:
    env = os.environ.get("FLEETMAP_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def load_pairs(
    name: str, config: FleetmapConfig, sample: int, seed: int
) -> list[tuple[SegmentMap, SegmentMap, Transform2D]]:
    log, no_return = DATASETS[name]
    root = data_dir()
    scans = list(read_carmen(root / log, range_max=no_return))
    stamps = np.array([s.stamp for s in scans])
    order = np.argsort(stamps)
    rel = np.loadtxt(root / "relations" / f"{name}.relations", ndmin=2)
    if sample and sample < len(rel):
        rel = rel[np.sort(np.random.default_rng(seed).choice(len(rel), sample, replace=False))]

    def find(t: float) -> int:
        k = int(np.searchsorted(stamps[order], t))
        best = min((abs(stamps[order[j]] - t), order[j]) for j in (k - 1, k) if 0 <= j < len(order))
        if best[0] > 1e-3:
            raise SystemExit(f"{name}: no scan at relation time {t}")
        return int(best[1])

    cache: dict[int, SegmentMap] = {}

    def segmap(i: int) -> SegmentMap:
        if i not in cache:
            cache[i] = SegmentMap(extract_segments(scans[i], config.extraction), ordered=True, oriented=True)
        return cache[i]

    pairs = []
    for t1, t2, x, y, _z, _roll, _pitch, yaw in rel:
        a, b = segmap(find(t1)), segmap(find(t2))
        if len(a) and len(b):
            pairs.append((a, b, Transform2D(x, y, yaw)))
    return pairs


def run_one(job: tuple[SegmentMap, SegmentMap, Transform2D, str, IntegrationParams]) -> dict[str, float | bool | int]:
    a, b, truth, heuristic, params = job
    r = integrate(a, b, params, heuristic=heuristic)
    dt, dr = r.transform.distance(truth)
    return {
        "trans_err": dt,
        "rot_err": dr,
        "seconds": r.seconds,
        "value": r.value,
        "valid": r.valid,
        "n1": len(a),
        "n2": len(b),
        "len1": a.total_length,
        "len2": b.total_length,
        "candidates": r.candidates,
        "violation": r.violation,
        "runner_up": r.runner_up,
    }


def summarize(rows: list[dict]) -> dict[str, float]:
    te = np.array([r["trans_err"] for r in rows])
    re = np.degrees([r["rot_err"] for r in rows])
    sec = np.array([r["seconds"] for r in rows])
    right = (te < 0.3) & (re < 5)
    valid = np.array([r["valid"] for r in rows])
    return {
        "pairs": len(rows),
        "success_10cm_2deg": float(np.mean((te < 0.10) & (re < 2))),
        "success_30cm_5deg": float(np.mean(right)),
        "median_trans_err_m": float(np.median(te)),
        "median_rot_err_deg": float(np.median(re)),
        "median_seconds": float(np.median(sec)),
        "valid_right": float(np.mean(valid[right])) if right.any() else math.nan,
        "valid_wrong": float(np.mean(valid[~right])) if (~right).any() else math.nan,
        "wrong": int((~right).sum()),
    }


HEADER = [
    "dataset",
    "heuristic",
    "pairs",
    "success (0.10 m, 2°)",
    "success (0.30 m, 5°)",
    "median error",
    "median time/pair",
    "valid on right / wrong",
]
TITLE = "Pose-free integration of real scan pairs (`benchmarks/integration.py`)"
EXPLAINED = (
    "The two scans of each Kümmerle relation (a sample of `--sample` per log; 0: all) extracted and "
    "integrated with no prior, by each heuristic; overall: every log's pairs together. Success: the result "
    "within (0.10 m, 2°) or (0.30 m, 5°) of the relation; median error: of translation and rotation over all "
    "pairs; median time/pair: the integration's own seconds; valid on right / wrong: the share of the "
    "pairs right within (0.30 m, 5°), and of the others, that the validity rule calls valid. Below the "
    "table: the largest pair (most segments, product of the two) with `all` and with `auto`."
)


def table(rows: list[tuple[str, str, dict[str, float]]]) -> str:
    """The printed table: one row per dataset and heuristic, ``summarize``'s figures."""
    cells = [
        [
            name,
            h,
            str(s["pairs"]),
            f"{100 * s['success_10cm_2deg']:.1f} %",
            f"{100 * s['success_30cm_5deg']:.1f} %",
            f"{100 * s['median_trans_err_m']:.1f} cm, {s['median_rot_err_deg']:.2f}°",
            f"{1000 * s['median_seconds']:.0f} ms",
            f"{100 * s['valid_right']:.0f} % / {100 * s['valid_wrong']:.0f} %",
        ]
        for name, h, s in rows
    ]
    return markdown_table(HEADER, cells)


def largest_pair(a: SegmentMap, b: SegmentMap, truth: Transform2D, config: FleetmapConfig) -> list[str]:
    """The largest pair integrated with ``all`` and with ``auto``: a line each, and their time ratio."""
    lines, times = [], {}
    for h in ("all", "auto"):
        params = replace(config.integration, heuristic=h)
        r = integrate(a, b, params)
        dt, dr = r.transform.distance(truth)
        times[h] = r.seconds
        lines.append(
            f"largest pair ({len(a)} x {len(b)} segments): {h}: {r.seconds:.3f} s, {r.candidates} transformations, "
            f"error {100 * dt:.1f} cm {math.degrees(dr):.2f} deg"
        )
    return [*lines, f"all / auto time ratio: {times['all'] / max(times['auto'], 1e-9):.1f}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default=",".join(DATASETS))
    ap.add_argument("--heuristics", default="consecutive,histogram,random,all,auto")
    ap.add_argument("--sample", type=int, default=300, help="relations per dataset (0: all)")
    ap.add_argument("--sample-seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=1, help="processes (timings are per pair either way)")
    ap.add_argument("--json", metavar="FILE", help="write every result row here")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    add_config_arguments(ap, ["extraction", "integration"])
    args = ap.parse_args()
    config = config_from_args(args)
    print(f"data: {data_dir()}; extraction {config.extraction}", file=sys.stderr)
    rows_of_table = []
    all_rows: dict[str, dict[str, list[dict]]] = {}
    largest: tuple[int, SegmentMap, SegmentMap, Transform2D] | None = None
    for name in args.datasets.split(","):
        pairs = load_pairs(name, config, args.sample, args.sample_seed)
        for a, b, t in pairs:
            if largest is None or len(a) * len(b) > largest[0]:
                largest = (len(a) * len(b), a, b, t)
        for h in args.heuristics.split(","):
            params = replace(config.integration, heuristic=h)
            jobs = [(a, b, t, h, params) for a, b, t in pairs]
            start = time.perf_counter()
            if args.workers > 1:
                with multiprocessing.Pool(args.workers) as pool:
                    rows = pool.map(run_one, jobs, chunksize=4)
            else:
                rows = [run_one(j) for j in jobs]
            wall = time.perf_counter() - start
            all_rows.setdefault(name, {})[h] = rows
            s = summarize(rows)
            rows_of_table.append((name, h, s))
            print(
                f"{name:10s} {h:12s} n={s['pairs']:4d} ok@10cm/2deg {100 * s['success_10cm_2deg']:5.1f}% "
                f"ok@30cm/5deg {100 * s['success_30cm_5deg']:5.1f}% med err {100 * s['median_trans_err_m']:.1f} cm "
                f"{s['median_rot_err_deg']:.2f} deg, med {1000 * s['median_seconds']:.0f} ms/pair "
                f"valid: right {100 * s['valid_right']:.0f}% wrong {100 * s['valid_wrong']:.0f}% ({s['wrong']}) "
                f"[{wall:.0f} s]",
                flush=True,
            )
    for h in args.heuristics.split(","):
        rows = [r for name in all_rows for r in all_rows[name].get(h, [])]
        s = summarize(rows)
        rows_of_table.append(("overall", h, s))
    text = table(rows_of_table)
    print()
    print(text)
    lines = [] if largest is None else largest_pair(*largest[1:], config)
    for line in lines:
        print(line)
    if args.write_results:
        heuristics = [*args.heuristics.split(","), *(("all", "auto") if lines else ())]
        write_result(
            "integration",
            TITLE,
            "\n\n".join([EXPLAINED, text, *lines]),
            config=config,
            varied=[f"integration.heuristic={','.join(dict.fromkeys(heuristics))}"],
        )
    if args.json:
        Path(args.json).write_text(json.dumps(all_rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
