"""Benchmark tool: where a corrected log's map is wrong, by scan, by robot and by the merger's own
edges (run on demand, not in CI).

A corrected log (``../shared/data/corrected``) is mapped as ``fleetmap map LOG --split K`` maps it
(in this process, the default executor) and scored with its relations as
``benchmarks/relations.py`` scores it. Then it prints:

- the wrong relations (> 1 m or 10 degrees), counted by robot pair, and the stretches of scans
  they hold (consecutive scans of one robot, gaps of up to 5), each with how many wrong
  relations have a scan in it and their median error: where the map is wrong;
- the merger's integrations against the corrected poses: those the last solve *accepted* (tree
  or loop) that are wrong (> 1 m or 10 degrees), and the *valid* ones it *rejected* that are right
  (within 0.3 m and 3 degrees): which joins went wrong and which were refused;
- the robots' own links between consecutive submaps off by more than their own covariance says
  (Mahalanobis^2 beyond chi-square's 99 % with 3 degrees of freedom) or by more than 1 m or
  10 degrees: what tracking handed the merger wrong;
- each component's frames against the corrected poses, laid on them by the median turn and shift
  between them: by chain (a robot's epoch), how far its frames stand off, the
  most and where, and the stretches of frames more than 1 m off: where the refined map is wrong
  although every join and loop may be right (a chain drifted, its links tighter than their error).

A submap's true frame is its frame scan's corrected pose. The corrected poses are GMapping's, wrong at a few scans
(``raw_truth.py``); a wrong relation the raw scans contradict is listed apart.

    python benchmarks/wrong_relations.py corrected/freiburg-campus --split 6
    python benchmarks/wrong_relations.py corrected/orebro --split 1 --odometry off
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from fleetmap.merger.executor import make_executor
from fleetmap.shared.core.geometry import Transform2D, wrap_scalar
from fleetmap.shared.core.motion import CHI2_3DOF_99
from fleetmap.shared.io.logs import read_carmen

from fleetmap.mapping import map_logs, read_inputs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raw_truth import RawTruth, beyond
from relations import WRONG_DEG, WRONG_M, corrected_relations, map_config
from tracking import CORRECTED, data_folder

RIGHT_M, RIGHT_DEG = 0.3, 3.0
"""An integration this close to the corrected poses counts as right (the corrected poses' own
error is a few centimetres; their submaps' frames a little more)."""
LOOSE_DEG = 2.0
"""A link whose heading's standard deviation is beyond this (degrees) is listed as loose: one that
steps the walls did not check left open (a registration's is under a degree)."""
GAP = 5
"""Scans of one robot this close in the log belong to one stretch of the listing."""


def stretches(scans: dict[tuple[str, int], list[float]]) -> list[tuple[str, int, int, int, float]]:
    """(robot, first scan, last scan, wrong relations, their median error in m) of each stretch of a
    robot's consecutive scans (gaps up to :data:`GAP`), most wrong relations first."""
    out = []
    by_robot: dict[str, list[int]] = defaultdict(list)
    for robot, i in scans:
        by_robot[robot].append(i)
    for robot, indices in by_robot.items():
        indices.sort()
        run = [indices[0]]
        for i in [*indices[1:], None]:
            if i is not None and i - run[-1] <= GAP:
                run.append(i)
                continue
            errors = [e for j in run for e in scans[(robot, j)]]
            out.append((robot, run[0], run[-1], len(errors), statistics.median(errors)))
            if i is not None:
                run = [i]
    return sorted(out, key=lambda s: -s[3])


def frame_truth(submap, truth: list[Transform2D]) -> Transform2D | None:
    """The submap's frame in the corrected poses' frame: its frame scan's corrected pose (None:
    beyond the log, or a submap that does not say its frame scan)."""
    if submap.frame_scan is None or submap.frame_scan >= len(truth):
        return None
    return truth[submap.frame_scan]


def _error(estimate: Transform2D, true: Transform2D) -> tuple[float, float]:
    e = true.inverse().compose(estimate)
    return math.hypot(e.x, e.y), math.degrees(abs(e.theta))


def _span(submap) -> str:
    s = submap.scan_indices
    return f"{int(min(s))}-{int(max(s))}" if s is not None and len(s) else "-"


def list_relations(result, relations, raw: RawTruth) -> None:
    poses = {index: (robot, n, pose) for (robot, index), (n, pose) in result.by_index.items()}
    wrong, contradicted = [], 0
    apart: Counter[tuple[str, str]] = Counter()
    for i, j, truth in relations:
        a, b = poses.get(i), poses.get(j)
        if a is not None and b is not None and a[1] != b[1]:
            apart[tuple(sorted((f"{a[0]} ({a[1]})", f"{b[0]} ({b[1]})")))] += 1
        if a is None or b is None or a[1] != b[1]:
            continue
        estimate = a[2].inverse().compose(b[2])
        error = truth.inverse().compose(estimate)
        if not beyond(error, WRONG_M, WRONG_DEG):
            continue
        if raw.sides_with_map(i, j, truth, estimate, WRONG_M, WRONG_DEG):
            contradicted += 1
            continue
        wrong.append((a[0], i, b[0], j, math.hypot(error.x, error.y), math.degrees(abs(error.theta))))
    components: dict[str, set[int]] = defaultdict(set)
    for robot, n, _ in poses.values():
        components[robot].add(n)
    print("\n## Components by robot\n")
    for robot in sorted(components):
        print(f"- {robot}: {sorted(components[robot])}")
    if apart:
        print("\nRelations not joined (robot (component) with robot (component)):\n")
        for (ra, rb), n in apart.most_common():
            print(f"- {ra} with {rb}: {n}")
    print(f"\n## Wrong relations: {len(wrong)} (+{contradicted} the raw scans contradict)\n")
    pairs = Counter(tuple(sorted((ra, rb))) for ra, _, rb, _, _, _ in wrong)
    for (ra, rb), n in pairs.most_common():
        print(f"- {ra} with {rb}: {n}" + (" (own)" if ra == rb else " (cross-robot)"))
    scans: dict[tuple[str, int], list[float]] = defaultdict(list)
    for ra, i, rb, j, et, _ in wrong:
        scans[(ra, i)].append(et)
        scans[(rb, j)].append(et)
    if scans:
        print("\n| robot | scans | wrong relations with a scan here | median error |\n|---|---|---|---|")
        for robot, first, last, n, med in stretches(scans)[:25]:
            print(f"| {robot} | {first}-{last} | {n} | {med:.2f} m |")


def _solved(merger) -> dict[tuple[str, str], tuple[str, object]]:
    """The last solve's integrations by key: ("accepted" or "rejected", the edge as the solve took
    it). An ambiguous integration a cycle confirmed is there as the alignment the cycle took (one
    of its rivals, perhaps), valid; the graph holds it as integrated."""
    solved = merger.result
    if solved is None:
        return {}
    out = {e.key(): ("accepted", e) for e in [*solved.tree, *solved.loops] if not e.link}
    out.update({e.key(): ("rejected", e) for e in solved.rejected if not e.link})
    return out


def list_edges(result, truth: list[Transform2D]) -> None:
    merger = result.merger
    if merger.result is None:
        print("\nThe merger never solved.")
        return
    solved = _solved(merger)
    frames = {k: frame_truth(m, truth) for k, m in merger.submaps.items()}
    rows: dict[str, list[str]] = {"accepted wrong": [], "rejected right": []}
    counts = Counter()
    for e in merger.graph.edges:
        if e.link or frames.get(e.a) is None or frames.get(e.b) is None:
            continue
        if e.key() not in solved:
            counts["valid, not in the last solve" if e.valid else "invalid"] += 1
            continue
        verdict, taken = solved[e.key()]
        if taken.a != e.a:
            taken = taken.reversed()
        et, er = _error(taken.transform, frames[e.a].inverse().compose(frames[e.b]))
        right, bad = et < RIGHT_M and er < RIGHT_DEG, et > WRONG_M or er > WRONG_DEG
        counts[f"{verdict} {'right' if right else 'wrong' if bad else 'between'}"] += 1
        counts[f"{verdict} as a rival the cycle confirmed"] += not e.valid
        kind = f"{verdict} {'wrong' if verdict == 'accepted' else 'right'}"
        if (verdict == "accepted" and bad) or (verdict == "rejected" and right):
            sa, sb = merger.submaps[e.a], merger.submaps[e.b]
            rows[kind].append(
                f"| {e.a} ({_span(sa)}) | {e.b} ({_span(sb)}) | {et:.2f} m, {er:.1f} deg | {taken.value:.1f} |"
            )
    print("\n## The merger's integrations against the corrected poses\n")
    print(", ".join(f"{k}: {n}" for k, n in sorted(counts.items()) if n))
    for kind, lines in rows.items():
        if lines:
            print(f"\n{kind}:\n\n| a (scans) | b (scans) | error | value |\n|---|---|---|---|")
            print("\n".join(lines))


def list_edges_of(result, truth: list[Transform2D], scans: list[int]) -> None:
    """Every integration tried of the submaps that place any of ``scans``: its verdict in the last
    solve and its error (as the solve took it, where it did)."""
    merger = result.merger
    solved = merger.result
    verdicts = _solved(merger)
    frames = {k: frame_truth(m, truth) for k, m in merger.submaps.items()}
    keys = {
        k
        for k, m in merger.submaps.items()
        if m.scan_indices is not None and set(map(int, m.scan_indices)) & set(scans)
    }
    for key in sorted(keys):
        m = merger.submaps[key]
        where = solved.poses.get(key) if solved else None
        print(f"\n### {key} (scans {_span(m)}, frame scan {m.frame_scan}): placed {where}\n")
        print("| with (scans) | valid | verdict | error | value | wall in free space (m) |\n|---|---|---|---|---|---|")
        for e in merger.graph.edges:
            if key not in (e.a, e.b):
                continue
            other = e.b if e.a == key else e.a
            verdict, taken = verdicts.get(e.key(), ("-", e))
            if taken.a != e.a:
                taken = taken.reversed()
            err = "-"
            if frames.get(e.a) is not None and frames.get(e.b) is not None:
                true = frames[e.a].inverse().compose(frames[e.b])
                err = "{:.2f} m, {:.1f} deg".format(*_error(taken.transform, true))
            cells = f"| {other} ({_span(merger.submaps[other])}) | {e.valid} | {verdict} | {err} "
            print(cells + f"| {e.value:.1f} | {e.violation:.1f} |")


def list_links(result, truth: list[Transform2D]) -> None:
    merger = result.merger
    frames = {k: frame_truth(m, truth) for k, m in merger.submaps.items()}
    by_place = {(m.robot, m.epoch, m.submap): k for k, m in merger.submaps.items()}
    lines, loose, n = [], [], 0
    for k, m in merger.submaps.items():
        if m.link is None:
            continue
        prev = by_place.get((m.robot, m.epoch, m.link.submap))
        if prev is None or frames.get(prev) is None or frames.get(k) is None:
            continue
        n += 1
        true = frames[prev].inverse().compose(frames[k])
        e = true.inverse().compose(m.link.transform)
        # the link's covariance is on the submap's pose in the previous one's frame: its error there
        t = m.link.transform
        v = np.array([t.x - true.x, t.y - true.y, wrap_scalar(t.theta - true.theta)])
        try:
            d2 = float(v @ np.linalg.solve(m.link.covariance_matrix, v))
        except np.linalg.LinAlgError:
            d2 = math.inf
        et, er = math.hypot(e.x, e.y), math.degrees(abs(e.theta))
        sd = math.degrees(math.sqrt(max(m.link.covariance_matrix[2, 2], 0.0)))
        row = f"| {prev} ({_span(merger.submaps[prev])}) | {k} ({_span(m)}) | {et:.2f} m, {er:.1f} deg "
        row += f"| {sd:.1f} deg | {d2:.1f} |"
        if d2 > CHI2_3DOF_99 or et > WRONG_M or er > WRONG_DEG:
            lines.append(row)
        if sd > LOOSE_DEG:
            loose.append(row)
    head = "| from (scans) | to (scans) | error | heading's sd | Mahalanobis^2 |\n|---|---|---|---|---|"
    for title, rows in (("not covered by their covariance", lines), (f"looser than {LOOSE_DEG} degrees", loose)):
        print(f"\n## Links {title}: {len(rows)} of {n}\n")
        if rows:
            print(head + "\n" + "\n".join(rows))


def laid_on(solved: list[Transform2D], true: list[Transform2D]) -> Transform2D:
    """The rigid transform that lays ``solved`` frames on their ``true`` ones: the median turn
    between their headings, then the median shift between their positions (the median: a
    drifted stretch stands out, its error not spread over the rest)."""
    turn = float(np.median([wrap_scalar(b.theta - a.theta) for a, b in zip(solved, true, strict=True)]))
    c, s = math.cos(turn), math.sin(turn)
    shift = np.median(
        [[b.x - (c * a.x - s * a.y), b.y - (s * a.x + c * a.y)] for a, b in zip(solved, true, strict=True)], axis=0
    )
    return Transform2D(float(shift[0]), float(shift[1]), turn)


def frame_offsets(solved: dict[str, Transform2D], true: dict[str, Transform2D]) -> dict[str, tuple[float, float]]:
    """Each frame's offset from its true one (m, deg), the solution laid on the truth
    (:func:`laid_on`)."""
    keys = [k for k in solved if k in true]
    if not keys:
        return {}
    lay = laid_on([solved[k] for k in keys], [true[k] for k in keys])
    out = {}
    for k in keys:
        e = true[k].inverse().compose(lay.compose(solved[k]))
        out[k] = (math.hypot(e.x, e.y), math.degrees(abs(wrap_scalar(e.theta))))
    return out


def runs_over(scans: list[int], values: list[float], bound: float) -> list[tuple[int, int]]:
    """The runs of consecutive entries (a chain's frames in order) whose value exceeds ``bound``,
    each as its first and last frame scan."""
    out: list[tuple[int, int]] = []
    start = None
    for n, v in enumerate([*values, -math.inf]):
        if v > bound and start is None:
            start = n
        elif v <= bound and start is not None:
            out.append((scans[start], scans[n - 1]))
            start = None
    return out


def list_frames(result, truth: list[Transform2D]) -> None:
    merger = result.merger
    solved = merger.result
    if solved is None:
        return
    frames = {k: frame_truth(m, truth) for k, m in merger.submaps.items()}
    print("\n## Frames against the corrected poses, each component laid on them by the median\n")
    print("| component | chain | frames | median off | most off (frame scan) | most turned | over 1 m (frame scans) |")
    print("|---|---|---|---|---|---|---|")
    for n, c in enumerate(solved.components):
        poses = {k: solved.poses[k] for k in c.members if solved.poses.get(k) is not None}
        offsets = frame_offsets(poses, {k: f for k, f in frames.items() if f is not None})
        chains: dict[str, list[str]] = defaultdict(list)
        for k in offsets:
            chains[k.rsplit("/", 1)[0]].append(k)
        for chain, keys in sorted(chains.items()):
            keys.sort(key=lambda k: merger.submaps[k].frame_scan)
            off = [offsets[k] for k in keys]
            worst = max(range(len(keys)), key=lambda i: off[i][0])
            scans = [merger.submaps[k].frame_scan for k in keys]
            spans = ", ".join(f"{a}-{b}" for a, b in runs_over(scans, [o[0] for o in off], WRONG_M)) or "-"
            print(
                f"| {n} | {chain} | {len(keys)} | {statistics.median(o[0] for o in off):.2f} m "
                f"| {off[worst][0]:.2f} m ({merger.submaps[keys[worst]].frame_scan}) "
                f"| {max(o[1] for o in off):.1f} deg | {spans} |"
            )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", help="a corrected log: corrected/NAME (" + ", ".join(CORRECTED) + ")")
    ap.add_argument("--split", type=int, default=1, help="cut into K robots (default 1)")
    ap.add_argument(
        "--scans", default="", help="also list every integration of the submaps placing these scans (e.g. 1084,1086)"
    )
    args, extra = ap.parse_known_args()
    name = args.log.removeprefix("corrected/")
    if name not in CORRECTED:
        raise SystemExit(f"unknown corrected log {args.log!r} (known: {', '.join(CORRECTED)})")
    path = data_folder() / "corrected" / f"{name}-corrected.log.gz"
    truth = [Transform2D(*s.odometry) for s in read_carmen(path) if s.odometry is not None]
    executor = make_executor("local")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            result = map_logs(
                read_inputs([str(path)], args.split), Path(tmp) / "out", map_config(extra), executor=executor
            )
    finally:
        executor.close()
    print(f"# {args.log} cut in {args.split}: {len(result.merger.submaps)} submaps")
    list_relations(result, corrected_relations(path), RawTruth(path))
    list_edges(result, truth)
    list_links(result, truth)
    list_frames(result, truth)
    if args.scans:
        list_edges_of(result, truth, [int(i) for i in args.scans.split(",")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
