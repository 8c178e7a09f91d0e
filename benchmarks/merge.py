"""Benchmark: merging local maps whose order is unknown, on real data (run on demand, not in CI).

The paper's four-robot experiment (Fig. 16-17) at a larger scale. For each SLAM-corrected log of
``../shared/data/corrected`` (GMapping output; the corrected poses are the ground truth and are
never given to the algorithms, but for the reference ``--local-maps truth``):

1. cut the tour into K consecutive pieces overlapping by a few scans (K robots);
2. build each piece's local maps from its scans alone with the robot agent's own front end
   (:class:`fleetmap.agents.pivot.PivotFrontEnd`: the pivot method, no poses; the scans' times give
   the motion bound and prior, as a live agent's stamps do), one local map per epoch: a new one when
   ``--kidnap-after`` scans in a row cannot be placed, or one cannot be placed on a local map of
   one scan, started again from the unplaced scans (the agent's rules; see its module);
3. shuffle the local maps and merge them as ``fleetmap merge --order unknown`` does (the pose graph,
   no links);
4. compare each placed map's pose (its first scan's frame, in the anchor's frame) with the
   corrected poses, and where its content lies (the frame that puts its scans nearest them).

Prints per dataset and K: local maps placed within (0.2 m, 3 deg) in the largest component,
placed wrongly (> 1 m or > 10 deg) relative to their component's anchor, in any component,
unplaced (not wrong, and not in the largest component, or merged with nothing), the scans in maps
placed right, and the merge time.
A local map whose own scans were placed wrongly (one scan off by more than 1 m or 10 deg from
where the corrected poses put it relative to the map's first scan) is counted too: no merge can
place it right everywhere. Such a map's first scan may sit apart from the rest of it (orebro's
log has no times, and a map's second scan matched its first 2.5 m along a corridor): then every
map merged with it reads that far off against its first scan, though their walls agree. So the
wrong maps are counted a second way too, "by content": each map's frame taken where its scans'
corrected poses put its content (:func:`content_frame`), not its first scan's.

    python benchmarks/merge.py                         # every dataset, K = 4 and 8
    python benchmarks/merge.py --datasets aces,csail --k 8
    python benchmarks/merge.py --write-results         # and write its result (benchmarks/results/)
    python benchmarks/merge.py --stamps index          # a scan a second, for logs without usable times
    python benchmarks/merge.py --local-maps truth      # the merge alone: each piece's one map fused
                                                       # from its scans at their corrected poses
    python benchmarks/merge.py --datasets aces,csail --full-rate 2
                                                       # every 2nd scan of the full-rate log in between

``--full-rate N``: GMapping kept about a scan a metre in the corrected logs, so a piece's scans are a
metre and seconds apart, where a robot's laser gives several a second. Where the full-rate log of
the same tour is in ``../shared/data`` (aces; csail's is mit-csail), each corrected scan is found
in it (same ranges) and every Nth scan the log holds between two corrected ones joins the piece.
Only the corrected scans have a true pose: a map is then judged by the pose of its first
corrected scan (the corrected pose, moved by where the map placed that scan), its size by its
corrected scans, and the scan figures count the corrected scans.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fleetmap.agents.pivot import PivotFrontEnd
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.pivotmap import PivotMapBuilder
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.io.logs import read_carmen
from results import markdown_table, write_result

from fleetmap.config_args import add_config_arguments, config_from_args

DATASETS = {
    # name: subsampling step (freiburg-079 is logged every 0.1 m; the others about every metre)
    "aces": 1,
    "acapulco": 1,
    "belgioioso": 1,
    "csail": 1,
    "edmonton": 1,
    "freiburg-079": 5,
    "freiburg-101": 1,
    "freiburg-campus": 1,
    "infinite-corridor": 1,
    "orebro": 1,
}

FULL_RATE = {
    # name: the full-rate log of the same tour (``--full-rate``), under ../shared/data
    "aces": "aces/aces.clf.gz",
    "csail": "mit-csail/mit-csail.clf.gz",
}


def data_dir() -> Path:
    env = os.environ.get("FLEETMAP_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass
class Piece:
    scans: list[RangeScan]
    """The piece's scans that see something (a segment), in order; their times (s) give the agent's
    motion bound and prior, as a live agent's stamps do (``--stamps log``)."""
    truth: list[Transform2D | None]
    """The corrected pose of each scan (given to no algorithm; ``--local-maps truth`` builds the
    reference maps with it); None for a scan of the full-rate log between two corrected ones."""


def load_pieces(
    name: str, k: int, overlap: int, max_scans: int, config: FleetmapConfig, full_rate: int = 0
) -> list[Piece]:
    scans = list(read_carmen(data_dir() / "corrected" / f"{name}-corrected.log.gz"))[:: DATASETS[name]][:max_scans]
    raw = full_rate_positions(name, scans) if full_rate > 0 else None
    size = math.ceil(len(scans) / k)
    pieces = []
    for i in range(k):
        lo, hi = i * size, min(len(scans), (i + 1) * size + overlap)
        sequence: list[tuple[RangeScan, Transform2D | None]] = []
        for j in range(lo, hi):
            pose = scans[j].odom
            assert pose is not None  # corrected logs carry the SLAM pose on every laser line
            sequence.append((scans[j], Transform2D(*pose)))
            if raw is not None and j + 1 < hi:
                log, at = raw
                sequence.extend((log[n], None) for n in range(at[j] + full_rate, at[j + 1], full_rate))
        # Scans without a segment place nothing and count for no kidnap (the agent's rule too): left
        # out, so that the figures count the scans that see something.
        keep = [(s, t) for s, t in sequence if len(extract_segments(s, config.extraction)) > 0]
        if keep:
            pieces.append(Piece([s for s, _ in keep], [t for _, t in keep]))
    return pieces


def scan_maps(piece: Piece, config: FleetmapConfig) -> list[SegmentMap]:
    """The piece's scans as segment maps (``config.extraction``), as the agent extracts them."""
    return [SegmentMap(extract_segments(s, config.extraction), ordered=True, oriented=True) for s in piece.scans]


def full_rate_positions(name: str, scans: list[RangeScan]) -> tuple[list[RangeScan], list[int]]:
    """The full-rate log of ``name``'s tour, and where each corrected scan is in it (the first scan
    from there on with the same ranges; the logs' clocks differ)."""
    if name not in FULL_RATE:
        raise SystemExit(f"--full-rate: no full-rate log of {name} (there is one of {', '.join(FULL_RATE)})")
    log = list(read_carmen(data_dir() / FULL_RATE[name]))
    ranges = np.array([s.ranges for s in log])
    at: list[int] = []
    for j, s in enumerate(scans):
        start = at[-1] + 1 if at else 0
        same = np.flatnonzero(np.abs(ranges[start:] - np.asarray(s.ranges)).max(axis=1) < 1e-6)
        if len(same) == 0:
            raise SystemExit(f"--full-rate: corrected scan {j} of {name} is not in {FULL_RATE[name]}")
        at.append(start + int(same[0]))
    return log, at


@dataclass
class LocalMap:
    map: SegmentMap
    scans: list[int]
    """Indices (in its piece) of the scans placed in it; the first one's frame is the map's."""
    broken: bool
    """One of its scans is placed more than 1 m or 10 deg from where the corrected poses put it."""
    content: Transform2D | None
    """Where its content lies: the frame that puts its placed scans nearest their corrected poses
    (the median over its scans of corrected pose times placed pose inverse). Its first scan's
    corrected pose, unless that scan is placed apart from the rest (a broken map). None: it
    holds no corrected scan (``--full-rate``)."""
    frame: Transform2D | None
    """Where its frame is, by the corrected pose of its first corrected scan (moved by where it
    placed that scan): its first scan's corrected pose, unless ``--full-rate``."""
    corrected: int
    """How many of its scans have a corrected pose (``len(scans)`` unless ``--full-rate``)."""


def content_frame(placed: list[Transform2D], truth: list[Transform2D]) -> Transform2D | None:
    """The median over the scans of ``truth[k] * placed[k]^-1`` (x, y and heading separately; the
    headings as turns from the first scan's, so that none wraps); None without scans."""
    if not placed:
        return None
    frames = np.array([t.compose(p.inverse()).as_array() for p, t in zip(placed, truth, strict=True)])
    turn = float(np.median(np.remainder(frames[:, 2] - frames[0, 2] + math.pi, 2 * math.pi) - math.pi))
    x, y = (float(np.median(frames[:, k])) for k in (0, 1))
    return Transform2D(x, y, math.remainder(frames[0, 2] + turn, 2 * math.pi))


def build_local_maps(job: tuple[Piece, FleetmapConfig, int, str, str]) -> tuple[list[LocalMap], float]:
    """A piece's local maps, built by the agent's front end (see the module docstring), or with
    ``local_maps="truth"`` its one map fused from its scans at their corrected poses."""
    piece, config, kidnap_after, stamps, local_maps = job
    clock = {
        "log": lambda j: piece.scans[j].stamp,
        "index": lambda j: float(j),
    }[stamps]
    start = time.perf_counter()
    if local_maps == "truth":
        builder = PivotMapBuilder(config.integration)
        truth = [t for t in piece.truth if t is not None]
        if len(truth) < len(piece.scans):
            raise ValueError("--local-maps truth needs every scan's corrected pose (not with --full-rate)")
        for j, scan in enumerate(scan_maps(piece, config)):
            builder.add_at(scan, truth[0].inverse().compose(truth[j]), clock(j))
        every = list(range(len(piece.scans)))
        return [LocalMap(builder.map, every, False, truth[0], truth[0], len(every))], time.perf_counter() - start
    # The robot's agent, scan by scan (a local map message only at an epoch's first scan and end:
    # the benchmark reads the epochs' maps from the front end, not from its messages).
    agent = PivotFrontEnd("robot", config, publish_every=len(piece.scans) + 1, kidnap_after=kidnap_after, lost_scans=0)
    for j, scan in enumerate(piece.scans):
        agent.add_scan(j, clock(j), scan)
    out: list[LocalMap] = []
    for epoch in agent.epochs:
        frame: Transform2D | None = None
        broken = False
        for j, pose in epoch.scans:
            truth = piece.truth[j]
            if truth is None:
                continue
            if frame is None:
                frame = truth.compose(pose.inverse())
            dt, dr = pose.distance(frame.inverse().compose(truth))
            broken |= dt > 1.0 or math.degrees(dr) > 10
        known = [(p, t) for j, p in epoch.scans if (t := piece.truth[j]) is not None]
        content = content_frame([p for p, _ in known], [t for _, t in known])
        out.append(LocalMap(epoch.map, [j for j, _ in epoch.scans], broken, content, frame, len(known)))
    return out, time.perf_counter() - start


def run(name: str, k: int, args: argparse.Namespace, config: FleetmapConfig, pool: multiprocessing.pool.Pool) -> dict:
    pieces = load_pieces(name, k, args.overlap, args.max_scans, config, args.full_rate)
    stamps = args.stamps
    times = [s.stamp for p in pieces for s in p.scans]
    if stamps == "log" and any(t < 0 for t in times):
        # infinite-corridor's times run negative (the data README: "timestamps corrupt"); the
        # scans' indices stand in for them here
        print(f"{name}: the log's times are corrupt (negative); a scan a second instead (--stamps index)")
        stamps = "index"
    built = pool.map(build_local_maps, [(p, config, args.kidnap_after, stamps, args.local_maps) for p in pieces])
    local = [
        (f"{name}/{i}.{e}", i, lm)
        for i, (maps, _) in enumerate(built)
        for e, lm in enumerate(maps)
        if lm.corrected >= args.min_scans
    ]
    dropped = [lm for maps, _ in built for lm in maps if lm.corrected < args.min_scans]
    # A map of at least one corrected scan has a frame and a content frame.
    truth = {key: lm.frame for key, _, lm in local if lm.frame is not None}
    content = {key: lm.content for key, _, lm in local if lm.content is not None}
    order = list(range(len(local)))
    random.Random(args.shuffle_seed).shuffle(order)
    graph = PoseGraph(config.integration, config.merge, anchor="largest")
    start = time.perf_counter()
    for n in order:
        graph.add_map(local[n][0], local[n][2].map)
    result = graph.solve()
    seconds = time.perf_counter() - start
    good = wrong = unplaced = scans_good = wrong_content = good_content = 0
    # Why the maps not within are not: merged with nothing, right in a smaller component (and of
    # those, how many lie within their anchor's frame), or in the largest but 0.2-1 m (or 3-10
    # degrees) off.
    alone = side = side_within = off = 0
    details = []
    largest = result.components[0]
    for key, _, lm in local:
        tag = "!" if lm.broken else ""
        comp = result.component_of(key)
        if comp is None or len(comp.members) < 2:
            unplaced += 1
            alone += 1
            details.append(f"{key}{tag}:-")
            continue
        # Placed in its component's anchor frame: a map merged wrongly into a smaller component
        # is as wrong as one in the largest, though only the largest's maps count as placed.
        dt, dr = truth[comp.anchor].compose(comp.poses[key]).distance(truth[key])
        ct, cr = content[comp.anchor].compose(comp.poses[key]).distance(content[key])
        wrong_content += ct > 1.0 or math.degrees(cr) > 10
        good_content += comp is largest and ct <= 0.2 and math.degrees(cr) <= 3
        mark = "" if comp is largest else f"({comp.anchor})"
        if dt > 1.0 or math.degrees(dr) > 10:
            wrong += 1
        elif comp is not largest:
            unplaced += 1
            side += 1
            side_within += dt <= 0.2 and math.degrees(dr) <= 3
        elif dt <= 0.2 and math.degrees(dr) <= 3:
            good += 1
            scans_good += lm.corrected
        else:
            off += 1
        by_content = "" if abs(ct - dt) < 0.5 else f"(content {ct:.2f}m/{math.degrees(cr):.1f}d)"
        details.append(f"{key}{tag}{mark}:{dt:.2f}m/{math.degrees(dr):.1f}d{by_content}")
    if args.edges_json:
        for e in graph.edges:
            t = truth[e.a].inverse().compose(truth[e.b])
            dt, dr = e.transform.distance(t)
            args.edges_rows.append(
                {
                    "dataset": name,
                    "k": k,
                    "a": e.a,
                    "b": e.b,
                    "value": e.value,
                    "valid": e.valid,
                    "runner_up": e.runner_up,
                    "violation": e.violation,
                    "limited_violation": e.limited_violation,
                    "seconds": e.seconds,
                    "error_m": dt,
                    "error_deg": math.degrees(dr),
                    "size_a": graph.map_of(e.a).total_length,
                    "size_b": graph.map_of(e.b).total_length,
                }
            )
    maps = [lm for _, _, lm in local]
    segs = [len(lm.map) for lm in maps]
    return {
        "dataset": name,
        "k": len(pieces),
        "maps": len(local),
        "good": good,
        "wrong": wrong,
        "wrong_content": wrong_content,
        "good_content": good_content,
        "unplaced": unplaced,
        "alone": alone,
        "side": side,
        "side_within": side_within,
        "off": off,
        "broken": sum(lm.broken for lm in maps),
        "dropped": len(dropped),
        "dropped_scans": sum(lm.corrected for lm in dropped),
        "merge_s": seconds,
        "build_s": sum(b[1] for b in built),
        "segments": f"{min(segs)}-{max(segs)}",
        "scans_placed": sum(lm.corrected for lm in maps) + sum(lm.corrected for lm in dropped),
        "scans_good": scans_good,
        "scans": sum(t is not None for p in pieces for t in p.truth),
        "rejected": len(result.rejected),
        "details": " ".join(details),
    }


HEADER = [
    "dataset",
    "K",
    "local maps",
    "within (0.2 m, 3°)",
    "wrong (> 1 m or > 10°)",
    "unplaced",
    "scans in maps within",
    "merge time",
    "segments per map",
]
EXPLAINED = (
    "Each SLAM-corrected log (its corrected poses are the truth, given to no algorithm) cut into K "
    "consecutive pieces, one robot each; each piece's local maps built from its scans alone by the pivot "
    "agent's front end, shuffled and merged as `fleetmap merge` does (the pose graph without links, order "
    "unknown). Local maps: those merged (at least `--min-scans` scans); within: in the largest component, "
    "within (0.2 m, 3°) of where the corrected poses put it, relative to its anchor, judged by its first "
    "scan's frame and, in brackets, by where its content lies (a bent anchor moves every map measured "
    "from its first scan); wrong: more than 1 m or 10° off relative to its "
    "component's anchor, in any component, judged by its first scan's frame and, in brackets, by where its "
    "content lies (a local map bent by its front end reads off at its first scan though its walls lie "
    "right); unplaced: merged with nothing, or not wrong but in a smaller component (a map in the largest "
    "but 0.2-1 m or 3-10° off is in none of the three: see the totals below); scans in maps within: the "
    "share of the pieces' scans in maps placed within; merge time: adding the maps to the graph and solving "
    "it (building the local maps not counted); segments per map: the smallest and largest map's."
)


def table(rows: list[dict]) -> str:
    """The printed table of ``run``'s rows, one per dataset and K."""
    cells = [
        [
            r["dataset"],
            str(r["k"]),
            str(r["maps"]),
            f"{r['good']} ({r['good_content']})",
            f"{r['wrong']} ({r['wrong_content']})",
            str(r["unplaced"]),
            f"{100 * r['scans_good'] / max(r['scans'], 1):.0f} %",
            f"{r['merge_s']:.1f} s",
            r["segments"],
        ]
        for r in rows
    ]
    return markdown_table(HEADER, cells)


def totals(rows: list[dict]) -> list[str]:
    """Why the maps not within are not, and the overall figures: two lines."""
    total = sum(r["maps"] for r in rows)
    good = sum(r["good"] for r in rows)
    wrong = sum(r["wrong"] for r in rows)
    wrong_content = sum(r["wrong_content"] for r in rows)
    good_content = sum(r["good_content"] for r in rows)
    scans = sum(r["scans"] for r in rows)
    scans_good = sum(r["scans_good"] for r in rows)
    alone, side, side_within, off = (sum(r[k] for r in rows) for k in ("alone", "side", "side_within", "off"))
    return [
        f"not within: {alone} merged with nothing, {side} in a smaller component (not wrong; {side_within} of "
        f"them within its anchor's frame), {off} in the largest but 0.2-1 m or 3-10 deg off",
        f"overall: {good}/{total} local maps within (0.2 m, 3 deg) ({100 * good / max(total, 1):.1f} %; "
        f"{good_content} by where their content lies), "
        f"{wrong} wrong ({wrong_content} by where their content lies); "
        f"{100 * scans_good / max(scans, 1):.1f} % of the scans in maps placed within",
    ]


def report(rows: list[dict], write: bool, config: FleetmapConfig) -> None:
    """Print the table and the totals; with ``write``, into section ``merge``'s result (run with ``config``) too."""
    print()
    print(table(rows))
    print("\n" + "\n".join(totals(rows)))
    if write:
        body = "\n\n".join([EXPLAINED, table(rows), *totals(rows)])
        write_result("merge", "Merging local maps of the corrected logs (`benchmarks/merge.py`)", body, config=config)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default=",".join(DATASETS))
    ap.add_argument("--k", default="4,8", help="numbers of pieces")
    ap.add_argument("--overlap", type=int, default=3, help="scans shared by consecutive pieces")
    ap.add_argument("--max-scans", type=int, default=400, help="scans used per dataset (after subsampling)")
    ap.add_argument("--shuffle-seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2, help="processes building local maps")
    ap.add_argument("--kidnap-after", type=int, default=2, help="unplaced scans in a row that start a new local map")
    ap.add_argument(
        "--stamps",
        choices=["log", "index"],
        default="log",
        help="the scans' times for the motion bound and prior: the log's, or the scan's index in seconds "
        "(the corrected logs hold a scan about every metre)",
    )
    ap.add_argument(
        "--local-maps",
        choices=["built", "truth"],
        default="built",
        help="each piece's local maps built from its scans alone (the benchmark), or its one map fused from "
        "its scans at their corrected poses (a reference: how the merge does on right local maps)",
    )
    ap.add_argument("--min-scans", type=int, default=5, help="local maps of fewer scans are not merged")
    ap.add_argument(
        "--full-rate",
        type=int,
        default=0,
        metavar="N",
        help=f"also every Nth scan of the full-rate log between two corrected ones ({', '.join(FULL_RATE)}; see above)",
    )
    ap.add_argument("--edges-json", metavar="FILE", help="write every integrated pair, with its error, here")
    ap.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    add_config_arguments(ap, ["extraction", "integration", "merge"])
    args = ap.parse_args()
    if args.full_rate < 0:
        ap.error(f"--full-rate must be 0 (off) or a positive step, got {args.full_rate}")
    if args.full_rate and args.local_maps == "truth":
        ap.error("--full-rate's scans between the corrected ones have no true pose: not with --local-maps truth")
    config = config_from_args(args)
    args.edges_rows = []
    rows = []
    with multiprocessing.Pool(args.workers) as pool:
        for name in args.datasets.split(","):
            for k in (int(x) for x in args.k.split(",")):
                r = run(name, k, args, config, pool)
                rows.append(r)
                print(
                    f"{name:18s} K={r['k']} maps {r['maps']} good {r['good']} wrong {r['wrong']} "
                    f"(by content {r['wrong_content']}) unplaced "
                    f"{r['unplaced']} broken {r['broken']} (dropped {r['dropped']} maps, {r['dropped_scans']} scans) "
                    f"merge {r['merge_s']:.1f} s (segments {r['segments']}, "
                    f"scans placed {r['scans_placed']}/{r['scans']}, in good maps {r['scans_good']}, built in "
                    f"{r['build_s']:.0f} s) rejected edges {r['rejected']} | {r['details']}",
                    flush=True,
                )
    if args.edges_json:
        Path(args.edges_json).write_text(json.dumps(args.edges_rows))
    report(rows, args.write_results, config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
