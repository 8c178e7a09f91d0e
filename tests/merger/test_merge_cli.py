"""``fleetmap merge`` as a user runs it: the contract's JSON, the outputs, clear errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.mapfile import write_map

from tests.merger.test_graph import MAPS, TRUE
from tests.test_cli import fleetmap

pytestmark = pytest.mark.slow  # every test runs the command line in a process of its own


def _files(tmp_path: Path, keys: list[str]) -> list[str]:
    paths = []
    for key in keys:
        path = tmp_path / f"{key}.json"
        write_map(path, MAPS[key])
        paths.append(str(path))
    return paths


def test_unknown_order_prints_the_contract_and_writes_map_and_plot(tmp_path: Path) -> None:
    files = _files(tmp_path, ["m3", "m0", "m4", "m1"])
    out, png = tmp_path / "global.json", tmp_path / "global.png"
    r = fleetmap("merge", *files, "--order", "unknown", "--json", "--out", str(out), "--plot", str(png))
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert set(result) == {"poses", "components", "segments"}
    assert set(result["poses"]) == set(files) and result["components"] == [result["components"][0]]
    assert sorted(result["components"][0]) == sorted(files)
    anchor = next(f for f in files if result["poses"][f] == {"x": 0.0, "y": 0.0, "theta": 0.0})
    world = TRUE[Path(anchor).stem]
    for f in files:
        p = result["poses"][f]
        dt, dr = world.compose(Transform2D(p["x"], p["y"], p["theta"])).distance(TRUE[Path(f).stem])
        assert dt < 0.05 and dr < math.radians(1)
    assert len(result["segments"]) > 10
    written = json.loads(out.read_text())
    assert written["segments"] == result["segments"] and set(written["poses"]) == set(files)
    assert png.stat().st_size > 10_000


def test_known_order_uses_the_first_map_as_anchor(tmp_path: Path) -> None:
    files = _files(tmp_path, ["m0", "m1", "m2"])
    r = fleetmap("merge", *files, "--order", "pivot", "--json")
    assert r.returncode == 0, r.stderr
    poses = json.loads(r.stdout)["poses"]
    assert poses[files[0]] == {"x": 0.0, "y": 0.0, "theta": 0.0}
    p = poses[files[2]]
    dt, dr = Transform2D(p["x"], p["y"], p["theta"]).distance(TRUE["m0"].inverse().compose(TRUE["m2"]))
    assert dt < 0.05 and dr < math.radians(1)


def test_bad_inputs_exit_2_with_one_line(tmp_path: Path) -> None:
    good = _files(tmp_path, ["m0"])[0]
    bad = tmp_path / "bad.json"
    bad.write_text('{"segments": [[0, 0, 0, 0]]}')
    r = fleetmap("merge", good, str(bad))
    assert r.returncode == 2 and "bad.json" in r.stderr and "zero length" in r.stderr
    r = fleetmap("merge", good, good)
    assert r.returncode == 2 and "twice" in r.stderr
    r = fleetmap("merge", good, "--order", "zigzag")
    assert r.returncode == 2
