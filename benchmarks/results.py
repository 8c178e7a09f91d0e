"""Benchmark results as data, and ``benchmarks/RESULTS.md`` rendered from them (run on demand, not in CI).

Each benchmark's ``--write-results`` writes ``benchmarks/results/<section>.json``: the section's
name and title, the command, the date, the commit and whether the checkout had uncommitted changes
(the result files themselves aside), the SHA-256 of the canonical JSON of the config it ran with
(and the parameters it varied from it), the figures of its tables as rows of named values, and the
markdown body that shows them. The figures are read back from the body's own tables, so they are
the numbers the section shows, built in one place for every benchmark.

``python benchmarks/results.py render`` writes RESULTS.md from those files. It refuses (exit 2) a
checkout with uncommitted changes (the results and RESULTS.md aside) and any result that came from
one, so every figure in RESULTS.md comes from a commit. A result converted from an older RESULTS.md
has its config hash and varied parameters null: they were not recorded.

To regenerate, on a clean checkout of one commit (an idle machine for the timings): run each
benchmark with ``--write-results``, then ``render``, and commit ``benchmarks/results/`` with
RESULTS.md.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import hashlib
import json
import re
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from fleetmap.shared.config import FleetmapConfig

CHECKOUT = Path(__file__).resolve().parent.parent
FOLDER = "benchmarks/results"
"""Where the results live, relative to the checkout: one ``<section>.json`` each."""
RESULTS = "benchmarks/RESULTS.md"
OUTPUTS = (FOLDER, RESULTS)
"""What writing and rendering results change: not counted as uncommitted changes to the code."""
ORDER = (
    "relations",
    "tracking",
    "clock-spread",
    "tracking-pieces",
    "live-secure",
    "integration-size",
    "executor",
    "live",
    "recorder",
    "scan-pairs",
    "kidnap",
    "offline",
    "integration",
    "merge",
    "scenarios",
    "growth",
    "live-ros2",
    "aligners",
    "hostile-secure",
    "hostile",
    "start_poses",
    "fusion",
)
"""The sections' order in RESULTS.md, and the order ``regenerate.py`` runs them in (clock-spread draws
again the misses tracking lists); a section not named here follows them, by name."""
HEADER = """# Benchmark results

The current figures, written by the benchmark scripts themselves (`--write-results` writes
`benchmarks/results/<section>.json`; `python benchmarks/results.py render` renders this file from
them); each section names the command, the date and the commit that produced it. Real data:
Kümmerle et al., "On measuring the accuracy of SLAM algorithms", Autonomous Robots 27(4), 2009, and
the Robotics Data Set Repository (Radish, Howard & Roy 2003).
"""
FIELDS = {"section": str, "title": str, "command": str, "date": str, "commit": str, "dirty": bool, "body": str}
"""Every result's required fields and their types."""


class BadResult(Exception):
    """A result that cannot be rendered: unreadable, malformed, dirty, or from a dirty checkout."""


def checkout_state(root: Path = CHECKOUT) -> tuple[str, list[str]]:
    """The checkout's commit and its files with uncommitted changes (the result files aside).

    Outside a git checkout the commit is ``unknown`` and the checkout counts as changed: nothing
    says it is not.
    """
    exclude = [f":(exclude){p}" for p in OUTPUTS]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--", ".", *exclude], cwd=root, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown", ["(not a git checkout)"]
    return head, [line[3:] for line in status.splitlines() if line.strip()]


def config_hash(config: FleetmapConfig) -> str:
    """The SHA-256 of the config's canonical JSON (keys sorted, no spaces): equal configs, equal hashes."""
    text = json.dumps(config.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def write_result(
    name: str,
    title: str,
    body: str,
    *,
    config: FleetmapConfig | None,
    varied: Sequence[str] = (),
    root: Path = CHECKOUT,
    argv: Sequence[str] | None = None,
) -> Path:
    """Write section ``name``'s result into ``<root>/benchmarks/results/<name>.json``; return its path.

    ``config``: the config the benchmark ran with (None for one that runs none); ``varied``: the
    parameters it changed from that config between runs, as ``name=value,value``. ``argv``: the
    command line (default: this process's).
    """
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]).resolve()
    shown = script.relative_to(root).as_posix() if script.is_relative_to(root) else script.name
    head, changed = checkout_state(root)
    result = {
        "section": name,
        "title": title,
        "command": "python " + " ".join([shown, *argv[1:]]),
        "date": datetime.date.today().isoformat(),
        "commit": head,
        "dirty": bool(changed),
        "config_hash": None if config is None else config_hash(config),
        "config_varied": list(varied),
        "figures": figures(body),
        "body": body.strip(),
    }
    path = root / FOLDER / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_result(result), encoding="utf-8")
    return path


def dump_result(result: dict[str, Any]) -> str:
    """A result as JSON text, one field a line and one figure row a line (so a diff shows a row)."""

    def dumps(value: Any) -> str:
        return json.dumps(value, ensure_ascii=False)

    def table(t: dict[str, Any]) -> str:
        rows = "".join(f"\n   {dumps(r)}," for r in t["rows"]).rstrip(",")
        return f'  {{"columns": {dumps(t["columns"])}, "rows": [{rows}\n  ]}}'

    fields = []
    for key, value in result.items():
        text = dumps(value)
        if key == "figures" and value:
            text = "[\n" + ",\n".join(table(t) for t in value) + "\n ]"
        fields.append(f" {dumps(key)}: {text}")
    return "{\n" + ",\n".join(fields) + "\n}\n"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table: the header, its rule and one line per row (no newline at the end)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


NUMBER = re.compile(r"^([+-]?\d[\d,]*(?:\.\d+)?|[+-]?\.\d+)\s*(%|°|[A-Za-zµ]+(?:/[A-Za-z]+)?)?$")
"""A cell that is one number, with a unit or none: ``1279``, ``96.2 %``, ``0.097 m``, ``4.2x``."""


def _key(text: str) -> str:
    """A column header or unit as a key: ``time (share of log)`` -> ``time_share_of_log``."""
    text = text.replace("%", " pct ").replace("°", " deg ").replace("/", " per ")
    return re.sub(r"[^0-9a-z]+", "_", text.lower()).strip("_") or "column"


def _number(cell: str) -> tuple[float | int, str] | None:
    """A cell's number and its unit ('' for none), or None when the cell is not one number."""
    m = NUMBER.match(cell.strip())
    if m is None:
        return None
    digits = m.group(1).replace(",", "")
    value: float | int = float(digits) if "." in digits else int(digits)
    return value, m.group(2) or ""


PAREN = re.compile(r"^(.*\S)\s*\((.+)\)$")
"""``time (share of log)``, ``42 s (0.03)``: a name or value with a second one in brackets."""


def _readings(header: str, cell: str) -> list[tuple[list[str], list[str], bool]]:
    """The ways to read a cell as several named values, most literal first: as it is; numbers
    with distinct units (``0.036 m, 0.31 deg``); a value and another in brackets (``42 s (0.03)``
    under ``time (share of log)``); values split as the header splits (``2 / 6 ms`` under ``first /
    last``, ``11.5 / 46.9`` under ``ms per scan (median / p95)``, ``CPU s: agents / merger``, the
    last value's unit for all). Each: the names, the values, whether the last unit is for all."""
    out = [([header], [cell], False)]
    commas = cell.split(", ")
    if len(commas) > 1 and all(n is not None and n[1] for n in map(_number, commas)):  # each with its unit
        out.append(([header] * len(commas), commas, False))
    h, c = PAREN.match(header), PAREN.match(cell)
    if h and c:
        out.append(([h[1], h[2]], [c[1], c[2]], False))
    slashes = cell.split(" / ")
    if len(slashes) > 1:
        if h and len(h[2].split(" / ")) == len(slashes):
            out.append(([f"{h[1]} {part}" for part in h[2].split(" / ")], slashes, True))
        names = header.split(" / ")
        if len(names) == len(slashes):
            prefix = names[0].split(": ")[0] + " " if ": " in names[0] else ""
            out.append(([names[0], *(prefix + n for n in names[1:])], slashes, True))
    return out


def _cell(header: str, cell: str) -> dict[str, Any]:
    """One cell as named values: each number keyed by its column and its unit, by the first of
    the cell's readings that gives only numbers under distinct keys; ``-`` as None; else its text."""
    cell = cell.strip()
    if cell in ("-", ""):
        return {_key(header): None}
    for names, parts, share in _readings(header, cell):
        numbers = [n for n in (_number(p) for p in parts) if n is not None]
        if len(numbers) < len(parts):
            continue
        shared = numbers[-1][1] if share else ""
        out: dict[str, Any] = {}
        for name, (value, unit) in zip(names, numbers, strict=True):
            key, unit_key = _key(name), _key(unit or shared) if (unit or shared) else ""
            out[key if not unit_key or key.endswith("_" + unit_key) else f"{key}_{unit_key}"] = value
        if len(out) == len(parts):
            return out
    return {_key(header): cell}


def _row(header: list[str], cells: list[str]) -> dict[str, Any]:
    row: dict[str, Any] = {}
    for column, cell in zip(header, cells, strict=False):
        for key, value in _cell(column, cell).items():
            unique, n = key, 2
            while unique in row:  # a header repeated under another group (cross-robot: joined, ...)
                unique, n = f"{key}_{n}", n + 1
            row[unique] = value
    return row


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def figures(body: str) -> list[dict[str, Any]]:
    """The markdown tables of ``body`` as data: per table its column headers and one dict per row."""
    out: list[dict[str, Any]] = []
    lines = body.splitlines()
    i = 0
    while i + 1 < len(lines):
        if lines[i].startswith("|") and re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", lines[i + 1].strip()):
            header = _cells(lines[i])
            i += 2
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(_row(header, _cells(lines[i])))
                i += 1
            out.append({"columns": header, "rows": rows})
        else:
            i += 1
    return out


def load_results(folder: Path) -> list[dict[str, Any]]:
    """Every result in ``folder``, checked field by field, in RESULTS.md's order."""
    results = []
    for path in sorted(folder.glob("*.json")):
        try:
            result = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise BadResult(f"{path}: not a readable JSON result ({e})") from e
        if not isinstance(result, dict):
            raise BadResult(f"{path}: not a JSON object")
        for field, kind in FIELDS.items():
            if not isinstance(result.get(field), kind):
                raise BadResult(f"{path}: field {field!r} missing or not a {kind.__name__}")
        if result["section"] != path.stem:
            raise BadResult(f"{path}: section {result['section']!r} in a file named {path.name}")
        results.append(result)
    rank = {name: i for i, name in enumerate(ORDER)}
    return sorted(results, key=lambda r: (rank.get(r["section"], len(ORDER)), r["section"]))


def _short(commit: str) -> str:
    return commit[:7]


def render_markdown(results: list[dict[str, Any]]) -> str:
    """RESULTS.md's text: the header, the commits the sections come from, then every section."""
    commits = collections.Counter(_short(r["commit"]) for r in results)
    text = HEADER
    if commits:
        common, n = commits.most_common(1)[0]
        others = [f"`{r['section']}` ({_short(r['commit'])})" for r in results if _short(r["commit"]) != common]
        if others:
            text += (
                f"\nSections from commit {common}: {n} of {len(results)}; from other commits: {', '.join(others)}.\n"
            )
        else:
            text += f"\nEvery section from commit {common}.\n"
    for r in results:
        line = f"`{r['command']}` on {r['date']}, commit {_short(r['commit'])}{'+' if r['dirty'] else ''}"
        if r.get("config_hash"):
            line += f", config {r['config_hash'][:12]}"
            if r.get("config_varied"):
                line += " varying " + "; ".join(f"`{v}`" for v in r["config_varied"])
        if r.get("note"):
            line += f" ({r['note']})"
        text += f"\n<!-- section: {r['section']} -->\n## {r['title']}\n\n{line}.\n\n{r['body'].strip()}\n"
    return text


def render(root: Path = CHECKOUT) -> Path:
    """Write ``<root>/benchmarks/RESULTS.md`` from ``<root>/benchmarks/results/``; return its path.

    Refused (BadResult, naming the files) when the checkout has uncommitted changes or any result
    came from a checkout that had.
    """
    _, changed = checkout_state(root)
    if changed:
        raise BadResult(f"{root}: uncommitted changes in {', '.join(changed)}; commit them, then render")
    folder = root / FOLDER
    results = load_results(folder)
    if not results:
        raise BadResult(f"{folder}: no results (run a benchmark with --write-results)")
    dirty = [f"{FOLDER}/{r['section']}.json ({_short(r['commit'])}+)" for r in results if r["dirty"]]
    if dirty:
        raise BadResult(
            "results from a checkout with uncommitted changes: "
            + ", ".join(dirty)
            + "; run those benchmarks again on a clean checkout"
        )
    out = root / RESULTS
    out.write_text(render_markdown(results), encoding="utf-8")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = ap.add_subparsers(dest="command", required=True)
    render_command = commands.add_parser("render", help="write benchmarks/RESULTS.md from benchmarks/results/*.json")
    render_command.add_argument(
        "--checkout", type=Path, default=CHECKOUT, help="the checkout to render (default: the one holding this script)"
    )
    args = ap.parse_args(argv)
    try:
        out = render(args.checkout)
    except BadResult as e:
        print(f"results.py render: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
