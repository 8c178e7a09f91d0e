"""The merged map's picture: one legend row per robot whatever its number of submaps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fleetmap.merger.plot import plot_merged
from fleetmap.shared.core.geometry import Transform2D


def test_a_fleet_of_many_submaps_gets_one_legend_row_per_robot(tmp_path: Path) -> None:
    square = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 1.0, 1.0]])
    maps = {f"r{r}/0/{k}": square for r in range(1, 4) for k in range(20)}
    poses = {name: Transform2D(float(k), float(r), 0.0) for name in maps for r, k in [(int(name[1]), int(name[-1]))]}
    poses["r3/0/19"] = None
    groups = {name: name.split("/")[0] for name in maps}
    paths = {"r1": np.array([[0.0, 1.0], [5.0, 1.0]]), "r2": np.array([[0.0, 2.0], [np.nan, np.nan], [3.0, 2.0]])}
    out = tmp_path / "map.png"
    rows = plot_merged(out, maps, poses, fused=square, groups=groups, paths=paths, notes=["1 other component"])
    assert rows == [
        "global map (fused walls)",
        "r1: 20 maps placed, path from the dot",
        "r2: 20 maps placed, path from the dot",
        "r3: 19 maps placed",
    ]
    assert out.stat().st_size > 10_000
