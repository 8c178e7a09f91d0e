"""Known start poses (``--start-poses FILE``): where each robot starts, in one frame the fleet shares.

A CSV file of ``robot,x,y,theta`` lines (metres, radians; ``theta`` counter-clockwise), a header
line ``robot,x,y,theta`` allowed first, blank lines and ``#`` comments skipped. A robot's start pose
is its laser's pose when it starts: the frame of its first submap (its first placed scan), as
``poses.csv`` gives a laser's pose. Measured at the dock or given by a fleet manager, it lets the
merger place the robot from its first submap (Dugarjav & Lee 2015, Section III;
:mod:`fleetmap.merger.startposes`).
"""

from __future__ import annotations

import math
from pathlib import Path

from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import NAME_PATTERN

HEADER = ("robot", "x", "y", "theta")


def read_start_poses(path: str | Path) -> dict[str, Transform2D]:
    """Each robot's start pose, by robot id, from a ``robot,x,y,theta`` file; :class:`BadInput`
    naming the file and line of the first bad row (wrong number of fields, not a robot id, a
    number that is not finite, a robot given twice), or the file when it holds no start pose."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(str(path), f"cannot be read ({exc.__class__.__name__}: {exc})") from None
    poses: dict[str, Transform2D] = {}
    first = True
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{path}, line {n}"
        cells = [c.strip() for c in line.split(",")]
        if first and tuple(c.lower() for c in cells) == HEADER:
            first = False
            continue
        first = False
        if len(cells) != len(HEADER):
            raise BadInput(where, f"expected robot,x,y,theta (4 fields), got {len(cells)}: {line[:80]!r}")
        robot = cells[0]
        if NAME_PATTERN.fullmatch(robot) is None:
            raise BadInput(where, f"{robot[:64]!r} is not a robot id (^[a-z][a-z0-9_-]{{0,31}}$)")
        values = []
        for name, cell in zip(HEADER[1:], cells[1:], strict=True):
            try:
                value = float(cell)
            except ValueError:
                raise BadInput(where, f"{name} {cell[:32]!r} is not a number") from None
            if not math.isfinite(value):
                raise BadInput(where, f"{name} {cell[:32]!r} is not finite")
            values.append(value)
        if robot in poses:
            raise BadInput(where, f"robot {robot!r} is given a start pose twice")
        poses[robot] = Transform2D(*values)
    if not poses:
        raise BadInput(str(path), "holds no start pose (expected robot,x,y,theta lines)")
    return poses
