"""The layout keeps the pure core apart from I/O.

``fleetmap.shared.core`` (geometry, extraction, integration and its validity, fusion, tracking)
imports nothing of ``fleetmap.shared.io``, zenoh or mcap: it runs in a notebook, a test or a Ray
worker with no files, no network and no recording. The agent's and the merger's logic (the
tracker, the local-map builder, the pose graph, the merger as a library, the integration jobs)
reads and writes bus messages but imports neither zenoh nor mcap.

The layers: ``shared`` imports nothing of fleetmap above it; ``agents`` and ``merger`` import
``shared`` and themselves, not each other, and ``agents`` not the simulator (``scenarios``: the
command line plugs it in as a scan source); ``scenarios`` imports ``shared`` and itself. Checked on
the source of every module, imports inside functions included."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import fleetmap.agents
import fleetmap.merger
import fleetmap.scenarios
import fleetmap.shared
import fleetmap.shared.core
import pytest

CORE = sorted(f"fleetmap.shared.core.{m.name}" for m in pkgutil.iter_modules(fleetmap.shared.core.__path__))

LOGIC = [
    "fleetmap.shared.io.messages",
    "fleetmap.agents.tracker",
    "fleetmap.agents.submap",
    "fleetmap.agents.prediction",
    "fleetmap.agents.fitcheck",
    "fleetmap.agents.clock_evidence",
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


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_the_core_imports_no_io_and_the_logic_neither_zenoh_nor_mcap() -> None:
    argv = [sys.executable, "-c", CHECK, ",".join(CORE), ",".join(LOGIC)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr.strip().splitlines()[-1:]


LAYERS = {
    "shared": ({"shared"}, fleetmap.shared),
    "agents": ({"shared", "agents"}, fleetmap.agents),
    "merger": ({"shared", "merger"}, fleetmap.merger),
    "scenarios": ({"shared", "scenarios"}, fleetmap.scenarios),
}
"""Each layer: the layers (``fleetmap.<name>``) it may import, and its package."""


def layer_breaches(layer: str, source: str) -> list[str]:
    """The fleetmap modules ``source`` (a module of ``layer``) imports that its layer may not."""
    allowed = LAYERS[layer][0]
    imported: list[str] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            imported += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module is not None:
            imported.append(node.module)
    return [m for m in imported if m.split(".")[0] == "fleetmap" and [*m.split("."), ""][1] not in allowed]


@pytest.mark.parametrize("layer", sorted(LAYERS))
def test_each_layer_imports_only_the_layers_below_it(layer: str) -> None:
    folder = Path(LAYERS[layer][1].__path__[0])
    breaches = {
        str(path.relative_to(folder.parent)): found
        for path in sorted(folder.rglob("*.py"))
        if (found := layer_breaches(layer, path.read_text(encoding="utf-8")))
    }
    assert not breaches


@pytest.mark.parametrize(
    ("layer", "line"),
    [
        ("merger", "from fleetmap.agents.localmap import PivotMapBuilder"),
        ("agents", "from fleetmap.scenarios.stream import robot_stream"),
        ("shared", "from fleetmap import __version__"),
        ("shared", "def f():\n    import fleetmap.mapping"),
    ],
)
def test_the_layer_check_finds_each_rule_broken(layer: str, line: str) -> None:
    assert layer_breaches(layer, line)
