"""``fleetmap extract``: segments from range scans (paper III-D), one JSON line per scan."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path

from fleetmap.commands import add_no_return_reading
from fleetmap.config_args import add_config_arguments, config_from_args
from fleetmap.shared.core.extraction import extract_segments
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.logs import read_carmen, read_ranges_jsonl


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "extract",
        help="extract segments from range scans",
        description="Segments from range scans (paper III-D): one output line per input scan, in order: "
        '{"stamp", "segments": [[x1, y1, x2, y2], ...], "ordered": true}.',
    )
    p.add_argument("input", help="a CARMEN log (plain or .gz) or a ranges JSONL file")
    p.add_argument(
        "--format",
        choices=("carmen", "ranges-jsonl"),
        required=True,
        help="what the input is: a CARMEN log, or ranges JSONL (one range scan per line)",
    )
    p.add_argument("--out", required=True, help="output JSONL file ('-' for stdout)")
    add_no_return_reading(p)
    add_config_arguments(p, ["extraction"])
    p.set_defaults(func=run)


def scans_of(path: str, fmt: str, range_max: float) -> Iterator[RangeScan]:
    if fmt == "carmen":
        return read_carmen(path, range_max=range_max)
    return read_ranges_jsonl(path)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    if not Path(args.input).exists():
        raise BadInput(args.input, "no such file")
    out = sys.stdout if args.out == "-" else None
    lines = []
    for scan in scans_of(args.input, args.format, args.no_return_reading):
        seg = extract_segments(scan, config.extraction)
        lines.append(json.dumps({"stamp": scan.stamp, "segments": seg.round(6).tolist(), "ordered": True}))
    text = "\n".join(lines) + ("\n" if lines else "")
    if out is not None:
        out.write(text)
    else:
        try:
            Path(args.out).write_text(text, encoding="utf-8")
        except OSError as exc:
            raise BadInput(args.out, f"cannot write: {exc.strerror}") from None
    return 0
