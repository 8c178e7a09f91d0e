"""Benchmark: the paper's integration and Ballesta et al.'s RANSAC aligner side by side (run on demand).

Two sets of real scan pairs, each integrated with no prior by both aligners (``[integration]
aligner``):

- **relations**: the two scans of Kümmerle relations (``benchmarks/integration.py``'s pairs: a
  sample of ``--sample`` per full-rate log), seconds to minutes apart, loop closures included;
- **consecutive**: every consecutive pair of the first ``--max-scans`` scans of each corrected log
  (``benchmarks/scan_pairs.py``'s pairs), against the corrected poses.

Per set, log and aligner: success at (0.10 m, 2 deg), the validity rule's verdict on the right
(within 0.30 m and 5 deg) and wrong pairs, and the median seconds per pair. The last columns ask
whether RANSAC is a second opinion worth having: of the pairs the paper's integration calls valid,
the share that are right, and the same among those RANSAC also calls valid within (0.30 m, 5 deg)
of it (and how many of the paper's valid pairs that keeps).

    python benchmarks/aligners.py
    python benchmarks/aligners.py --write-results     # and write its result (benchmarks/results/)
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
from dataclasses import replace

import numpy as np
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Integration, integrate
from fleetmap.shared.core.segmap import SegmentMap
from integration import load_pairs
from merge import load_pieces, scan_maps
from results import markdown_table, write_result

from fleetmap.config_args import add_config_arguments, config_from_args

ALIGNERS = ("paper", "ransac")
RIGHT = (0.30, math.radians(5))
SUCCESS = (0.10, math.radians(2))

Pair = tuple[SegmentMap, SegmentMap, Transform2D]


def consecutive_pairs(name: str, max_scans: int, config: FleetmapConfig) -> list[Pair]:
    piece = load_pieces(name, 1, 0, max_scans, config)[0]
    scans = scan_maps(piece, config)
    return [
        (scans[j - 1], scans[j], piece.truth[j - 1].inverse().compose(piece.truth[j])) for j in range(1, len(scans))
    ]


def within(r: Integration, truth: Transform2D, limit: tuple[float, float]) -> bool:
    dt, dr = r.transform.distance(truth)
    return dt < limit[0] and dr < limit[1]


def agree(a: Integration, b: Integration) -> bool:
    dt, dr = a.transform.distance(b.transform)
    return dt < RIGHT[0] and dr < RIGHT[1]


def run(job: tuple[str, str, int, FleetmapConfig]) -> tuple[str, str, dict[str, list[tuple[bool, bool, bool, float]]]]:
    """One log of one set: per aligner, per pair (success, right, valid, seconds), and the
    second-opinion flags under the key ``both`` (paper valid, paper right, RANSAC valid and agrees)."""
    kind, name, size, config = job
    pairs = load_pairs(name, config, size, 1) if kind == "relations" else consecutive_pairs(name, size, config)
    out: dict[str, list[tuple[bool, bool, bool, float]]] = {a: [] for a in ALIGNERS}
    out["both"] = []
    for a, b, truth in pairs:
        found = {al: integrate(a, b, replace(config.integration, aligner=al)) for al in ALIGNERS}
        for al, r in found.items():
            out[al].append((within(r, truth, SUCCESS), within(r, truth, RIGHT), r.valid, r.seconds))
        p, q = found["paper"], found["ransac"]
        out["both"].append((p.valid, within(p, truth, RIGHT), q.valid and agree(p, q), 0.0))
    return kind, name, out


def rows_of(kind: str, name: str, out: dict[str, list[tuple[bool, bool, bool, float]]]) -> list[str]:
    cells = [kind, name, str(len(out["paper"]))]
    for al in ALIGNERS:
        r = np.array(out[al], dtype=np.float64).reshape(-1, 4)
        ok, right, valid = r[:, 0] > 0, r[:, 1] > 0, r[:, 2] > 0
        vr = 100 * valid[right].mean() if right.any() else math.nan
        vw = 100 * valid[~right].mean() if (~right).any() else math.nan
        cells += [f"{100 * ok.mean():.1f} %", f"{vr:.0f} % / {vw:.0f} %", f"{1000 * np.median(r[:, 3]):.0f} ms"]
    b = np.array(out["both"], dtype=bool).reshape(-1, 4)
    pv, pr, second = b[:, 0], b[:, 1], b[:, 2]
    both = pv & second
    cells.append(f"{100 * pr[pv].mean():.1f} % of {pv.sum()}" if pv.any() else "-")
    cells.append(f"{100 * pr[both].mean():.1f} % of {both.sum()}" if both.any() else "-")
    return cells


HEADER = [
    "pairs",
    "log",
    "n",
    "paper: success (0.10 m, 2°)",
    "paper: valid on right / wrong",
    "paper: time/pair",
    "ransac: success (0.10 m, 2°)",
    "ransac: valid on right / wrong",
    "ransac: time/pair",
    "right among paper-valid",
    "right among paper-valid that ransac confirms",
]
TITLE = "The paper's integration and RANSAC side by side (`benchmarks/aligners.py`)"
EXPLAINED = (
    "Relations: the two scans of a sample of `--sample` Kümmerle relations per full-rate log "
    "(`benchmarks/integration.py`'s pairs); consecutive: every consecutive pair of each corrected log's first "
    "`--max-scans` scans (`benchmarks/scan_pairs.py`'s pairs), against the corrected poses. Each pair "
    "integrated with no prior by the paper's integration (`--aligner paper`, heuristic auto) and by Ballesta et "
    "al.'s RANSAC over landmark correspondences (`--aligner ransac`). Success: within (0.10 m, 2°); valid on "
    "right / wrong: the share of the pairs within (0.30 m, 5°), and of the others, that the validity rule calls "
    "valid; time/pair: the median of the aligner's own seconds. The last two columns: of the pairs the paper's "
    "integration calls valid, the share right (0.30 m, 5°), and the same among those RANSAC also calls valid "
    "within (0.30 m, 5°) of it (a second opinion: how many it keeps, how many of them are right)."
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--relations", default="aces,fr079,mit-csail", help="full-rate logs (relation pairs)")
    ap.add_argument("--consecutive", default="aces,csail,freiburg-101,infinite-corridor,edmonton,orebro")
    ap.add_argument("--sample", type=int, default=300, help="relations per log (0: all)")
    ap.add_argument("--max-scans", type=int, default=200, help="scans per corrected log")
    ap.add_argument("--workers", type=int, default=1, help="processes (timings are per pair either way)")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    add_config_arguments(ap, ["extraction", "integration"])
    args = ap.parse_args()
    config = config_from_args(args)
    jobs = [("relations", n, args.sample, config) for n in args.relations.split(",") if n]
    jobs += [("consecutive", n, args.max_scans, config) for n in args.consecutive.split(",") if n]
    rows = []
    if args.workers > 1:
        with multiprocessing.Pool(args.workers) as pool:
            results = pool.map(run, jobs, chunksize=1)
    else:
        results = [run(j) for j in jobs]
    for kind, name, out in results:
        rows.append(rows_of(kind, name, out))
        print(" | ".join(rows[-1]), file=sys.stderr, flush=True)
    for kind in ("relations", "consecutive"):
        mine = [out for k, _, out in results if k == kind]
        if len(mine) > 1:
            rows.append(rows_of(kind, "overall", {key: [x for o in mine for x in o[key]] for key in mine[0]}))
    body = markdown_table(HEADER, rows)
    print(body)
    if args.write_results:
        write_result(
            "aligners",
            TITLE,
            EXPLAINED + "\n\n" + body,
            config=config,
            varied=[f"integration.aligner={','.join(ALIGNERS)}"],
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
