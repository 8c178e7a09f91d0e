"""The layout keeps the pure core apart from I/O.

``fleetmap.shared.core`` (geometry, extraction, integration and its validity, fusion, tracking)
imports nothing of ``fleetmap.shared.io``, zenoh or mcap: it runs in a notebook, a test or a Ray
worker with no files, no network and no recording. The agent's and the merger's logic (the
tracker, the local-map builder, the pose graph, the merger as a library, the integration jobs)
reads and writes bus messages but imports neither zenoh nor mcap."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import fleetmap.shared.core

CORE = sorted(f"fleetmap.shared.core.{m.name}" for m in pkgutil.iter_modules(fleetmap.shared.core.__path__))

LOGIC = [
    "fleetmap.shared.io.messages",
    "fleetmap.agents.tracker",
    "fleetmap.agents.localmap",
    "fleetmap.agents.agent",
    "fleetmap.agents.pivot",
    "fleetmap.merger.graph",
    "fleetmap.merger.posegraph",
    "fleetmap.merger.executor",
    "fleetmap.merger.follow",
    "fleetmap.merger.engine",
    "fleetmap.merger.schedule",
    "fleetmap.merger.outputs",
    "fleetmap.merger.state",
    "fleetmap.merger.stats",
    "fleetmap.merger.sequence",
]

CHECK = """
import importlib, sys
def check(forbidden, modules):
    for module in modules:
        importlib.import_module(module)
        found = sorted(n for n in sys.modules if any(n == f or n.startswith(f + ".") for f in forbidden))
        if found:
            sys.exit(f"{module} imports {found}")
core, logic = sys.argv[1].split(","), sys.argv[2].split(",")
check(["zenoh", "mcap", "fleetmap.shared.io"], core)  # first: the logic imports fleetmap.shared.io
check(["zenoh", "mcap"], logic)
"""


def test_the_core_is_every_algorithm_module() -> None:
    expected = {"geometry", "integration", "validity", "transformation_value", "tracking"}
    assert {f"fleetmap.shared.core.{m}" for m in expected} <= set(CORE)


def test_the_core_imports_no_io_and_the_logic_neither_zenoh_nor_mcap() -> None:
    argv = [sys.executable, "-c", CHECK, ",".join(CORE), ",".join(LOGIC)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr.strip().splitlines()[-1:]
