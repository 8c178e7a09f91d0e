"""``benchmarks/RESULTS.md``: each benchmark writes its own section (run on demand, not in CI).

A section starts with ``<!-- section: NAME -->`` and runs to the next section or the end of the
file; writing one section keeps the others as they are. Every section says the command, the date
and the commit that produced it.
"""

from __future__ import annotations

import datetime
import re
import subprocess
import sys
from pathlib import Path

RESULTS = Path(__file__).with_name("RESULTS.md")
HEADER = """# Benchmark results

The current figures, written by the benchmark scripts themselves (`--write-results`); each
section names the command, the date and the commit that produced it. Real data: Kümmerle et al.,
"On measuring the accuracy of SLAM algorithms", Autonomous Robots 27(4), 2009, and the Robotics
Data Set Repository (Radish, Howard & Roy 2003).
"""


def commit() -> str:
    """The checkout's commit, with ``+`` when it has uncommitted changes."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+" if dirty.strip() else "")


def write_section(name: str, title: str, body: str) -> None:
    """Replace (or add) section ``name`` of RESULTS.md."""
    text = RESULTS.read_text(encoding="utf-8") if RESULTS.exists() else HEADER
    root = Path(__file__).resolve().parent.parent
    script = Path(sys.argv[0]).resolve()
    shown = script.relative_to(root).as_posix() if script.is_relative_to(root) else script.name
    command = "python " + " ".join([shown, *sys.argv[1:]])
    stamp = datetime.date.today().isoformat()
    block = f"<!-- section: {name} -->\n## {title}\n\n`{command}` on {stamp}, commit {commit()}.\n\n{body.strip()}\n\n"
    pattern = re.compile(rf"<!-- section: {re.escape(name)} -->\n.*?(?=<!-- section: |\Z)", re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + block
    RESULTS.write_text(text.rstrip("\n") + "\n", encoding="utf-8")


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table: the header, its rule and one line per row (no newline at the end)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])
