"""Benchmark: does the merger's cost grow with what is new, or with the whole map? (run on demand)

A fleet that drives the same building again and again: ``fleetmap map LOG LOG ...`` with the
log given 1 and N times (each copy one robot, their clocks starting together), mapped as the
command maps it (same code, the default executor). Printed per run: the time, its share of the
log's duration, the integrations, the submaps, and the ratio of N tours' time to one tour's.

A merger step is one of two kinds, and they differ by two orders of magnitude: a step that
integrates a new submap version with its partners (a dozen integrations, waited for from the
pool: 0.1-0.5 s) and a step that integrates nothing (1-2 ms). One median over all the steps of a
tenth reads whichever kind that tenth happens to hold more of, so each kind is timed apart: the
median over the first and the last tenth of that kind's steps, and their ratio. A second table
gives the time per step against the submaps in the graph. Issue 49's targets: N = 4 tours in at
most 5 times one tour's time, and the last tenth's steps at most twice the first tenth's.

    python benchmarks/growth.py                          # aces, 1 and 4 tours
    python benchmarks/growth.py --log mit-csail --copies 1,2,4 --write-results
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from fleetmap.merger.executor import make_executor

from fleetmap.config_args import preset
from fleetmap.mapping import map_logs, read_inputs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results import write_result
from tracking import LOGS, data_folder


@dataclass(frozen=True)
class Growth:
    log: str
    copies: int
    seconds: float
    duration: float
    integrations: int
    submaps: int
    steps: list[tuple[int, int, float]]
    """(submaps in the graph, integrations so far, seconds) of every step."""

    def kind(self, integrating: bool) -> list[tuple[int, int, float]]:
        """The steps that integrated something (``integrating``) or nothing, in order, as
        (submaps in the graph, integrations in the step, seconds)."""
        out, before = [], 0
        for n, total, s in self.steps:
            if (total > before) == integrating:
                out.append((n, total - before, s))
            before = total
        return out

    def tenth(self, integrating: bool, last: bool) -> float:
        """The median time (s) of a kind of step over the first or the last tenth of its steps."""
        steps = self.kind(integrating)
        n = max(len(steps) // 10, 1)
        part = steps[-n:] if last else steps[:n]
        return statistics.median(s for _, _, s in part) if part else float("nan")


def run(log: str, copies: int) -> Growth:
    path, range_max = LOGS[log]
    pieces = read_inputs([str(data_folder() / path)] * copies, 1, range_max=range_max)
    steps: list[tuple[int, int, float]] = []
    executor = make_executor("local")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            result = map_logs(
                pieces, Path(tmp), preset("offline"), executor=executor, on_step=lambda *s: steps.append(s)
            )
    finally:
        executor.close()
    summary = result.report["map"]
    return Growth(
        log,
        copies,
        summary["seconds"],
        summary["session_s"],
        summary["integrations"],
        summary["submaps"],
        steps,
    )


def table(runs: list[Growth]) -> str:
    one = {r.log: r.seconds for r in runs if r.copies == 1}
    rows = [
        "| log | tours | time (share of the log) | against one tour | integrations | submaps | steps "
        "| integrating steps: first tenth / last tenth (median) | last / first "
        "| quiet steps: first tenth / last tenth (median) | last / first |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        base = one.get(r.log)
        against = "-" if base is None else f"{r.seconds / base:.1f}x"
        cells = []
        for integrating in (True, False):
            first, last = r.tenth(integrating, False), r.tenth(integrating, True)
            cells.append(f"{len(r.kind(integrating))}: {1000 * first:.0f} / {1000 * last:.0f} ms | {last / first:.1f}")
        rows.append(
            f"| {r.log} | {r.copies} | {r.seconds:.0f} s ({r.seconds / r.duration:.2f}) | {against} "
            f"| {r.integrations} | {r.submaps} | {len(r.steps)} | " + " | ".join(cells) + " |"
        )
    return "\n".join(rows)


def by_size(r: Growth, bins: int = 5) -> str:
    """The step time against the submaps in the graph: the steps in ``bins`` equal spans of it."""
    top = max(n for n, _, _ in r.steps)
    rows = [
        f"{r.log}, {r.copies} tour(s):\n",
        "| submaps in the graph | steps | integrating: steps, integrations each (median), time (median) "
        "| quiet: steps, time (median) |",
        "|---|---|---|---|",
    ]
    for b in range(bins):
        lo, hi = b * top // bins, (b + 1) * top // bins
        inside = [(n, c, s) for n, c, s in r.kind(True) if lo < n <= hi]
        quiet = [(n, c, s) for n, c, s in r.kind(False) if lo < n <= hi]
        cell_i = (
            f"{len(inside)}, {statistics.median(c for _, c, _ in inside):.0f}, "
            f"{1000 * statistics.median(s for _, _, s in inside):.0f} ms"
            if inside
            else "0"
        )
        cell_q = f"{len(quiet)}, {1000 * statistics.median(s for _, _, s in quiet):.1f} ms" if quiet else "0"
        rows.append(f"| {lo + 1}-{hi} | {len(inside) + len(quiet)} | {cell_i} | {cell_q} |")
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", default="aces", choices=sorted(LOGS), help="the full-rate log (default aces)")
    ap.add_argument("--copies", default="1,4", help="tours to map, comma-separated (default 1,4)")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = ap.parse_args()
    runs = []
    for n in sorted({int(c) for c in args.copies.split(",") if c}):
        runs.append(run(args.log, n))
        print(table(runs).splitlines()[-1], flush=True)
    body = (
        f"`fleetmap map` on {args.log} given 1 and more times (each copy one robot, one tour each, their clocks "
        "starting together). A step that integrates (a new submap version with its partners, waited for from "
        "the integration pool) and a quiet step (nothing to integrate) differ a hundredfold, so each kind is "
        "timed apart: its count, then the median over the first and the last tenth of its steps.\n\n"
        + table(runs)
        + "\n\nThe step time against the submaps in the graph:\n\n"
        + "\n\n".join(by_size(r) for r in runs)
    )
    print(body)
    if args.write_results:
        write_result(
            "growth", "The merger's cost as the map grows (`benchmarks/growth.py`)", body, config=preset("offline")
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
