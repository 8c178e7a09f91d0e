"""Benchmark: does the merger's cost grow with what is new, or with the whole map? (run on demand)

A fleet that drives the same building again and again: ``fleetmap map LOG LOG ...`` with the
log given 1 and N times (each copy one robot, their clocks starting together), mapped as the
command maps it (same code, the default executor). Printed per run: the time, its share of the
log's duration, the integrations, the submaps; the merger's step time (median) over the first and
the last tenth of the steps; and the ratio of N tours' time to one tour's. Issue 49's targets: N =
4 tours in at most 5 times one tour's time, and the last tenth's steps at most twice the first
tenth's.

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

    def tenth(self, last: bool) -> float:
        """The median step time (s) over the first or the last tenth of the steps."""
        n = max(len(self.steps) // 10, 1)
        part = self.steps[-n:] if last else self.steps[:n]
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
        "| step time, first tenth / last tenth (median) | last / first |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        base = one.get(r.log)
        first, last = r.tenth(False), r.tenth(True)
        against = "-" if base is None else f"{r.seconds / base:.1f}x"
        rows.append(
            f"| {r.log} | {r.copies} | {r.seconds:.0f} s ({r.seconds / r.duration:.2f}) | {against} "
            f"| {r.integrations} | {r.submaps} | {len(r.steps)} | {1000 * first:.0f} / {1000 * last:.0f} ms "
            f"| {last / first:.1f} |"
        )
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
        "starting together); the merger's step time over the first and last tenth of its steps.\n\n" + table(runs)
    )
    print(body)
    if args.write_results:
        write_result(
            "growth", "The merger's cost as the map grows (`benchmarks/growth.py`)", body, config=preset("offline")
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
