"""``fleetmap merge``: one global map from many partial maps, in a known or an unknown order."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.sequence import pivot, sequential, tree
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.mapfile import read_map
from fleetmap.shared.io.outputs import output_file


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "merge",
        help="merge partial maps into one global map",
        description="Merge partial maps. --order unknown (default) resolves the order from the pose graph the merger "
        "solves (maximum spanning forest of valid integrations, each join borne out by the maps it joins, "
        "cycle-checked); sequential, tree and pivot are the "
        "paper's methods (IV) for maps given in sequence order. Poses are in the frame of the anchor map.",
    )
    p.add_argument("maps", nargs="+", metavar="MAP", help="map files (JSON)")
    p.add_argument(
        "--order",
        choices=("unknown", "sequential", "tree", "pivot"),
        default="unknown",
        help="unknown: the pose graph finds the merge order (default); or the paper's sequential, tree or pivot "
        "merging of the maps in the order given",
    )
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--out", metavar="GLOBAL.json", help="write the merged map (largest component) with poses")
    p.add_argument("--plot", metavar="GLOBAL.png", help="draw the merged map, each input map in its colour")
    add_config_arguments(p, ["integration", "merge"], "offline")
    p.set_defaults(func=run)


def _pose(t: Transform2D | None) -> dict[str, float] | None:
    return None if t is None else t.to_dict()


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    for path, flag in ((args.out, "--out"), (args.plot, "--plot")):
        if path:
            output_file(path, flag)
    names: list[str] = list(args.maps)
    if len(set(names)) != len(names):
        raise BadInput("command line", "the same map file is given twice")
    maps = [read_map(n) for n in names]
    notes: list[str] = []
    poses: dict[str, Transform2D | None]
    if args.order == "unknown":
        graph = PoseGraph(config.integration, config.merge, anchor="largest")
        for name, m in zip(names, maps, strict=True):
            graph.add_map(name, m)
        result = graph.solve()
        poses = {n: result.poses[n] for n in names}
        components = [list(c.members) for c in result.components]
        segments: Array = result.components[0].segments
        for e in result.rejected:
            notes.append(f"rejected edge {e.a} - {e.b} (value {e.value:.2f} m): disagrees with its cycle")
        if len(result.components[0].members) == 1:
            poses[result.components[0].anchor] = Transform2D.identity()
    else:
        method = {"sequential": sequential, "tree": tree, "pivot": pivot}[args.order]
        seq = method(maps, config.integration)
        poses = dict(zip(names, seq.poses, strict=True))
        placed = [n for n in names if poses[n] is not None]
        components = [placed] + [[n] for n in names if poses[n] is None]
        segments = seq.map.segments
    segments = np.asarray(segments).round(6)  # micrometres: the same numbers in every output
    if args.out:
        main = components[0]
        out = SegmentMap(segments, ordered=False, oriented=all(m.oriented for m in maps)).to_json_dict()
        out["poses"] = {n: _pose(poses[n]) if n in main else None for n in names}
        _write(args.out, json.dumps(out) + "\n")
    if args.plot:
        from fleetmap.merger.plot import plot_merged

        plot_merged(
            args.plot, {n: m.segments for n, m in zip(names, maps, strict=True)}, poses, fused=segments, notes=notes
        )
    if args.json:
        print(json.dumps(_contract(names, poses, components, segments)))
    else:
        for n in names:
            t = poses[n]
            print(f"{n}: " + ("not placed" if t is None else f"x={t.x:.3f} y={t.y:.3f} theta={t.theta:.4f}"))
        print(f"{len(components)} component(s); largest: {len(components[0])} map(s), {len(segments)} segments")
        for line in notes:
            print(line)
    return 0


def _contract(
    names: list[str], poses: dict[str, Transform2D | None], components: list[list[str]], segments: Array
) -> dict[str, Any]:
    return {
        "poses": {n: _pose(poses[n]) for n in names},
        "components": components,
        "segments": segments.tolist(),
    }


def _write(path: str, text: str) -> None:
    try:
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as exc:
        raise BadInput(path, f"cannot write: {exc.strerror}") from None
