"""The core's compiled loops built once, by the process that starts the others.

Each compiled loop (:mod:`fleetmap.shared.core.compiled`) is compiled on its first call and cached
beside its module; a later process loads it in milliseconds. On a fresh install there is no cache:
without this, every process of a live fleet compiles the same loops at its first scans, 1-2 s of
CPU each, all at once (16 agents and the merger on two cores: 3.6 s merge latency and 12.5 s of
catch-up, against 0.99 s and 0.6 s with the cache; decision record 073). :func:`warm` calls each
loop's public function once on a tiny input, with the argument types every caller passes (each
function converts its arrays to them), so the cache is written once, before the others start.
"""

from __future__ import annotations

import numpy as np
from fleetmap.shared.core.beamkernel import beam_codes
from fleetmap.shared.core.beammarch import beam_passes
from fleetmap.shared.core.freecells import mark_free
from fleetmap.shared.core.gridlookup import code_sums
from fleetmap.shared.core.nearest import CellIndex
from fleetmap.shared.core.pairkernel import near_matching_values
from fleetmap.shared.core.refinekernel import normal_equations
from fleetmap.shared.core.walllookup import wall_sums


def warm() -> None:
    """Compile every compiled loop, or load it from its cache (a few milliseconds each)."""
    walls = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    pair = np.array([0, 1])
    normal_equations(walls, walls, pair, pair, np.zeros(3), 0.9, 0.1)
    mid, half = np.array([[0.5, 0.0], [0.0, 0.5]]), np.array([0.5, 0.5])
    near_matching_values(walls, walls, mid, half, mid, half, pair, pair, 0.5, 0.1, 0.5, 2.0)
    beam_passes(np.zeros((1, 2)), np.ones((1, 2)), np.array([2]), np.ones(1), (4, 4))
    ranges = np.full(8, 2.0)
    scan = (ranges, 0.0, 0.0, 0.0, -np.pi, np.pi / 4, 5.0, 5.0, np.inf)
    beam_codes(mid, np.array([[0.0, 1.0], [1.0, 0.0]]), half, 2.0, [scan], (0.1, 0.02))
    CellIndex(mid, np.ones(2, dtype=bool), 0.5).query(mid, 1.0)
    code = np.zeros((8, 4, 4), dtype=np.int8)
    code_sums(code, mid, np.zeros(2), np.zeros((1, 3)), 0.01, (0.0, 0.0, 0.5, np.pi, 8))
    grid = np.zeros((4, 4), dtype=bool)
    wall_sums(code != 0, grid, mid, np.zeros(2), half, half, np.zeros((1, 3)), (0.0, 0.0, 0.5, np.pi, 8, True))
    mark_free(np.zeros(1), np.zeros(1), np.ones((1, 2)), np.ones((1, 2), dtype=np.int64), np.zeros((1, 2)), 0.5,
              np.zeros(2), 0.5, grid)  # fmt: skip
