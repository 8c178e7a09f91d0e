"""``fleetmap integrate``: the transformation of map B on map A, from geometry alone (paper III)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.shared.core.fusion import fuse
from fleetmap.shared.core.integration import Integration, integrate
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.mapfile import map_from_dict, parse_json, read_map, read_text, write_map


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "integrate",
        help="integrate two segment maps without pose information",
        description="Find the transformation {x, y, theta} that maps B's coordinates into A's frame "
        "(Amigoni et al. 2006, Algorithms 1-5), its transformation value (matched length, m) and "
        "whether the integration is valid.",
    )
    p.add_argument("maps", nargs="*", metavar="MAP", help="two map files: A.json B.json")
    p.add_argument("--batch", metavar="PAIRS.jsonl", help='lines {"id": str, "a": MAP, "b": MAP}')
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--fused", metavar="OUT.json", help="also write the fused map S_{A,B} (A's frame)")
    add_config_arguments(p, ["integration"])
    p.set_defaults(func=run)


def _result(r: Integration) -> dict[str, Any]:
    return r.to_json_dict()


def _human(r: Integration, a: str, b: str) -> str:
    t = r.transform
    verdict = "valid" if r.valid else "NOT valid"
    return (
        f"{b} in {a}'s frame: x={t.x:.4f} m  y={t.y:.4f} m  theta={t.theta:.5f} rad ({math.degrees(t.theta):.2f} deg)\n"
        f"value {r.value:.3f} m ({verdict}), {r.candidates} transformations tried, best from "
        f"'{r.heuristic}', {1000 * r.seconds:.1f} ms"
    )


def _batch_pairs(path: str) -> list[tuple[str, SegmentMap, SegmentMap]]:
    """Every line validated before any work: a bad line is reported with its number and id."""
    pairs = []
    for lineno, line in enumerate(read_text(path).splitlines(), 1):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        data = parse_json(line, where)
        if not isinstance(data, dict):
            raise BadInput(where, f"each line must be an object with id, a and b, got {type(data).__name__}")
        ident = data.get("id")
        if not isinstance(ident, str):
            raise BadInput(where, f"'id' must be a string, got {ident!r}")
        for key in ("a", "b"):
            if key not in data:
                raise BadInput(f"{where} (id {ident})", f"missing key '{key}'")
        a = map_from_dict(data["a"], f"{where} (id {ident}) map a")
        b = map_from_dict(data["b"], f"{where} (id {ident}) map b")
        pairs.append((ident, a, b))
    return pairs


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    params = config.integration
    if args.batch:
        if args.maps:
            raise BadInput("command line", "give either two maps or --batch, not both")
        for ident, a, b in _batch_pairs(args.batch):
            r = integrate(a, b, params)
            if args.json:
                print(json.dumps({"id": ident, **_result(r)}), flush=True)
            else:
                print(f"[{ident}] " + _human(r, "a", "b"), flush=True)
        return 0
    if len(args.maps) != 2:
        raise BadInput("command line", f"expected two map files A.json B.json, got {len(args.maps)}")
    path_a, path_b = args.maps
    a, b = read_map(path_a), read_map(path_b)
    r = integrate(a, b, params)
    if args.fused:
        try:
            write_map(args.fused, fuse(a, b, r.transform, params))
        except OSError as exc:
            raise BadInput(args.fused, f"cannot write: {exc.strerror}") from None
    if args.json:
        print(json.dumps(_result(r)))
    else:
        print(_human(r, Path(path_a).name, Path(path_b).name))
    sys.stdout.flush()
    return 0
