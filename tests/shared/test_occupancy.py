"""The occupancy grid: occupied where beams end, free where they pass, and map_server's files."""

from __future__ import annotations

import csv
import gzip
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.occupancy import FREE, OCCUPIED, UNKNOWN, Beams, occupancy_grid, write_map_server
from scipy.spatial import cKDTree

ROOM = np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [4.0, 3.0, 0.0, 3.0], [0.0, 3.0, 0.0, 0.0]])
"""A 4 m x 3 m room."""


def read_map_server(yaml_path: Path) -> tuple[np.ndarray, tuple[float, float], float]:
    """A map as nav2's map_server loads it (map_io.cpp, trinary): the YAML's image, resolution and
    origin; each pixel p read as occupancy (255 - p) / 255 (negate 0): above occupied_thresh 100,
    below free_thresh 0, else -1; the image's first row the northernmost. Cells (rows from south)."""
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["mode"] == "trinary" and meta["negate"] == 0 and meta["origin"][2] == 0.0
    data = (yaml_path.parent / meta["image"]).read_bytes()
    assert data.startswith(b"P5\n")
    fields, rest = [], data[3:]
    while len(fields) < 3:  # width, height, maxval, with comments between
        line, rest = rest.split(b"\n", 1)
        if not line.startswith(b"#"):
            fields += line.split()
    width, height, maxval = map(int, fields)
    assert maxval == 255 and len(rest) == width * height
    occupancy = (255 - np.frombuffer(rest, np.uint8).reshape(height, width)[::-1].astype(float)) / 255
    cells = np.full(occupancy.shape, -1, dtype=np.int8)
    cells[occupancy > meta["occupied_thresh"]] = 100
    cells[occupancy < meta["free_thresh"]] = 0
    return cells, (meta["origin"][0], meta["origin"][1]), float(meta["resolution"])


def _cast(pose: Transform2D, walls: np.ndarray, n: int = 360) -> Beams:
    """A scan at ``pose`` of ``walls``, each beam to the nearest wall it meets."""
    angles = -math.pi + 2 * math.pi * np.arange(n) / n
    ranges = np.full(n, np.inf)
    for i, a in enumerate(angles + pose.theta):
        d = np.array([math.cos(a), math.sin(a)])
        for x1, y1, x2, y2 in walls:
            e = np.array([x2 - x1, y2 - y1])
            m = np.array([d, -e]).T
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, np.array([x1 - pose.x, y1 - pose.y]))
            if t > 0 and 0 <= u <= 1:
                ranges[i] = min(ranges[i], t)
    return Beams(pose, -math.pi, 2 * math.pi / n, 30.0, ranges)


def test_the_beams_free_the_room_and_its_walls_are_occupied(tmp_path: Path) -> None:
    scan = _cast(Transform2D(1.0, 1.0, 0.3), ROOM)
    grid = occupancy_grid([scan], ROOM, resolution=0.05)
    row, col, inside = grid.cell_of(np.array([[2.0, 1.5], [0.3, 2.7], [3.7, 0.3]]))
    assert inside.all() and (grid.cells[row, col] == FREE).all()
    # every wall point is occupied, and nothing outside the room is known
    t = np.linspace(0, 1, 200)[:, None]
    on_walls = np.vstack([w[0:2] + t * (w[2:4] - w[0:2]) for w in ROOM])
    row, col, inside = grid.cell_of(on_walls)
    assert inside.all() and (grid.cells[row, col] == OCCUPIED).all()
    row, col, inside = grid.cell_of(np.array([[-0.06, 1.5], [4.06, 1.5], [2.0, 3.06]]))
    assert (grid.cells[row[inside], col[inside]] == UNKNOWN).all()
    # map_server reads the same cells back, at the same place
    write_map_server(grid, tmp_path)
    cells, origin, resolution = read_map_server(tmp_path / "map.yaml")
    np.testing.assert_array_equal(cells, grid.cells)
    assert origin == pytest.approx(grid.origin) and resolution == 0.05
    wall_point = np.array([4.0, 1.5])
    r, c = np.floor((wall_point[::-1] - np.array(origin)[::-1]) / resolution).astype(int)
    assert cells[r, c] == 100


def test_a_beam_that_ends_on_no_wall_or_never_returns_frees_nothing() -> None:
    # from (1, 1.5): ahead (east) a passer-by at 1 m, whom the walls do not have; north a beam to
    # the wall 1.5 m off; west a beam of no return; south the wall 1.5 m off, read as the no-return
    # value of a log whose range_max was not given
    pose = Transform2D(1.0, 1.5, 0.0)
    ranges = np.array([1.0, 1.5, np.nan, 81.91])
    grid = occupancy_grid([Beams(pose, 0.0, math.pi / 2, math.inf, ranges)], ROOM, 0.05)
    row, col, _ = grid.cell_of(np.array([[1.5, 1.5], [1.0, 2.2], [0.5, 1.5], [1.0, 0.8]]))
    assert list(grid.cells[row, col]) == [UNKNOWN, FREE, UNKNOWN, UNKNOWN]


def test_a_wall_the_beams_pass_through_is_not_in_the_grid() -> None:
    # the map's walls hold one more, across the middle of the room, that the robot drove through
    # (a merged segment bridging two pieces): its beams pass it at every angle and end on the room
    across = np.array([[2.0, 0.0, 2.0, 3.0]])
    scans = [_cast(Transform2D(x, 1.5, 0.0), ROOM) for x in (0.5, 1.2, 2.0, 2.8, 3.5)]
    grid = occupancy_grid(scans, np.vstack([ROOM, across]), 0.05)
    t = np.linspace(0.05, 0.95, 100)[:, None]
    row, col, _ = grid.cell_of(across[0, 0:2] + t * (across[0, 2:4] - across[0, 0:2]))
    assert (grid.cells[row, col] == FREE).all()
    # the room's own walls, where the beams ended, stay occupied
    on_walls = np.vstack([w[0:2] + t * (w[2:4] - w[0:2]) for w in ROOM])
    row, col, _ = grid.cell_of(on_walls)
    assert (grid.cells[row, col] == OCCUPIED).all()


def test_no_scans_and_no_walls_give_an_unknown_grid() -> None:
    grid = occupancy_grid([], np.zeros((0, 4)))
    assert (grid.cells == UNKNOWN).all()


REAL_LOGS = [
    # (log, its no-return reading, the first scans mapped): enough of each tour that the grid of
    # fused walls alone drew walls across the robot's own path
    ("aces/aces.clf.gz", "50", 600),
    ("fr079/fr079.clf.gz", "81.91", 1200),
    ("mit-csail/mit-csail.clf.gz", "81.91", 600),
]


@pytest.mark.slow  # maps 600-1200 real scans of each log (about 50 s in all)
@pytest.mark.parametrize(("log", "range_max", "scans"), REAL_LOGS, ids=[p[0].split("/")[0] for p in REAL_LOGS])
def test_no_wall_stands_where_the_robot_stood(
    datasets: Path, tmp_path: Path, log: str, range_max: str, scans: int
) -> None:
    # the map nav2 loads from `fleetmap map` has no occupied cell within 0.1 m of any placed scan's
    # laser position: the robot drove there, so a wall there is one the beams contradict
    lines, taken = [], 0
    with gzip.open(datasets / log, "rt") as fh:
        for line in fh:
            if line.startswith("FLASER"):
                taken += 1
                if taken > scans:
                    break
            if line.startswith(("FLASER", "ODOM")):
                lines.append(line)
    piece = tmp_path / "piece.clf"
    piece.write_text("".join(lines))
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "fleetmap", "map", str(piece), "--out", str(out), "--no-return-reading", range_max,
         "--no-progress"],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    with (out / "poses.csv").open(encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r["component"] == "0"]  # the grid is component 0's
    assert len(rows) > 0.9 * scans
    stood = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    cells, origin, resolution = read_map_server(out / "map.yaml")
    assert (cells == OCCUPIED).sum() > 2000 and (cells == FREE).sum() > 5 * (cells == OCCUPIED).sum()
    row, col = np.nonzero(cells == OCCUPIED)
    low = np.column_stack([origin[0] + col * resolution, origin[1] + row * resolution])
    # each occupied cell's square against the nearest laser positions: its nearest point to each
    near = cKDTree(stood).query_ball_point(low + resolution / 2, 0.1 + resolution / math.sqrt(2))
    close = []
    for corner, found in zip(low, near, strict=True):
        if found:
            gap = np.maximum(np.maximum(corner - stood[found], stood[found] - (corner + resolution)), 0.0)
            if np.hypot(gap[:, 0], gap[:, 1]).min() < 0.1:
                close.append(corner.round(2).tolist())
    assert not close, f"{len(close)} occupied cells within 0.1 m of where the robot stood, e.g. {close[:5]}"
