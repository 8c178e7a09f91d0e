"""Diagnostic: how many cores a command keeps busy, tenth by tenth of its run (Linux, run on demand).

``fleetmap map`` spreads its work over the agents' processes, the executor's workers and the
merger's thread. When the run is not a tenth of the log's duration, the question is whether that
work is too much or whether it waits in line: a stretch at one core on a machine of two is work
that waits for one thread. This runs the command, reads the CPU time of each process in its tree
from ``/proc`` every half second, and prints the wall time, the CPU time by process and the cores
used in each tenth of the run. It writes no result: it measures no goal, it shows where one is lost.

    python benchmarks/cores.py -- fleetmap map ../shared/data/mit-csail/mit-csail.clf.gz \
        --split 8 --out /tmp/m8 --no-progress
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

PROC = Path("/proc")
TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
"""Clock ticks per second, the unit of ``/proc/<pid>/stat``'s CPU times."""


def _stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command's name (None if the process is gone)."""
    try:
        text = (PROC / str(pid) / "stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()


def _tree(root: int) -> list[int]:
    """``root`` and every process descended from it."""
    children: dict[int, list[int]] = {}
    for entry in PROC.iterdir():
        if entry.name.isdigit() and (fields := _stat(int(entry.name))) is not None:
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    out, stack = [], [root]
    while stack:
        pid = stack.pop()
        out.append(pid)
        stack += children.get(pid, [])
    return out


def _name(pid: int) -> str:
    try:
        return (PROC / str(pid) / "cmdline").read_text().replace("\0", " ").strip()[:70]
    except OSError:
        return "?"


def measure(
    command: list[str], every: float = 0.5
) -> tuple[float, dict[int, tuple[str, float]], list[tuple[float, float]]]:
    """Run ``command``: its wall time (s), each process's CPU time (s) by pid with its command line,
    and the samples ``(seconds since start, CPU seconds of the whole tree so far)``. A process's
    CPU time is its last reading before it ended (``every`` seconds at most before)."""
    started = time.perf_counter()
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen: dict[int, tuple[str, float]] = {}
    samples: list[tuple[float, float]] = []
    while child.poll() is None:
        for pid in _tree(child.pid):
            fields = _stat(pid)
            if fields is not None:
                cpu = (int(fields[11]) + int(fields[12])) / TICK
                name, before = seen.get(pid) or (_name(pid), 0.0)
                seen[pid] = (name, max(cpu, before))
        samples.append((time.perf_counter() - started, sum(c for _, c in seen.values())))
        time.sleep(every)
    if child.returncode != 0:
        raise SystemExit(f"the command exited with {child.returncode}: {' '.join(command)}")
    return time.perf_counter() - started, seen, samples


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", nargs=argparse.REMAINDER, help="the command to run, after --")
    args = ap.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("no command given (put it after --)")
    if not PROC.is_dir():
        raise SystemExit("no /proc here: this diagnostic reads Linux's process table")
    wall, seen, samples = measure(command)
    cpu = sum(c for _, c in seen.values())
    print(f"wall {wall:.1f} s, CPU {cpu:.1f} s over {len(seen)} processes ({cpu / wall:.2f} cores on average)")
    for _pid, (name, c) in sorted(seen.items(), key=lambda x: -x[1][1])[:8]:
        print(f"  {c:6.1f} s  {name}")
    n = len(samples)
    for k in range(10 if n > 10 else 0):
        (t0, c0), (t1, c1) = samples[k * n // 10], samples[min((k + 1) * n // 10, n - 1)]
        print(f"  {t0:6.1f}-{t1:6.1f} s: {(c1 - c0) / max(t1 - t0, 1e-9):.2f} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
