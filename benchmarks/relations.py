"""Benchmark: ``fleetmap map`` on the full-rate logs, whole and cut into K robots, scored with their
Kümmerle relations (run on demand, not in CI).

Each log is mapped by the command itself (a subprocess, ``--split K``); its ``poses.csv`` is then
scored with the log's relations (``../shared/data/relations``): a relation counts where both of its
scans got a pose. Within one component, its error is the relation's against the two poses; across
components, the relation is *not joined*. Reported per log and K: relations with both scans placed;
joined and within (0.10 m, 2 deg), mean errors; for K > 1 the same over *cross-robot* relations (the
two scans in different robots' pieces), which only the merger can get right; relations off by more
than 1 m or 10 degrees (*wrong*); the time the command took against the log's duration; and the
integrations it did.

Errors are measured in the relations' own frame: ``poses.csv`` holds laser poses, and fr079's
relations sit about 5 cm ahead of its laser, which puts a right map's relations rotated by 90
degrees 6 cm off. ``relation_frame.py`` measures that frame on each log's raw scans, without any
map, before the runs; the table gives it, and the shares within as scored in the laser's frame.

    python benchmarks/relations.py                       # aces, fr079, mit-csail; K = 1, 2, 4, 8
    python benchmarks/relations.py --logs mit-csail --splits 1,4 --write-results
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fleetmap.shared.core.geometry import Transform2D

sys.path.insert(0, str(Path(__file__).resolve().parent))
from relation_frame import measure
from results import write_section
from tracking import LOGS, data_folder

WITHIN_M, WITHIN_DEG = 0.10, 2.0
WRONG_M, WRONG_DEG = 1.0, 10.0


@dataclass(frozen=True)
class Score:
    relations: int
    placed: int
    joined: int
    within: int
    wrong: int
    mean_t: float
    mean_r_deg: float


@dataclass(frozen=True)
class Run:
    log: str
    split: int
    all: Score
    cross: Score
    laser_all: Score
    laser_cross: Score
    frame: Transform2D
    seconds: float
    duration: float
    integrations: int
    components: int


def _key(stamp: float) -> int:
    return round(stamp * 1e4)  # mit-csail's relations give stamps to 5 decimals


def score(poses_csv: Path, relations: Path, frame: Transform2D | None = None) -> tuple[Score, Score]:
    """All and cross-robot relations scored against ``poses_csv``'s laser poses, each moved onto
    the relations' ``frame`` on the laser (:mod:`relation_frame`; none: the laser's)."""
    frame = frame or Transform2D.identity()
    poses: dict[int, tuple[str, int, Transform2D]] = {}
    with poses_csv.open(encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            t = Transform2D(float(row["x"]), float(row["y"]), float(row["theta"])).compose(frame)
            poses[_key(float(row["stamp"]))] = (row["robot"], int(row["component"]), t)
    tallies: dict[str, list[float]] = {"all": [], "cross": []}
    counts = {k: [0, 0, 0, 0, 0] for k in tallies}  # relations, placed, joined, within, wrong
    errors: dict[str, list[tuple[float, float]]] = {k: [] for k in tallies}
    for t1, t2, x, y, _z, _roll, _pitch, yaw in np.loadtxt(relations):
        a, b = poses.get(_key(t1)), poses.get(_key(t2))
        kinds = ["all"]
        if a is not None and b is not None and a[0] != b[0]:
            kinds.append("cross")
        for k in kinds:
            counts[k][0] += 1
        if a is None or b is None:
            continue
        for k in kinds:
            counts[k][1] += 1
        if a[1] != b[1]:
            continue
        error = Transform2D(x, y, yaw).inverse().compose(a[2].inverse().compose(b[2]))
        et, er = math.hypot(error.x, error.y), math.degrees(abs(error.theta))
        for k in kinds:
            counts[k][2] += 1
            counts[k][3] += et < WITHIN_M and er < WITHIN_DEG
            counts[k][4] += et > WRONG_M or er > WRONG_DEG
            errors[k].append((et, er))
    del tallies
    out = []
    for k in ("all", "cross"):
        e = errors[k]
        out.append(
            Score(
                *counts[k],
                statistics.fmean(x for x, _ in e) if e else math.nan,
                statistics.fmean(r for _, r in e) if e else math.nan,
            )
        )
    return out[0], out[1]


def run(job: tuple[str, int, Path, list[str], Transform2D]) -> Run:
    name, split, data, extra, frame = job
    path, range_max = LOGS[name]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "fleetmap", "map", str(data / path), "--out", str(out)]
        cmd += ["--split", str(split), "--range-max", str(range_max), "--json", "--no-progress", *extra]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
        summary = json.loads(done.stdout)
        relations = data / "relations" / f"{name}.relations"
        all_, cross = score(out / "poses.csv", relations, frame)
        laser_all, laser_cross = score(out / "poses.csv", relations)
    return Run(
        name,
        split,
        all_,
        cross,
        laser_all,
        laser_cross,
        frame,
        summary["seconds"],
        summary["duration_s"],
        summary["integrations"],
        summary["components"],
    )


def _pct(n: int, d: int) -> str:
    return f"{100 * n / d:.1f} %" if d else "-"


def table(runs: list[Run]) -> str:
    head = (
        "| log | K | relations placed | joined | within 0.10 m, 2 deg | mean error | wrong "
        "| cross-robot: placed | joined | within | mean error | wrong | time (share of log) | integrations "
        "| components | relations' frame on the laser | within, laser frame (all / cross) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    rows = []
    for r in runs:
        a, c = r.all, r.cross
        rows.append(
            f"| {r.log} | {r.split} | {a.placed} of {a.relations} | {_pct(a.joined, a.placed)} "
            f"| {_pct(a.within, a.joined)} | {a.mean_t:.3f} m, {a.mean_r_deg:.2f} deg | {a.wrong} "
            + (
                f"| {c.placed} | {_pct(c.joined, c.placed)} | {_pct(c.within, c.joined)} "
                f"| {c.mean_t:.3f} m, {c.mean_r_deg:.2f} deg | {c.wrong} "
                if r.split > 1
                else "| - | - | - | - | - "
            )
            + f"| {r.seconds:.0f} s ({r.seconds / r.duration:.2f}) | {r.integrations} | {r.components} "
            + f"| {r.frame.x:+.3f}, {r.frame.y:+.3f} m "
            + f"| {_pct(r.laser_all.within, r.laser_all.joined)}"
            + (f" / {_pct(r.laser_cross.within, r.laser_cross.joined)} |" if r.split > 1 else " |")
        )
    return head + "\n".join(rows) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", default=",".join(LOGS), help="full-rate logs (comma-separated)")
    ap.add_argument("--splits", default="1,2,4,8", help="values of K (comma-separated)")
    ap.add_argument("--workers", type=int, default=2, help="maps at once (default 2)")
    ap.add_argument("--write-results", action="store_true", help="update benchmarks/RESULTS.md")
    args, extra = ap.parse_known_args()
    names = [n for n in args.logs.split(",") if n]
    unknown = [n for n in names if n not in LOGS]
    if unknown:
        raise SystemExit(f"unknown log {unknown[0]!r} (known: {', '.join(LOGS)})")
    data = data_folder()
    frames = {n: measure(data / LOGS[n][0], data / "relations" / f"{n}.relations", LOGS[n][1]).offset for n in names}
    jobs = [(n, int(k), data, extra, frames[n]) for n in names for k in args.splits.split(",")]
    with ThreadPoolExecutor(max_workers=args.workers) as pool:
        runs = []
        for r in pool.map(run, jobs):
            runs.append(r)
            print(table([r]).splitlines()[-1], flush=True)
    body = (
        "`fleetmap map` on the full-rate logs cut into K robots (`--split K`), scored with all of each "
        "log's relations; cross-robot: relations whose scans are in different robots' pieces. Errors in "
        "the relations' frame, measured on each log's raw scans by `benchmarks/relation_frame.py`.\n\n" + table(runs)
    )
    print(body)
    if args.write_results:
        write_section("relations", "Mapping real logs (`benchmarks/relations.py`)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
