"""Benchmark: does the seen free space refute right alignments? Wall one map puts where the other saw through.

The validity rule (``shared/core/validity.py``) and the joins' wholes rule (``merger/joins.py``)
take wall that one submap puts in the other's seen free space as evidence against an alignment:
more than :data:`~fleetmap.shared.core.validity.VALID_MAX_MAP_VIOLATION` of the matched wall
(:func:`~fleetmap.shared.core.validity.max_map_violation`), and at least
:data:`~fleetmap.shared.core.validity.VALID_REFUTE_VIOLATION` metres of it, refutes. That holds in
a world that stands still and that a laser cannot see through. Each corrected log
(``../shared/data/corrected``, poses a SLAM system corrected, given to no algorithm) is mapped as
``fleetmap map LOG --split K`` maps it; then, for the pairs of submaps the merger integrated, each
pair is also looked at where the corrected poses put it (a submap's true frame is its frame
scan's corrected pose), with the grid look the wholes rule takes (solid walls, both ways):

- **right alignments refuted**: of the pairs that share at least ``valid_min_value`` of wall at the
  corrected poses, the share whose wall in seen free space there is as much as refutes an
  alignment; apart: those whose scans are more than :data:`LATER` scans apart (a second visit: the
  world may have changed between them);
- **links refuted**: the robots' own links between consecutive submaps, looked at where the link
  puts them (seconds apart: what the laser sees through, not what moved);
- **wrong integrations refuted**: the integrations more than 1 m or 10 degrees off the corrected
  poses that share that much wall where they put the pair, the share the same look refutes: what
  the rule is for.

    python benchmarks/free_space.py [--logs aces,freiburg-campus,...] [--splits 1] [--write-results]
"""

from __future__ import annotations

import math
import statistics
import tempfile
from pathlib import Path

import numpy as np
from covariances import rows_by_log
from fleetmap.merger.executor import make_executor
from fleetmap.shared.core.geometry import Transform2D, wrap_scalar
from fleetmap.shared.core.validity import VALID_REFUTE_VIOLATION, refuted_by_free_space
from fleetmap.shared.io.logs import read_carmen
from results import markdown_table, write_result
from wrong_relations import frame_truth

from fleetmap.config_args import preset
from fleetmap.mapping import map_logs, read_inputs

LATER = 200
"""Pairs whose scans' medians lie more than this many scans apart are a second visit (about 200 m
on the corrected logs, a scan about every metre): a split of the report, not a rule."""

HEADER = [
    "log",
    "K",
    "pairs at the corrected poses",
    "right alignments refuted",
    "of those a second visit",
    "wall in free space, median / 90th percentile share",
    "links refuted",
    "wrong integrations refuted",
]


def _scan_middle(submaps: dict, key: str) -> float | None:
    s = submaps[key].scan_indices
    return float(np.median(s)) if s is not None and len(s) else None


def run(job: tuple[str, int, Path]) -> list[str]:
    name, split, data = job
    path = data / "corrected" / f"{name}-corrected.log.gz"
    truth = [Transform2D(*s.odometry) for s in read_carmen(path) if s.odometry is not None]
    config = preset("offline")
    executor = make_executor("local")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            result = map_logs(read_inputs([str(path)], split), Path(tmp) / "out", config, executor=executor)
    finally:
        executor.close()
    merger = result.merger
    assert merger is not None
    graph = merger.graph
    p = config.integration
    least = p.validity.valid_min_value
    at = {k: t for k, m in merger.submaps.items() if (t := frame_truth(m, truth)) is not None}
    right, later, shares, wrong = [], [], [], []
    seen: set[tuple[str, str]] = set()
    for e in graph.edges:
        if e.link or e.a not in at or e.b not in at or e.key() in seen:
            continue
        seen.add(e.key())
        true = at[e.a].inverse().compose(at[e.b])
        hit, free = graph._look(e.a, e.b, true, solid=True)
        if hit >= least:
            refuted = refuted_by_free_space(hit, free, p)
            right.append(refuted)
            shares.append(free / hit)
            ma, mb = _scan_middle(merger.submaps, e.a), _scan_middle(merger.submaps, e.b)
            if ma is not None and mb is not None and abs(ma - mb) > LATER:
                later.append(refuted)
        off = true.inverse().compose(e.transform)
        if math.hypot(off.x, off.y) > 1.0 or abs(wrap_scalar(off.theta)) > math.radians(10.0):
            hit, free = graph._look(e.a, e.b, e.transform, solid=True)
            if hit >= least:
                wrong.append(refuted_by_free_space(hit, free, p))
    links = [
        refuted_by_free_space(*graph._look(e.a, e.b, e.transform, solid=True), p)
        for e in graph.links
        if e.a in at and e.b in at
    ]

    def share(xs: list[bool]) -> str:
        return f"{100 * sum(xs) / len(xs):.1f} % of {len(xs)}" if xs else "-"

    q = sorted(shares)
    spread = f"{statistics.median(q):.3f} / {q[int(0.9 * (len(q) - 1))]:.3f}" if q else "-"
    return [name, str(split), str(len(seen)), share(right), share(later), spread, share(links), share(wrong)]


def main() -> int:
    rows, write = rows_by_log(__doc__ or "", "1", run)
    table = markdown_table(HEADER, rows)
    print(table)
    if write:
        body = (
            "Pairs of submaps the merger integrated, looked at where the corrected poses put them (solid wall on "
            f"wall at least `valid_min_value`); refuted: at least {VALID_REFUTE_VIOLATION:g} m of it in the other's "
            "seen free space and more than the validity rule allows; a second visit: scans more than "
            f"{LATER} apart.\n\n" + table
        )
        write_result(
            "free-space",
            "Free space against right alignments (`benchmarks/free_space.py`)",
            body,
            config=preset("offline"),
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
