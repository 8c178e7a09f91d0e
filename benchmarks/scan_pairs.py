"""Benchmark: consecutive scan pairs of the corrected logs, and why each fails (run on demand).

A robot agent grows its local map scan by scan (the pivot method), so a local map breaks where
consecutive scans do not integrate. This integrates every consecutive pair of each corrected log's
first ``--max-scans`` scans with no prior (INTEGRATE, as the agent's first witness does) and sorts
the pairs by outcome: right (within 0.3 m and 3 deg of the corrected poses) or wrong, valid or
not, and for the invalid ones the parts of the validity rule they fail:

- ``low``: value under ``valid_min_value`` or ``VALID_MIN_FRACTION`` of the smaller scan;
- ``viol``: more than ``VALID_MAX_VIOLATION`` of the value in the other scan's seen free space;
- ``amb``: a clearly different transformation scores more than ``VALID_MAX_AMBIGUITY`` of it.

A right but ambiguous pair is what a motion prior can settle; a wrong valid one is what breaks a
local map. The last column is the median, over the pairs that turn more than 10 degrees and are
placed within 3 degrees, of the rotation error as a fraction of the rotation: a scan whose beam
angles are stretched turns too far by the same fraction, so that a spin in place drifts.

``-v`` lists every pair that is not right and valid, with its best rival (where it puts the scan,
in the best's frame): along a corridor (a few tenths of a metre to a metre, no turn) or turned
round (180 deg, metres along).

A second table sorts those pairs by their *alias*: the wrong best, or the right best's best rival
(where geometry alone would put the scan instead). Turned round (over 170 deg from the step),
otherwise turned (over ``ALIAS_ROTATION``), or at the step's own heading: beside the way
(``ALIAS_ACROSS`` or more off it), short of the step (along the way, less far than the robot
drove, standing still or backing included) or past it. Steps under ``MIN_STEP`` are counted
apart. Along a corridor the value is nearly flat along the way, and on these logs the alias
lies mostly short of the step.

    python benchmarks/scan_pairs.py
    python benchmarks/scan_pairs.py --write-results    # and write its result (benchmarks/results/)
    python benchmarks/scan_pairs.py --datasets edmonton --kappa-noise-factor 0 -v
"""

from __future__ import annotations

import argparse
import collections
import math
import multiprocessing
import statistics
import sys
from collections.abc import Callable

from fleetmap.shared.config import FleetmapConfig, IntegrationParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Integration, integrate
from fleetmap.shared.core.validity import VALID_MAX_AMBIGUITY, VALID_MAX_VIOLATION, VALID_MIN_FRACTION
from merge import DATASETS, load_pieces, scan_maps
from results import markdown_table, write_result

from fleetmap.config_args import add_config_arguments, config_from_args

RIGHT_TRANSLATION = 0.3
RIGHT_ROTATION = math.radians(3)
TURN = math.radians(10)
ALIAS_ROTATION = math.radians(5)
ALIAS_ACROSS = 0.5
MIN_STEP = 0.5
ALIAS_KINDS = ("short of the step", "past the step", "beside the way", "turned round", "turned", "short steps")


def alias_kind(alias: Transform2D, truth: Transform2D) -> str:
    """What an alias of the step ``truth`` is (see the module docstring)."""
    turn = abs(math.remainder(alias.theta - truth.theta, 2 * math.pi))
    if turn > math.radians(170):
        return "turned round"
    if turn > ALIAS_ROTATION:
        return "turned"
    step = math.hypot(truth.x, truth.y)
    if step < MIN_STEP:
        return "short steps"
    ux, uy = truth.x / step, truth.y / step
    if abs(uy * alias.x - ux * alias.y) >= ALIAS_ACROSS:
        return "beside the way"
    return "short of the step" if alias.x * ux + alias.y * uy < step else "past the step"


def failed_parts(r: Integration, smaller: float, p: IntegrationParams) -> str:
    """The parts of the scan-pair validity rule (``is_valid``) that ``r`` fails."""
    parts = []
    if r.value < p.validity.valid_min_value or r.value < VALID_MIN_FRACTION * smaller:
        parts.append("low")
    if r.violation > VALID_MAX_VIOLATION * r.value:
        parts.append("viol")
    if r.runner_up > VALID_MAX_AMBIGUITY * (r.value - r.violation):
        parts.append("amb")
    return "+".join(parts)


Result = tuple[str, collections.Counter[str], list[str], list[float], collections.Counter[str]]
"""A dataset's name, its pairs by outcome, the lines of ``-v``, its turns' rotation errors, its aliases."""


def classify(job: tuple[str, int, FleetmapConfig]) -> Result:
    name, max_scans, config = job
    piece = load_pieces(name, 1, 0, max_scans, config)[0]
    scans = scan_maps(piece, config)
    p = config.integration
    counts: collections.Counter[str] = collections.Counter()
    aliases: collections.Counter[str] = collections.Counter()
    rows = []
    turn_errors = []
    for j in range(1, len(piece.scans)):
        a, b = scans[j - 1], scans[j]
        truth = piece.truth[j - 1].inverse().compose(piece.truth[j])
        r = integrate(a, b, p)
        dt, dr = r.transform.distance(truth)
        right = dt <= RIGHT_TRANSLATION and dr <= RIGHT_ROTATION
        if abs(truth.theta) > TURN and dr <= RIGHT_ROTATION:
            turn_errors.append(math.remainder(r.transform.theta - truth.theta, 2 * math.pi) / truth.theta)
        key = ("right" if right else "wrong") + (
            " valid" if r.valid else " invalid: " + failed_parts(r, min(a.total_length, b.total_length), p)
        )
        counts[key] += 1
        if right and r.valid:
            continue
        alias = r.transform if not right else r.rivals[0][0] if r.rivals else None
        kind = "" if alias is None else alias_kind(alias, truth)
        if kind:
            aliases[kind] += 1
        rival = ""
        if r.rivals:
            d = r.transform.inverse().compose(r.rivals[0][0])
            rival = f", best rival at ({d.x:.2f}, {d.y:.2f}) m turned {math.degrees(d.theta):.0f} deg"
        rows.append(
            f"{j - 1}->{j} {key}: {dt:.2f} m / {math.degrees(dr):.1f} deg off, value {r.value:.1f}, "
            f"violation {r.violation:.1f}, runner-up {r.runner_up:.1f}{rival}" + (f"; alias {kind}" if kind else "")
        )
    return name, counts, rows, turn_errors, aliases


COLUMNS: dict[str, Callable[[str], bool]] = {
    "right, valid": lambda k: k == "right valid",
    "right, only ambiguous": lambda k: k == "right invalid: amb",
    "right, invalid otherwise": lambda k: k.startswith("right invalid") and k != "right invalid: amb",
    "wrong, invalid": lambda k: k.startswith("wrong invalid"),
    "wrong, valid": lambda k: k == "wrong valid",
}
"""The outcome columns of the first table: which of ``classify``'s keys each one counts."""
TITLE = "Consecutive scan pairs of the corrected logs (`benchmarks/scan_pairs.py`)"
EXPLAINED = (
    "Every consecutive pair of each corrected log's first `--max-scans` scans integrated with no prior. Right: within "
    f"{RIGHT_TRANSLATION} m and {math.degrees(RIGHT_ROTATION):.0f} deg of the corrected poses; valid or not by "
    "the scan-pair validity rule (only ambiguous: a clearly different transformation scores nearly as much, "
    "which a motion prior can settle; invalid otherwise: too low a value or too much of it in the other "
    "scan's seen free space, ambiguous or not); a wrong valid pair is what breaks a local map. Rotation error "
    "on turns: the median, over the pairs that turn more than 10 deg and are placed within 3 deg, of the "
    "rotation error as a share of the rotation (how many such pairs). The second table sorts the pairs not "
    "right and valid by their alias (the wrong best, or the right best's best rival): turned round (over "
    f"170 deg from the step), turned (over {math.degrees(ALIAS_ROTATION):.0f} deg), beside the way "
    f"({ALIAS_ACROSS} m or more off it), short of the step or past it; steps under {MIN_STEP} m apart."
)


def tables(results: list[Result]) -> str:
    """The two printed tables: pairs by outcome, and pairs not right and valid by alias."""
    outcomes = []
    for name, counts, _, turns, _ in results:
        cells = [sum(n for k, n in counts.items() if test(k)) for test in COLUMNS.values()]
        bias = f"{100 * statistics.median(turns):+.2f} % ({len(turns)})" if turns else "-"
        outcomes.append([name, str(sum(counts.values())), *map(str, cells), bias])
    head = ["dataset", "pairs", *COLUMNS, "rotation error on turns"]
    kinds = [[name, str(sum(a.values())), *(str(a[k]) for k in ALIAS_KINDS)] for name, _, _, _, a in results]
    alias_head = ["dataset", "pairs not right and valid, by alias", *ALIAS_KINDS]
    return markdown_table(head, outcomes) + "\n\n" + markdown_table(alias_head, kinds)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default="aces,csail,freiburg-101,infinite-corridor,edmonton,orebro")
    ap.add_argument("--max-scans", type=int, default=200, help="scans used per dataset (after subsampling)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("-v", "--verbose", action="store_true", help="list the pairs that are not right and valid")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    add_config_arguments(ap, ["extraction", "integration"])
    args = ap.parse_args()
    config = config_from_args(args)
    names = args.datasets.split(",")
    unknown = [n for n in names if n not in DATASETS]
    if unknown:
        ap.error(f"unknown datasets {', '.join(unknown)} (known: {', '.join(DATASETS)})")
    with multiprocessing.Pool(args.workers) as pool:
        results = pool.map(classify, [(n, args.max_scans, config) for n in names])
    body = tables(results)
    print(body)
    if args.write_results:
        write_result("scan-pairs", TITLE, EXPLAINED + "\n\n" + body, config=config)
    if args.verbose:
        for name, counts, rows, _, _ in results:
            print(f"\n{name}: " + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())))
            print("\n".join("  " + r for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
