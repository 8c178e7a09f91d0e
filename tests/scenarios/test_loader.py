"""Scenario files: the bundled ones load and stay in free space; bad fields fail with a clear message."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fleetmap.scenarios.fleet import Join, Kidnap, Leave, MergerRestart, plan
from fleetmap.scenarios.loader import (
    DEFAULT_SCENARIO,
    MAX_SCAN_SPACING,
    MAX_SCAN_TURN,
    list_scenarios,
    load_scenario,
    read_scenario,
    scenario_to_toml,
)
from fleetmap.shared.core.geometry import point_segment_distance, segments_intersect
from fleetmap.shared.errors import ConfigError

WriteScenario = Callable[..., Path]


def moves(scenario_name: str) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """Every straight move of every robot of a bundled scenario, kidnap paths included."""
    sc = load_scenario(scenario_name)
    out = []
    for r in sc.robots:
        out += list(zip(r.path[:-1], r.path[1:], strict=True))
    for e in sc.kidnaps():
        pts = ((e.pose.x, e.pose.y), *e.path)
        out += list(itertools.pairwise(pts))
    return out


def test_the_bundled_scenarios_include_the_default_and_events_in_every_world() -> None:
    names = list_scenarios()
    assert DEFAULT_SCENARIO == "department" and {"department", "office", "warehouse"} <= set(names)
    kinds_by_world: dict[str, set[str]] = {}
    for name in names:
        sc = load_scenario(name)
        kinds_by_world.setdefault(sc.world.name, set()).update(e.kind for e in sc.events)
    for world in ("department", "office", "warehouse"):
        assert {"join", "leave", "crash", "kidnap"} <= kinds_by_world[world], world
    assert any(isinstance(e, MergerRestart) for n in names for e in load_scenario(n).events)


@pytest.mark.parametrize("name", list_scenarios())
def test_every_bundled_robot_drives_in_free_space(name: str) -> None:
    sc = load_scenario(name)
    walls = sc.world.walls
    for a, b in moves(name):
        move = np.array([[a[0], a[1], b[0], b[1]]])
        assert not segments_intersect(move, walls).any(), (name, a, b)
        k = np.linspace(0, 1, 50)[:, None]
        points = np.array(a) + (np.array(b) - np.array(a)) * k
        assert point_segment_distance(points[:, None, :], walls[None]).min() > 0.2, (name, a, b)
        assert sc.world.inside(points).all(), (name, a, b)


@pytest.mark.parametrize("name", list_scenarios())
def test_consecutive_scans_stay_within_the_papers_displacements(name: str) -> None:
    # Section V: 0.34 to 2.8 m and up to 1.73 rad between consecutive scans.
    sc = load_scenario(name)
    for r in sc.robots:
        scans = plan(sc, r.id)
        assert len(scans) >= 8, r.id
        for s, t in itertools.pairwise(scans):
            if s.leg == t.leg:
                shift, turn = s.pose.distance(t.pose)
                assert shift <= MAX_SCAN_SPACING + 1e-9 and turn <= MAX_SCAN_TURN + 1e-9, (r.id, s.index)


def test_the_default_scenario_is_short_three_robots_on_the_loop() -> None:
    sc = load_scenario(DEFAULT_SCENARIO)
    counts = [len(plan(sc, r.id)) for r in sc.robots]
    assert len(counts) == 3 and all(100 <= n <= 160 for n in counts), counts  # 5 Hz for 20-30 s
    assert max(plan(sc, r.id)[-1].stamp for r in sc.robots) < 30.0


def test_a_file_reads_back_from_its_resolved_form(tmp_path: Path) -> None:
    for name in ("department-events", "office"):
        sc = load_scenario(name)
        copy = tmp_path / f"{name}.toml"
        copy.write_text(scenario_to_toml(sc))
        again = read_scenario(copy)
        assert (again.name, again.world, again.seed, again.laser) == (sc.name, sc.world, sc.seed, sc.laser)
        assert again.robots == sc.robots and again.events == sc.events


def test_events_are_sorted_by_time_and_a_join_sets_the_start(scenario_file: WriteScenario) -> None:
    path = scenario_file(
        ("start = 1.0\n", ""),
        (
            '[[events]]\nt = 4.0\ntype = "kidnap"',
            '[[events]]\nt = 2.5\ntype = "join"\nrobot = "r2"\n\n[[events]]\nt = 4.0\ntype = "kidnap"',
        ),
    )
    sc = read_scenario(path)
    assert [type(e) for e in sc.events] == [Join, Kidnap, Leave]
    assert sc.robot("r2").start == 2.5 and plan(sc, "r2")[0].stamp == 2.5


def test_names_and_paths_both_load_and_an_unknown_name_lists_the_bundled_ones(tmp_path: Path) -> None:
    assert load_scenario("office").world.name == "office"
    with pytest.raises(ConfigError) as err:
        load_scenario("atlantis")
    assert "atlantis" in str(err.value) and "department" in str(err.value)
    with pytest.raises(ConfigError, match="no such scenario file"):
        load_scenario(tmp_path / "missing.toml")


BAD_FIELDS = [
    # (edit of the small scenario, field named in the error, what the error says)
    (("seed = 3", "seed = 3\nsede = 4"), "sede", "unknown key"),
    (("[laser]\nnoise = 0.01", "[laser]\nnoise = 0.01\nfov = 3.1"), "laser.fov", "unknown key"),
    (("spacing = 1.0", 'spacing = "1.0"'), "robots[0].spacing", "must be a number"),
    (("spacing = 1.0", "spacing = 3.0"), "robots[0].spacing", "<= 2.8"),
    (("period = 0.5", "period = 0"), "robots[0].period", "> 0"),
    (('id = "r1"', 'id = "Robot 1"'), "robots[0].id", "not a robot id"),
    (('id = "r2"', 'id = "r1"'), "robots[1].id", "duplicate"),
    (("[5.5, 6.0], [12.0, 6.0]", "[5.5, 6.0], [40.0, 6.0]"), "robots[0].path[4]", "outside"),
    (("[5.5, 6.0], [12.0, 6.0]", "[5.5, 6.0], [12.0, 3.0]"), "robots[0].path[4]", "outside"),
    (("[[14.0, 1.2], [8.0, 1.2]", "[[14.0, 1.2], [14.0, 6.0]"), "robots[1].path[1]", "goes through the wall"),
    (("[[14.0, 1.2], [8.0, 1.2]", "[[14.0, 1.2], [8.0, 0.3]"), "robots[1].path[1]", "from a wall"),
    (("[3.5, 5.6], [5.5, 6.0]", "[3.5, 5.6], [2.5, 6.0]"), "robots[0].path[3]", "turns"),
    (("[2.5, 2.2], [2.5, 3.9]", "[2.5, 2.2], [2.5, true]"), "robots[0].path[1]", "waypoint [x, y]"),
    (('robot = "r2"', 'robot = "r9"'), "events[1].robot", "unknown robot 'r9'"),
    (('type = "leave"', 'type = "explode"'), "events[1].type", "unknown event type"),
    (("t = 5.0", "t = 0.5"), "events[1].t", "before it starts"),
    (("t = 4.0", "t = 40.0"), "events[0].t", "finished its path"),
    (("pose = [20.0, 1.2, 3.14]", "pose = [20.0, 1.2]"), "events[0].pose", "pose [x, y, theta]"),
    (("[[16.0, 1.2], [12.0, 1.2]]", "[[16.0, 1.2], [16.0, 6.0]]"), "events[0].path[1]", "goes through the wall"),
    (('world = "department"', 'world = "moon"'), "world", "unknown world"),
    (("[[events]]\nt = 5.0", "[[events]]\nt = 5.0\ndown_for = 2.0"), "events[1].down_for", "unknown key"),
]


@pytest.mark.parametrize(("edit", "field", "reason"), BAD_FIELDS, ids=[b[1] + ":" + b[2] for b in BAD_FIELDS])
def test_a_bad_field_fails_naming_the_file_the_field_and_the_problem(
    scenario_file: WriteScenario, edit: tuple[str, str], field: str, reason: str
) -> None:
    path = scenario_file(edit)
    with pytest.raises(ConfigError) as err:
        read_scenario(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {field}: "), message
    assert reason in message, message
    assert "\n" not in message


def test_a_file_that_is_not_toml_or_has_no_robots_is_refused(scenario_file: WriteScenario, tmp_path: Path) -> None:
    broken = tmp_path / "broken.toml"
    broken.write_text("world = [department\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        read_scenario(broken)
    empty = tmp_path / "empty.toml"
    empty.write_text('world = "office"\n')
    with pytest.raises(ConfigError, match=r"robots: missing"):
        read_scenario(empty)


def test_the_laser_table_sets_the_simulated_laser(scenario_file: WriteScenario) -> None:
    sc = read_scenario(
        scenario_file(("noise = 0.01", "noise = 0.02\nfov_deg = 270\nresolution_deg = 0.5\ndropout = 0.1"))
    )
    assert sc.laser.beams == 541 and sc.laser.noise == 0.02 and sc.laser.dropout == 0.1
    assert math.isclose(sc.laser.fov, math.radians(270))
