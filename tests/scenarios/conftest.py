"""Fixtures of the scenario tests: a small valid scenario file to break field by field."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

SMALL = """\
name = "small"
world = "department"
seed = 3

[laser]
noise = 0.01

[[robots]]
id = "r1"
path = [[2.5, 2.2], [2.5, 3.9], [3.5, 5.6], [5.5, 6.0], [12.0, 6.0]]
spacing = 1.0
period = 0.5

[[robots]]
id = "r2"
path = [[14.0, 1.2], [8.0, 1.2], [5.0, 1.3]]
spacing = 0.8
period = 1.0
start = 1.0

[[events]]
t = 4.0
type = "kidnap"
robot = "r1"
pose = [20.0, 1.2, 3.14]
path = [[16.0, 1.2], [12.0, 1.2]]

[[events]]
t = 5.0
type = "leave"
robot = "r2"
"""
"""Two robots in the department world: r1 is kidnapped at t = 4, r2 starts at 1 and leaves at 5."""


@pytest.fixture
def scenario_file(tmp_path: Path) -> Callable[..., Path]:
    """Writes SMALL, with ``old -> new`` replacements applied, to a file; returns its path."""

    def write(*edits: tuple[str, str]) -> Path:
        text = SMALL
        for old, new in edits:
            assert old in text, old
            text = text.replace(old, new, 1)
        path = tmp_path / "small.toml"
        path.write_text(text)
        return path

    return write
