"""Benchmark: where the integrations of one large merge run (run on demand, not in CI).

``fleetmap map`` of a whole real log cut into ``--split`` robots, once with its integrations in
its own process (inline), every integration job kept. Those jobs then run again on the local
process pool with 1 and 2 workers and on a local Ray cluster of 2 CPUs, as the merger hands them
out (as many in flight as the executor's capacity, results taken in order): seconds, the ratio
to one local worker, and whether every result is identical to the inline one (transform, value,
validity, information: bit for bit). Last, the whole ``fleetmap map`` run again with a pool of 2
workers: its seconds against the inline run's, and whether every scan's pose is identical.

    python benchmarks/executor.py                        # mit-csail, --split 8
    python benchmarks/executor.py --log aces --split 8 --write-results
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import deque
from pathlib import Path

from fleetmap.merger.executor import Executor, InlineExecutor, Job, Outcome, PairResult, make_executor
from results import write_result
from tracking import data_folder

from fleetmap.config_args import preset
from fleetmap.mapping import map_logs, read_inputs

LOGS = {"aces": ("aces/aces.clf.gz", 50.0), "fr079": ("fr079/fr079.clf.gz", 81.91)}
LOGS["mit-csail"] = ("mit-csail/mit-csail.clf.gz", 81.91)


class Keeping(InlineExecutor):
    """The inline executor, keeping every job it ran and its result (in the order submitted)."""

    def __init__(self) -> None:
        super().__init__()
        self.jobs: list[Job] = []
        self.results: list[Outcome | None] = []

    def submit(self, job: Job, here=None):  # type: ignore[no-untyped-def]
        handle = super().submit(job, here)
        n = len(self.jobs)
        self.jobs.append(job)
        self.results.append(None)
        outer = self

        class Kept:
            def result(self) -> Outcome:
                r = handle.result()
                outer.results[n] = r
                return r

        return Kept()


def run_all(executor: Executor, jobs: list[Job]) -> tuple[list[Outcome], float]:
    """Every job through ``executor`` as the merger's step hands them out; results, seconds."""
    start = time.perf_counter()
    out: list[Outcome] = []
    running: deque = deque()  # type: ignore[type-arg]
    for job in jobs:
        running.append(executor.submit(job))
        if len(running) >= executor.capacity:
            out.append(running.popleft().result())
    while running:
        out.append(running.popleft().result())
    return out, time.perf_counter() - start


def same(a: Outcome, b: Outcome) -> bool:
    """The same answer: an integration's transform, value and verdict, or a far search's score."""

    def said(r: Outcome) -> tuple[object, ...]:
        if not isinstance(r, PairResult):
            return (r.value,)
        i = r.integration
        return (r.transform, r.information, i.value, i.valid, i.violation, i.solid_violation)

    return said(a) == said(b)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", default="mit-csail", choices=sorted(LOGS))
    ap.add_argument("--split", type=int, default=8)
    ap.add_argument("--no-ray", action="store_true", help="skip the Ray cluster (Ray not installed)")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = ap.parse_args()
    path, range_max = LOGS[args.log]
    pieces = read_inputs([str(data_folder() / path)], args.split, None, range_max, None)
    config = preset("offline")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        kept = Keeping()
        t = time.perf_counter()
        inline = map_logs(pieces, Path(tmp) / "inline", config, None, kept)
        inline_map_s = time.perf_counter() - t
        jobs = kept.jobs
        print(f"{args.log} --split {args.split}: {len(jobs)} integrations, map {inline_map_s:.1f} s inline", flush=True)
        base_s = None
        kinds = [("local", 1), ("local", 2)] + ([] if args.no_ray else [("ray", 2)])
        for kind, workers in kinds:
            executor = make_executor(kind, workers)
            try:
                run_all(executor, jobs[: executor.capacity])  # workers started and warm (Ray: its cluster)
                results, seconds = run_all(executor, jobs)
            finally:
                executor.close()
            identical = all(b is not None and same(a, b) for a, b in zip(results, kept.results, strict=True))
            base_s = base_s or seconds
            rows.append((kind, workers, len(jobs), seconds, base_s / seconds, identical))
            print(rows[-1], flush=True)
        pool = make_executor("local", 2)
        try:
            t = time.perf_counter()
            pooled = map_logs(pieces, Path(tmp) / "pool", config, None, pool)
            pool_map_s = time.perf_counter() - t
        finally:
            pool.close()
    same_poses = [(r, s, c, p.as_array().tolist()) for r, s, c, p in pooled.poses] == [
        (r, s, c, p.as_array().tolist()) for r, s, c, p in inline.poses
    ]
    lines = [
        f"The {len(jobs)} integrations of `fleetmap map` of {args.log} with `--split {args.split}` "
        f"({len(pieces)} robots, {sum(len(p.scans) for p in pieces)} scans):",
        "",
        "| executor | workers | integrations | seconds | speed-up (vs local, 1) | identical to inline |",
        "|---|---|---|---|---|---|",
    ]
    for kind, workers, n, seconds, ratio, identical in rows:
        lines.append(f"| {kind} | {workers} | {n} | {seconds:.1f} | {ratio:.2f} | {'yes' if identical else 'NO'} |")
    lines += [
        "",
        f"The whole map: {inline_map_s:.1f} s with its integrations inline, {pool_map_s:.1f} s with a pool of 2 "
        f"(ratio {inline_map_s / pool_map_s:.2f}; tracking and the pose graph stay in the mapping process); "
        f"every scan's pose identical: {'yes' if same_poses else 'NO'}.",
    ]
    body = "\n".join(lines)
    print()
    print(body)
    if args.write_results:
        write_result("executor", "Integration workers (`benchmarks/executor.py`)", body, config=config)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
