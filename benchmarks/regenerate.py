"""Regenerate every section of ``benchmarks/RESULTS.md`` at one commit, in one command.

Each result in ``benchmarks/results/`` names the command that produced it; this runs those
commands again, one after another, on this checkout (which must have no uncommitted changes: the
results would not say which code made them), then renders RESULTS.md (``results.py render``).
Run it on an idle machine: several sections are timings. The longest sections (relations,
tracking) take tens of minutes each; ``--dry-run`` lists the commands, ``--only`` and ``--skip``
choose sections by name. A command that fails is reported and the others still run; nothing is
rendered then.

    python benchmarks/regenerate.py --dry-run
    python benchmarks/regenerate.py --skip live-ros2
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from results import CHECKOUT, FOLDER, BadResult, checkout_state, load_results, render


def commands(root: Path, only: set[str], skip: set[str]) -> list[tuple[str, list[str]]]:
    """Each chosen section's command as an argument list run by this interpreter, with
    ``--write-results``."""
    out = []
    for r in load_results(root / FOLDER):
        name = r["section"]
        if (only and name not in only) or name in skip:
            continue
        argv = shlex.split(r["command"])
        if not argv or not argv[0].startswith("python") or len(argv) < 2:
            raise BadResult(f"{FOLDER}/{name}.json: command {r['command']!r} is not 'python benchmarks/...'")
        if "--write-results" not in argv:
            argv.append("--write-results")
        out.append((name, [sys.executable, *argv[1:]]))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default="", help="comma-separated sections to run (default: every one)")
    ap.add_argument("--skip", default="", help="comma-separated sections not to run")
    ap.add_argument("--dry-run", action="store_true", help="list the commands and run none")
    args = ap.parse_args(argv)
    only = {s for s in args.only.split(",") if s}
    skip = {s for s in args.skip.split(",") if s}
    try:
        head, changed = checkout_state(CHECKOUT)
        if changed and not args.dry_run:
            raise BadResult(f"{CHECKOUT}: uncommitted changes in {', '.join(changed)}; commit them first")
        todo = commands(CHECKOUT, only, skip)
    except BadResult as e:
        print(f"regenerate.py: {e}", file=sys.stderr)
        return 2
    unknown = (only | skip) - {r["section"] for r in load_results(CHECKOUT / FOLDER)}
    if unknown:
        print(f"regenerate.py: no such section: {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    failed = []
    for name, cmd in todo:
        print(f"[{name}] {shlex.join(cmd)}", flush=True)
        if args.dry_run:
            continue
        start = time.monotonic()
        done = subprocess.run(cmd, cwd=CHECKOUT, check=False)
        print(f"[{name}] exit {done.returncode} after {time.monotonic() - start:.0f} s", flush=True)
        if done.returncode != 0:
            failed.append(name)
    if args.dry_run:
        return 0
    if failed:
        print(f"regenerate.py: failed: {', '.join(failed)}; RESULTS.md not rendered", file=sys.stderr)
        return 1
    try:
        out = render(CHECKOUT)
    except BadResult as e:
        print(f"regenerate.py: {e}", file=sys.stderr)
        return 2
    stale = [r["section"] for r in load_results(CHECKOUT / FOLDER) if r["commit"] != head]
    print(f"wrote {out} at {head[:7]}" + (f"; not rerun: {', '.join(stale)}" if stale else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
