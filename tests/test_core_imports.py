"""The pure core (geometry, extraction, integration, fusion, tracking, the pose graph, the agent's
and the merger's logic) imports neither zenoh nor mcap: it runs in a notebook, a test or a Ray
worker with no network and no recording."""

from __future__ import annotations

import subprocess
import sys

CORE = [
    "fleetmap.shared.geometry",
    "fleetmap.shared.extraction",
    "fleetmap.shared.evaluation",
    "fleetmap.shared.integration",
    "fleetmap.shared.fusion",
    "fleetmap.shared.walls",
    "fleetmap.shared.tracking",
    "fleetmap.shared.mapgrid",
    "fleetmap.shared.messages",
    "fleetmap.agents.tracker",
    "fleetmap.agents.agent",
    "fleetmap.merger.graph",
    "fleetmap.merger.posegraph",
    "fleetmap.merger.executor",
    "fleetmap.merger.follow",
]


CHECK = """
import importlib, sys
for module in sys.argv[1:]:
    importlib.import_module(module)
    found = [n for n in ("zenoh", "mcap") if n in sys.modules]
    if found:
        sys.exit(f"{module} imports {found}")
"""


def test_the_core_imports_neither_zenoh_nor_mcap() -> None:
    argv = [sys.executable, "-c", CHECK, *CORE]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr.strip().splitlines()[-1:]
