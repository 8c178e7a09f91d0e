"""Benchmark: ``fleetmap map`` on every log at hand, whole and cut into K robots, scored with their
relations (run on demand, not in CI).

Each log is mapped by the command itself (a subprocess, ``--split K``); its ``poses.csv`` is then
scored with the log's relations (``../shared/data/relations``): a relation counts where both of its
scans got a pose. Within one component, its error is the relation's against the two poses; across
components, the relation is *not joined*. Reported per log and K: relations with both scans placed;
joined and within (0.10 m, 2 deg), mean errors; for K > 1 the same over *cross-robot* relations (the
two scans in different robots' pieces), which only the merger can get right, with the whole log's
(K = 1) mean error on those same relations beside theirs (the relations a cut crosses are mostly a
loop's two passes, harder than the log's average); relations off by more
than 1 m or 10 degrees (*wrong*); the time the command took against the log's duration (each map
alone by default: ``fleetmap map`` uses both of a two-core host's cores, and two maps at once took
up to 2.3 times as long: mit-csail cut in 8, 0.16 of its log against 0.07); and the integrations
it did.

Errors are measured in the relations' own frame: ``poses.csv`` holds laser poses, and fr079's
relations sit about 5 cm ahead of its laser, which puts a right map's relations rotated by 90
degrees 6 cm off. ``relation_frame.py`` measures that frame on each log's raw scans, without any
map, before the runs; the table gives it, and the shares within as scored in the laser's frame.

    python benchmarks/relations.py                       # every log; K = 1, 2, 4, 8 (about an hour)
    python benchmarks/relations.py --logs mit-csail --splits 1,4 --write-results
    python benchmarks/relations.py --logs corrected --splits 1,4,8   # the SLAM-corrected logs only

The SLAM-corrected logs (``corrected/NAME``: a scan about every metre, as long tours are often
logged) are mapped in-process as ``fleetmap map`` maps them and scored by scan index (their stamps
repeat, or are all 0) with relations made from their corrected poses: every two scans within
:data:`CORRECTED_WITHIN` of each other (infinite-corridor's stamps run negative, then repeat
4.29e9 s: it is tracked by its scans' sequence). Their corrected poses are GMapping's, wrong at a
few scans: a wrong relation whose own two raw scans side with the map, or the scans on both sides
of a misplaced scan's run (record 074), is counted apart, as the raw scans contradicting it
(:mod:`raw_truth`). A log that ``fleetmap map`` refuses says so.
``--clock burst`` (or another of :mod:`fleetmap.scenarios.clocks`) maps each corrected log's
pieces as a robot with that broken clock recorded them; ``--seeds N`` does it N times, each with
other breaks (one wrong placement can bend a sparse log's map, and which scan the clock breaks
decides it: a single seed is a single draw).

    python benchmarks/relations.py --logs corrected/aces,corrected/acapulco --splits 1,4 --clock burst

Any other option is ``fleetmap map``'s, for every log: ``--odometry off`` maps them as robots
without odometry would be mapped.

    python benchmarks/relations.py --logs corrected/csail --splits 1 --odometry off
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
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from fleetmap.merger.executor import make_executor
from fleetmap.scenarios.clocks import CLOCKS, break_clock
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.logs import read_carmen
from scipy.spatial import cKDTree

from fleetmap.commands.map import CONFIG_SECTIONS
from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.mapping import map_logs, read_inputs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raw_truth import RawTruth, beyond
from relation_frame import measure
from results import write_result
from tracking import CORRECTED, LOGS, data_folder

WITHIN_M, WITHIN_DEG = 0.10, 2.0
WRONG_M, WRONG_DEG = 1.0, 10.0
CORRECTED_WITHIN = 2.0
"""A corrected log's relations: its scans whose corrected poses lie this close (m)."""


@dataclass(frozen=True)
class Score:
    relations: int
    placed: int
    joined: int
    within: int
    wrong: int
    mean_t: float
    mean_r_deg: float
    errors: dict[int, float]
    """Each joined relation's translational error (m), by its place in the log's relations."""
    contradicted: int = 0
    """Relations wrong by the corrected poses whose own raw scans side with the map (:mod:`raw_truth`):
    not counted in ``wrong`` (they still count in ``within`` and the mean error)."""


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


Placed = tuple[str, int, Transform2D]
"""A scan's robot, component and pose."""


def score(poses_csv: Path, relations: Path, frame: Transform2D | None = None) -> tuple[Score, Score]:
    """All and cross-robot relations scored against ``poses_csv``'s laser poses, each moved onto
    the relations' ``frame`` on the laser (:mod:`relation_frame`; none: the laser's)."""
    frame = frame or Transform2D.identity()
    poses: dict[int, Placed] = {}
    with poses_csv.open(encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            t = Transform2D(float(row["x"]), float(row["y"]), float(row["theta"])).compose(frame)
            poses[_key(float(row["stamp"]))] = (row["robot"], int(row["component"]), t)
    return _tally(
        (poses.get(_key(t1)), poses.get(_key(t2)), Transform2D(x, y, yaw))
        for t1, t2, x, y, _z, _roll, _pitch, yaw in np.loadtxt(relations)
    )


Excuse = Callable[[int, Transform2D], bool]
"""Whether the raw scans of the relation at this place side with the map's estimate of it."""


def _tally(
    relations: Iterable[tuple[Placed | None, Placed | None, Transform2D]], excused: Excuse | None = None
) -> tuple[Score, Score]:
    """All and cross-robot relations scored: each its two scans as placed (None: not placed) and
    the second's true pose in the first's frame. A wrong one that ``excused`` says its raw scans
    contradict is counted apart (``Score.contradicted``)."""
    counts = {k: [0, 0, 0, 0, 0] for k in ("all", "cross")}  # relations, placed, joined, within, wrong
    contradicted = {k: 0 for k in counts}
    errors: dict[str, dict[int, tuple[float, float]]] = {k: {} for k in counts}
    for i, (a, b, truth) in enumerate(relations):
        kinds = ["all"] + (["cross"] if a is not None and b is not None and a[0] != b[0] else [])
        for k in kinds:
            counts[k][0] += 1
        if a is None or b is None:
            continue
        for k in kinds:
            counts[k][1] += 1
        if a[1] != b[1]:
            continue
        estimate = a[2].inverse().compose(b[2])
        error = truth.inverse().compose(estimate)
        et, er = math.hypot(error.x, error.y), math.degrees(abs(error.theta))
        wrong = beyond(error, WRONG_M, WRONG_DEG)
        not_truth = wrong and excused is not None and excused(i, estimate)
        for k in kinds:
            counts[k][2] += 1
            counts[k][3] += et < WITHIN_M and er < WITHIN_DEG
            counts[k][4] += wrong and not not_truth
            contradicted[k] += not_truth
            errors[k][i] = (et, er)
    out = []
    for k in ("all", "cross"):
        e = errors[k]
        mean_t = statistics.fmean(x for x, _ in e.values()) if e else math.nan
        mean_r = statistics.fmean(r for _, r in e.values()) if e else math.nan
        out.append(Score(*counts[k], mean_t, mean_r, {i: x for i, (x, _) in e.items()}, contradicted[k]))
    return out[0], out[1]


def run(job: tuple[str, int, Path, list[str], Transform2D, str, int]) -> Run:
    name, split, data, extra, frame, _clock, _draw = job
    path, range_max = LOGS[name]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "fleetmap", "map", str(data / path), "--out", str(out)]
        cmd += ["--split", str(split), "--no-return-reading", str(range_max), "--json", "--no-progress", *extra]
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


def corrected_relations(path: Path) -> list[tuple[int, int, Transform2D]]:
    """The corrected log's relations: every two scans whose corrected poses lie within
    :data:`CORRECTED_WITHIN` of each other, by scan index, the second's pose in the first's frame
    (the corrected poses are given to no algorithm)."""
    poses = [Transform2D(*s.odometry) for s in read_carmen(path) if s.odometry is not None]
    xy = np.array([[p.x, p.y] for p in poses])
    out = []
    for i, j in sorted(cKDTree(xy).query_pairs(CORRECTED_WITHIN)):
        out.append((i, j, poses[i].inverse().compose(poses[j])))
    return out


def score_by_index(
    by_index: dict[tuple[str, int], tuple[int, Transform2D]],
    relations: list[tuple[int, int, Transform2D]],
    raw: RawTruth | None = None,
) -> tuple[Score, Score]:
    """:func:`score` for relations named by scan index (a corrected log's stamps repeat); with the
    log's ``raw`` scans, a wrong relation they contradict is counted apart (:mod:`raw_truth`)."""
    poses = {index: (robot, n, pose) for (robot, index), (n, pose) in by_index.items()}

    def excused(k: int, estimate: Transform2D) -> bool:
        i, j, truth = relations[k]
        return raw is not None and raw.sides_with_map(i, j, truth, estimate, WRONG_M, WRONG_DEG)

    return _tally(((poses.get(i), poses.get(j), truth) for i, j, truth in relations), excused)


def map_config(extra: list[str]) -> FleetmapConfig:
    """The config ``fleetmap map`` runs with given the command line's other options (``extra``, as
    passed on to it for the full-rate logs: ``--odometry off``, ``--config FILE``, ...)."""
    ap = argparse.ArgumentParser(prog="fleetmap map")
    add_config_arguments(ap, CONFIG_SECTIONS, "offline")
    return config_from_args(ap.parse_args(extra))


def run_corrected(job: tuple[str, int, Path, list[str], Transform2D, str, int]) -> Run:
    """A corrected log mapped as ``fleetmap map LOG --split K`` maps it (same code, the default
    executor), in a process of its own, each piece's clock broken as ``clock`` says (on the
    job's ``draw``: 0, 1, ...); scored by scan index."""
    name, split, data, extra, frame, clock, draw = job
    path = data / "corrected" / f"{name.removeprefix('corrected/')}-corrected.log.gz"
    pieces = read_inputs([str(path)], split)
    if clock != "true":
        broken = [
            list(break_clock(p.scans, clock, seed=n + 1000 * draw)) for n, p in enumerate(pieces)
        ]  # no clock: ValueError
        pieces = [
            replace(p, scans=b, stamps={s.index: s.stamp for s in b}) for p, b in zip(pieces, broken, strict=True)
        ]
        name = f"{name} ({clock})" if draw == 0 else f"{name} ({clock}, draw {draw})"
    executor = make_executor("local")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            result = map_logs(pieces, Path(tmp) / "out", map_config(extra), executor=executor)
    finally:
        executor.close()
    all_, cross = score_by_index(result.by_index, corrected_relations(path), RawTruth(path))
    summary = result.report["map"]
    return Run(
        name,
        split,
        all_,
        cross,
        all_,
        cross,
        frame,
        summary["seconds"],
        summary["duration_s"] or math.nan,
        summary["integrations"],
        summary["components"],
    )


def _pct(n: int, d: int) -> str:
    return f"{100 * n / d:.1f} %" if d else "-"


def same_relations(cut: Score, whole: Run | None) -> str:
    """The cut's cross-robot relations' mean error against the whole log's (K = 1) on the same
    relations: the relations that cross a cut are not a random sample (mostly a loop's two passes,
    far apart in time), so the whole log's mean over all its relations says little of them."""
    ids = [i for i in cut.errors if i in whole.all.errors] if whole is not None else []
    if whole is None or not ids:
        return "-"
    w = statistics.fmean(whole.all.errors[i] for i in ids)
    c = statistics.fmean(cut.errors[i] for i in ids)
    return f"{w:.3f} m ({c / w:.2f}x)" if w > 0 else f"{w:.3f} m"


def _wrong(s: Score) -> str:
    return f"{s.wrong} (+{s.contradicted} the raw scans contradict)" if s.contradicted else str(s.wrong)


def table(runs: list[Run], everything: list[Run] | None = None) -> str:
    """The runs' rows; the whole log's (K = 1) run is looked for in ``everything`` (default: ``runs``)."""
    head = (
        "| log | K | relations placed | joined | within 0.10 m, 2 deg | mean error | wrong "
        "| cross-robot: placed | joined | within | mean error | whole log on them (ratio) | wrong "
        "| time (share of log) | integrations "
        "| components | relations' frame on the laser | within, laser frame (all / cross) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    wholes = {r.log: r for r in (everything or runs) if r.split == 1}
    rows = []
    for r in runs:
        a, c = r.all, r.cross
        rows.append(
            f"| {r.log} | {r.split} | {a.placed} of {a.relations} | {_pct(a.joined, a.placed)} "
            f"| {_pct(a.within, a.joined)} | {a.mean_t:.3f} m, {a.mean_r_deg:.2f} deg | {_wrong(a)} "
            + (
                f"| {c.placed} | {_pct(c.joined, c.placed)} | {_pct(c.within, c.joined)} "
                f"| {c.mean_t:.3f} m, {c.mean_r_deg:.2f} deg | {same_relations(c, wholes.get(r.log))} | {_wrong(c)} "
                if r.split > 1
                else "| - | - | - | - | - | - "
            )
            + f"| {r.seconds:.0f} s ({r.seconds / r.duration:.2f}) | {r.integrations} | {r.components} "
            + f"| {r.frame.x:+.3f}, {r.frame.y:+.3f} m "
            + f"| {_pct(r.laser_all.within, r.laser_all.joined)}"
            + (f" / {_pct(r.laser_cross.within, r.laser_cross.joined)} |" if r.split > 1 else " |")
        )
    return head + "\n".join(rows) + "\n"


def _in_process(processes: ProcessPoolExecutor, job: tuple[str, int, Path, list[str], Transform2D, str, int]) -> Run:
    """A corrected log's map (:func:`run_corrected`) in a worker process, waited for on a thread of
    the pool that bounds how many maps run at once (``--workers``, maps of either kind)."""
    return processes.submit(run_corrected, job).result()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--logs",
        default=",".join([*LOGS, "corrected"]),
        help="logs (comma-separated): full-rate ones by name, SLAM-corrected ones as corrected/NAME "
        "(or 'corrected' for all of them; default: every log)",
    )
    ap.add_argument("--splits", default="1,2,4,8", help="values of K (comma-separated)")
    ap.add_argument("--workers", type=int, default=1, help="maps at once (default 1: each map's time its own)")
    ap.add_argument("--clock", default="true", choices=CLOCKS, help="the corrected logs' clock (default: their own)")
    ap.add_argument(
        "--seeds", type=int, default=1, help="with --clock: map each log this many times, each clock broken anew"
    )
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args, extra = ap.parse_known_args()
    names = [
        m
        for n in args.logs.split(",")
        if n
        for m in ([f"corrected/{c}" for c in CORRECTED] if n == "corrected" else [n])
    ]
    unknown = [n for n in names if n not in LOGS and n.removeprefix("corrected/") not in CORRECTED]
    if unknown:
        raise SystemExit(f"unknown log {unknown[0]!r} (known: {', '.join(LOGS)}, corrected/NAME)")
    data = data_folder()
    frames = {
        n: measure(data / LOGS[n][0], data / "relations" / f"{n}.relations", LOGS[n][1]).offset
        if n in LOGS
        else Transform2D.identity()
        for n in names
    }
    if args.clock != "true" and any(n in LOGS for n in names):
        raise SystemExit(f"--clock {args.clock}: only the corrected logs' clocks are broken here (corrected/NAME)")
    if args.seeds < 1 or (args.seeds > 1 and args.clock == "true"):
        raise SystemExit("--seeds: a positive number, and more than 1 only with a broken --clock")
    jobs = [
        (n, int(k), data, extra, frames[n], args.clock, draw)
        for n in names
        for k in args.splits.split(",")
        for draw in range(args.seeds if n not in LOGS else 1)
    ]
    runs = []
    with ThreadPoolExecutor(max_workers=args.workers) as threads, ProcessPoolExecutor(args.workers) as processes:
        # at most --workers maps at once, of either kind: the times are shares of the logs' durations
        futures = [
            threads.submit(run, job) if job[0] in LOGS else threads.submit(_in_process, processes, job) for job in jobs
        ]
        refused = []
        for job, f in zip(jobs, futures, strict=True):
            try:
                r = f.result()
            except (BadInput, ValueError) as e:  # as fleetmap map refuses it; a clock there is none to break
                refused.append(f"- {job[0]} cut in {job[1]}: refused ({e})")
                print(refused[-1], flush=True)
                continue
            runs.append(r)
            print(table([r], runs).splitlines()[-1], flush=True)
    body = (
        "`fleetmap map` on the logs cut into K robots (`--split K`), scored with all of each log's "
        "relations; cross-robot: relations whose scans are in different robots' pieces. Errors in the "
        "relations' frame, measured on each log's raw scans by `benchmarks/relation_frame.py`; the "
        "corrected logs' relations are every two scans within 2 m by their corrected poses.\n\n"
        + table(runs)
        + "".join(f"\n{r}" for r in refused)
    )
    print(body)
    if args.write_results:
        write_result("relations", "Mapping real logs (`benchmarks/relations.py`)", body, config=map_config(extra))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
