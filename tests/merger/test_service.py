"""The merger's logic as a library: local maps in, global map and robot poses out."""

from __future__ import annotations

import functools
import json
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest
from fleetmap.merger import intake, schedule
from fleetmap.merger.budget import SubmapBudget
from fleetmap.merger.engine import Merger
from fleetmap.scenarios.metrics import pose_error, world_from_global
from fleetmap.shared.config import FleetmapConfig, MergeParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Window
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import (
    EpochLink,
    FleetEvent,
    GlobalMap,
    LocalMap,
    MergeEdge,
    MergerStep,
    RobotPose,
    Scan,
    decode,
)

from tests.helpers import set_constant, true_local_map

KEYS = FleetKeys("test")


@pytest.fixture(scope="module")
def maps() -> dict[str, tuple[LocalMap, Transform2D]]:
    """Whole-path local maps of the three department robots (perfect agents)."""
    return {r: true_local_map("department", r, 0, 200) for r in ("r1", "r2", "r3")}


def _decoded(out: list) -> list:  # type: ignore[type-arg]
    return [decode(o.payload) for o in out]


def _feed(merger: Merger, messages: list[LocalMap]) -> list:  # type: ignore[type-arg]
    for m in messages:
        merger.receive(KEYS.localmap(m.robot), m.to_msgpack())
    return _decoded(merger.step())


@pytest.mark.slow  # integrates whole-path maps of 200 simulated scans
def test_three_robots_are_merged_and_placed(maps) -> None:  # type: ignore[no-untyped-def]
    merger = Merger(KEYS)
    out = _feed(merger, [maps[r][0] for r in ("r1", "r2", "r3")])
    step = next(m for m in out if isinstance(m, MergerStep))
    assert step.maps == ("r1/0/0", "r2/0/0", "r3/0/0") and step.versions == (0, 0, 0)
    assert sum(isinstance(m, MergeEdge) for m in out) == 3
    gmap = next(m for m in out if isinstance(m, GlobalMap))
    assert len(gmap.components) == 1 and set(gmap.components[0].members) == {"r1/0/0", "r2/0/0", "r3/0/0"}
    comp = gmap.components[0]
    world = world_from_global(maps[comp.anchor.split("/")[0]][1], comp.poses[comp.anchor])
    poses = {m.robot: m for m in out if isinstance(m, RobotPose)}
    assert set(poses) == {"r1", "r2", "r3"}
    for robot, (local, frame) in maps.items():
        p = poses[robot]
        assert p.pose is not None and p.component == 0 and p.stamp == local.stamp
        true_last = frame.compose(local.pose)  # the robot's true pose at its last scan
        e = pose_error(p.pose, true_last, world)
        assert e.translation_m < 0.10 and e.rotation_deg < 1.0, f"{robot}: {e}"


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_a_flood_of_malformed_messages_is_counted_and_changes_nothing(maps) -> None:  # type: ignore[no-untyped-def]
    clean, noisy = Merger(KEYS), Merger(KEYS)
    rng = np.random.default_rng(0)
    for k in range(300):
        noisy.receive(KEYS.localmap("r1"), rng.bytes(int(rng.integers(0, 200))))
        noisy.receive(KEYS.localmap("r2"), maps["r2"][0].to_msgpack()[: 10 + k])  # truncated
    bad_robot = maps["r1"][0].to_msgpack().replace(b"r1", b"R!")
    noisy.receive(KEYS.localmap("r1"), bad_robot)
    # a schema that is a list (16 bytes), and a local map whose epoch no map key can name (each of
    # its fields valid on its own): neither may stop the step that builds the global map
    noisy.receive(KEYS.localmap("r1"), msgpack.packb({"schema": [], "v": 1}))
    wire = msgpack.unpackb(maps["r1"][0].to_msgpack())
    noisy.receive(KEYS.localmap("r1"), msgpack.packb({**wire, "epoch": 10**18}))
    a = _feed(clean, [maps["r1"][0], maps["r2"][0]])
    b = _feed(noisy, [maps["r1"][0], maps["r2"][0]])
    assert noisy.stats.malformed == 603
    assert [m.to_msgpack() for m in a] == [m.to_msgpack() for m in b]


@pytest.mark.slow  # integrates whole-path maps of 200 simulated scans
def test_the_same_messages_in_the_same_order_give_identical_outputs(maps) -> None:  # type: ignore[no-untyped-def]
    runs = []
    for _ in range(2):
        merger = Merger(KEYS)
        out = _feed(merger, [maps["r2"][0], maps["r3"][0]]) + _feed(merger, [maps["r1"][0]])
        runs.append([m.to_msgpack() for m in out])
    assert runs[0] == runs[1]


@pytest.mark.slow  # integrates whole-path maps of 200 simulated scans
def test_a_restored_state_continues_exactly_like_the_original(maps, tmp_path) -> None:  # type: ignore[no-untyped-def]
    original = Merger(KEYS)
    _feed(original, [maps["r1"][0], maps["r2"][0]])
    original.schedule.behind = True  # as a live step that stopped at its budget leaves it: searches unranked
    original.save_state(tmp_path / "merger.state")
    restored = Merger(KEYS)
    restored.load_state(tmp_path / "merger.state")
    assert restored.schedule.behind
    assert restored.global_map.to_msgpack() == original.global_map.to_msgpack()
    # Every integration comes back as it was, the violation its validity limits included.
    assert {e.key(): e for e in restored.graph.edges} == {e.key(): e for e in original.graph.edges}
    assert any(e.solid_violation is not None for e in restored.graph.edges)
    assert any(e.information is not None for e in restored.graph.edges)  # how firmly walls fix it
    a = _feed(original, [maps["r3"][0]])
    b = _feed(restored, [maps["r3"][0]])
    assert [m.to_msgpack() for m in a] == [m.to_msgpack() for m in b]


def test_a_restored_merger_searches_its_queued_loops_where_the_original_would(tmp_path) -> None:  # type: ignore[no-untyped-def]
    small = {r: true_local_map("department", r, 0, 8)[0] for r in ("r1", "r2")}
    original = Merger(KEYS)
    _feed(original, [small["r1"], small["r2"]])
    pair = tuple(sorted(m.submap_key for m in small.values()))
    window = Window(Transform2D(1.5, -0.5, 0.3), 0.8, 0.2)
    original.schedule.queue[pair] = None  # a loop queued at the last step, not yet integrated
    original.schedule.windows[pair] = window
    original.save_state(tmp_path / "merger.state")
    restored = Merger(KEYS)
    restored.load_state(tmp_path / "merger.state")
    assert restored.schedule.windows == {pair: window}, "a restored merger would search the whole map"


def test_a_merger_killed_before_publishing_its_step_says_where_it_stands_when_restored(tmp_path) -> None:  # type: ignore[no-untyped-def]
    small = {r: true_local_map("department", r, 0, 8)[0] for r in ("r1", "r2")}
    assert Merger(KEYS).where_it_stands() == []  # a fresh merger has nothing to say yet
    killed = Merger(KEYS)
    for m in small.values():
        killed.receive(KEYS.localmap(m.robot), m.to_msgpack())
    lost = killed.step()  # saved, then killed before any of this was published
    killed.save_state(tmp_path / "merger.state")
    restored = Merger(KEYS)
    restored.load_state(tmp_path / "merger.state")
    # Everything that step would have published, byte for byte, the MergerStep everyone waits on last.
    said = restored.where_it_stands()
    assert [(o.key, o.payload) for o in said] == [(o.key, o.payload) for o in lost]
    kinds = [type(m).__name__ for m in _decoded(said)]
    assert {"MergeEdge", "GlobalMap", "RobotPose"} <= set(kinds) and kinds[-1] == "MergerStep"
    assert decode(said[-1].payload).maps == ("r1/0/0", "r2/0/0")  # type: ignore[union-attr]
    # The robots' republished maps are the versions it holds: no step follows, nothing else to say.
    for m in small.values():
        restored.receive(KEYS.localmap(m.robot), m.to_msgpack())
    assert restored.pending == 0 and restored.stats.stale == 2
    # A merger of another fleet restored from that state repeats nothing on its own keys.
    other = Merger(FleetKeys("other"))
    other.load_state(tmp_path / "merger.state")
    assert other.where_it_stands() == []


@functools.cache
def _three_robots_state() -> bytes:
    """The state file of a merger that stepped once with three robots' first maps."""
    merger = Merger(KEYS)
    for r in ("r1", "r2", "r3"):
        m = true_local_map("department", r, 0, 8)[0]
        merger.receive(KEYS.localmap(m.robot), m.to_msgpack())
    merger.step()
    with tempfile.TemporaryDirectory() as folder:
        merger.save_state(Path(folder) / "merger.state")
        return (Path(folder) / "merger.state").read_bytes()


def _rewrite_edges(path: Path, change: Callable[[dict], None]) -> None:
    state = msgpack.unpackb(path.read_bytes(), raw=False)
    for e in state["edges"]:
        change(e)
    path.write_bytes(msgpack.packb(state, use_bin_type=True))


def test_a_state_file_of_an_older_merger_is_refused_by_name(tmp_path) -> None:  # type: ignore[no-untyped-def]
    # Version 1 held whole-epoch local maps, not submaps: nothing in it carries over.
    path = tmp_path / "merger.state"
    path.write_bytes(_three_robots_state())
    state = msgpack.unpackb(path.read_bytes(), raw=False)
    state["v"] = 1
    path.write_bytes(msgpack.packb(state, use_bin_type=True))
    with pytest.raises(BadInput, match="merger state") as caught:
        Merger(KEYS).load_state(path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize(
    "information", [[math.nan] * 9, [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 0.0] + [0.0] * 6, [1.0]]
)
def test_a_state_whose_edge_information_is_no_weight_is_refused_by_name(tmp_path, information) -> None:  # type: ignore[no-untyped-def]
    # NaN, a matrix that is not positive semidefinite or not symmetric, or not 3x3: the merger
    # would fail at its first step on every step after; it refuses the file instead, naming it.
    path = tmp_path / "merger.state"
    path.write_bytes(_three_robots_state())
    _rewrite_edges(path, lambda e: e.update(information=information))
    with pytest.raises(BadInput, match="information") as caught:
        Merger(KEYS).load_state(path)
    assert str(path) in str(caught.value)


def test_a_robot_speaking_for_another_is_dropped_and_counted(maps) -> None:  # type: ignore[no-untyped-def]
    clean, spoofed = Merger(KEYS), Merger(KEYS)
    r1_map = maps["r1"][0]
    # r2 publishes r1's map (a newer version, its segments moved) on its own key, and a scan and an
    # epoch event naming r1 on its own keys: whatever a router let through, none of it counts
    forged = LocalMap("r1", 0, 99, r1_map.stamp, r1_map.segments + 5.0, r1_map.scans, r1_map.pose)
    spoofed.receive(KEYS.localmap("r2"), forged.to_msgpack())
    spoofed.receive(KEYS.robot_events("r2"), FleetEvent("epoch", "r1", 1.0, "{}").to_msgpack())
    assert spoofed.stats.foreign == 2 and spoofed.pending == 0
    a = _feed(clean, [r1_map, maps["r2"][0]])
    b = _feed(spoofed, [r1_map, maps["r2"][0]])
    assert [m.to_msgpack() for m in a] == [m.to_msgpack() for m in b]


def test_limits_refuse_oversized_submaps_extra_robots_and_queue_overflow_and_count_them(maps, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    small = min(len(maps[r][0].segments) for r in ("r1", "r2", "r3"))
    set_constant(monkeypatch, intake, "MAX_SUBMAP_SEGMENTS", small)
    set_constant(monkeypatch, schedule, "MAX_QUEUED_PAIRS", 1)
    merger = Merger(KEYS, FleetmapConfig(merge=MergeParams(max_robots=3)))
    big = max(("r1", "r2", "r3"), key=lambda r: len(maps[r][0].segments))
    merger.receive(KEYS.localmap(big), maps[big][0].to_msgpack())
    assert merger.pending == 0 and merger.stats.refused["max_submap_segments"] == 1
    for robot, source in (("r1", "r1"), ("r2", "r2"), ("r3", "r3"), ("r4", "r1")):
        m = maps[source][0]
        clipped = LocalMap(robot, 0, 1, m.stamp, m.segments[:small], m.scans, m.pose)
        merger.receive(KEYS.localmap(robot), clipped.to_msgpack())
    assert merger.pending == 3 and merger.stats.refused["max_robots"] == 1
    assert merger.presence("r9", True, 1.0) == [] and merger.stats.refused["max_robots"] == 2
    # three robots' first submaps search each other: three pairs due, one queued (a refused pair may be due again)
    merger.step(limit=0)
    assert merger.queued == 1 and merger.stats.refused["max_queued_pairs"] >= 2
    assert {k.split("/")[0] for c in merger.global_map.components for k in c.members} == {"r1", "r2", "r3"}


def test_an_integration_past_the_work_budget_is_said_counted_and_joins_nothing(maps, caplog) -> None:  # type: ignore[no-untyped-def]
    # (well under a second: the one integration stops at its first stage) The two robots' maps
    # merge within the default budget (test_three_robots_are_merged_and_placed); within 1,000 units
    # their integration stops, is said and counted, and its edge is not valid: two components
    merger = Merger(KEYS, FleetmapConfig(merge=MergeParams(max_integration_work=1000)))
    with caplog.at_level("WARNING"):
        out = _feed(merger, [maps["r1"][0], maps["r2"][0]])
    edges = [m for m in out if isinstance(m, MergeEdge)]
    assert len(edges) == 1 and not edges[0].valid and merger.stats.exhausted == 1
    assert "r1/0/0 and r2/0/0: the integration stopped at the work budget" in caplog.text
    assert len(next(m for m in out if isinstance(m, GlobalMap)).components) == 2


def test_an_old_version_is_stale_and_a_newer_one_replaces_the_map(maps) -> None:  # type: ignore[no-untyped-def]
    merger = Merger(KEYS)
    first, _ = true_local_map("department", "r1", 0, 6, version=0)
    _feed(merger, [first, maps["r2"][0]])
    merger.receive(KEYS.localmap("r1"), first.to_msgpack())
    assert merger.pending == 0 and merger.stats.stale == 1
    newer = LocalMap("r1", 0, 1, maps["r1"][0].stamp, maps["r1"][0].segments, 30, maps["r1"][0].pose)
    out = _feed(merger, [newer])
    assert next(m for m in out if isinstance(m, MergerStep)).versions == (1,)


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_a_lost_robot_is_unknown_until_relocalized(maps) -> None:  # type: ignore[no-untyped-def]
    merger = Merger(KEYS)
    _feed(merger, [maps["r1"][0], maps["r2"][0]])
    # r1 starts epoch 1 seeing next to nothing (a box in an open space): it cannot be placed.
    elsewhere = LocalMap("r1", 1, 0, 50.0, np.array([[1.0, -0.3, 1.0, 0.3], [1.0, 0.3, 1.4, 0.3]]), 1, Transform2D())
    out = _feed(merger, [elsewhere])
    pose = next(m for m in out if isinstance(m, RobotPose) and m.robot == "r1")
    assert pose.epoch == 1 and pose.pose is None and pose.component is None
    # Its next epoch sees the department again (r3's stretch): relocalized, with an event.
    back = LocalMap("r1", 2, 0, 99.0, maps["r3"][0].segments, 40, maps["r3"][0].pose)
    out = _feed(merger, [back])
    pose = next(m for m in out if isinstance(m, RobotPose) and m.robot == "r1")
    assert pose.epoch == 2 and pose.pose is not None and pose.component == 0
    event = next(m for m in out if isinstance(m, FleetEvent))
    assert event.kind == "relocalized" and event.robot == "r1"


def test_presence_is_published_and_maps_stay_after_a_leave(maps) -> None:  # type: ignore[no-untyped-def]
    merger = Merger(KEYS)
    join = _decoded(merger.presence("r1", True, 1.0))
    assert join[0].kind == "join" and join[0].robot == "r1"
    _feed(merger, [maps["r1"][0], maps["r2"][0]])
    leave = _decoded(merger.presence("r1", False, 2.0))
    assert leave[0].kind == "leave"
    assert "r1/0/0" in merger.global_map.components[0].members
    assert math.isfinite(merger.global_map.stamp)


@pytest.mark.slow  # integrates whole-path maps of 200 simulated scans
def test_a_stopping_merger_leaves_what_it_could_not_integrate_in_its_state(maps, tmp_path, caplog) -> None:  # type: ignore[no-untyped-def]
    # SIGTERM with maps received and none integrated: the service saves them and stops at once,
    # whatever its queue; the next start finishes the job to the same map
    import threading

    import fleetmap.merger.service as service
    from fleetmap.shared.io.memory_bus import InMemoryBus

    state = tmp_path / "merger.state"
    merger = Merger(KEYS)
    svc = service.MergerService(InMemoryBus(), merger, state_file=state, step_seconds=1e-6)
    for r in ("r1", "r2", "r3"):
        merger.presence(r, True, 0.0)  # a live merger listens to robots holding their token
        merger.receive(KEYS.localmap(r), maps[r][0].to_msgpack())
    stop = threading.Event()
    stop.set()
    with caplog.at_level("WARNING"):
        svc.run(stop)
    assert merger.backlog > 0 and f"kept in {state}" in caplog.text
    restored = Merger(KEYS)
    restored.load_state(state)
    assert restored.pending == 3 and merger.stats.steps == 0  # nothing received was lost, nothing was integrated
    while restored.has_work:
        restored.step()
    whole = Merger(KEYS)
    _feed(whole, [maps[r][0] for r in ("r1", "r2", "r3")])
    while whole.has_work:
        whole.step()
    assert len(restored.global_map.components) == len(whole.global_map.components) == 1
    for key, pose in whole.global_map.components[0].poses.items():
        other = restored.global_map.components[0].poses[key]
        assert pose.distance(other)[0] < 0.02 and pose.distance(other)[1] < 0.01


@pytest.mark.slow  # two zenoh sessions on loopback
def test_a_liveliness_token_that_names_no_robot_is_counted_and_the_merger_goes_on() -> None:
    from fleetmap.merger.service import MergerService

    from tests.bus_helpers import open_zenoh_pair

    merger_bus, other = open_zenoh_pair(KEYS.fleet)
    svc = MergerService(merger_bus, Merger(KEYS))
    tokens = []
    try:
        svc.start()
        # anyone on an open fleet may declare any token: one named like no robot, then a real robot
        tokens.append(other.declare_liveliness(f"{KEYS.prefix}/alive/BAD"))
        tokens.append(other.declare_liveliness(KEYS.alive("r9")))
        deadline = time.monotonic() + 5.0
        while "r9" not in svc.merger.robots and time.monotonic() < deadline:
            svc.run_once()
            time.sleep(0.01)
        assert svc.merger.robots == ["r9"]
        assert svc.merger.stats.malformed_reasons["liveliness token"] == 1
    finally:
        for token in tokens:
            token.close()
        svc.close()
        other.close()
        merger_bus.close()


def _box(robot: str, epoch: int = 0, submap: int = 0, version: int = 0, **fields) -> LocalMap:  # type: ignore[no-untyped-def]
    """A small valid submap (three walls of a box), as any process on an open fleet can send."""
    walls = np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [4.0, 3.0, 0.0, 3.0]])
    return LocalMap(robot, epoch, version, 1.0, walls, 3, Transform2D(), submap=submap, **fields)


def _live(max_robots: int = 256) -> Merger:
    merger = Merger(KEYS, FleetmapConfig(merge=MergeParams(max_robots=max_robots)))
    merger.require_presence = True  # as MergerService makes it
    return merger


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_fake_robots_without_tokens_or_gone_unplaced_take_no_room(maps, tmp_path) -> None:  # type: ignore[no-untyped-def]
    # 1000 ids' valid maps before the robots started filled the 256-robot limit for good, the
    # state file too: the real robots' messages were all refused
    merger = _live(max_robots=2)
    for i in range(1000):
        merger.receive(KEYS.localmap(f"f{i}"), _box(f"f{i}").to_msgpack())
    assert merger.pending == 0 and merger.stats.refused["absent"] == 1000
    # a fake that holds a token counts while it holds it, and is forgotten when it leaves unplaced
    # (a few centimetres of wall: nothing to place it by)
    merger.presence("f1", True, 1.0)
    scrap = LocalMap("f1", 0, 0, 1.0, np.array([[0.0, 0.0, 0.05, 0.0], [0.0, 0.1, 0.0, 0.15]]), 1, Transform2D())
    merger.receive(KEYS.localmap("f1"), scrap.to_msgpack())
    for robot in ("r1", "r2"):
        merger.presence(robot, True, 1.0)
        merger.receive(KEYS.localmap(robot), maps[robot][0].to_msgpack())
    assert merger.stats.refused["max_robots"] == 1 and merger.pending == 2  # f1 and r1 count, r2 waits
    merger.step()
    merger.presence("f1", False, 2.0)
    merger.receive(KEYS.localmap("r2"), maps["r2"][0].to_msgpack())
    # a robot that finished and left before a busy merger got to its map is not forgotten for that
    merger.presence("r1", False, 3.0)  # placed: it stays, and no longer counts
    merger.presence("r3", True, 3.0)
    merger.receive(KEYS.localmap("r3"), maps["r3"][0].to_msgpack())
    merger.presence("r3", False, 4.0)
    assert "r3" in merger.robots
    while merger.has_work:  # f1 is forgotten once its submap has had its tries
        merger.step()
    merger.save_state(tmp_path / "state")
    restored = _live()
    restored.load_state(tmp_path / "state")
    assert restored.robots == ["r1", "r2", "r3"] and len(restored.global_map.components) == 1


def test_a_final_submap_never_changes(maps) -> None:  # type: ignore[no-untyped-def]
    # a robot restarted under its id published a new r2/0/0 over its final one (map error 0.017 -> 2.2 m)
    merger = _live()
    merger.presence("r1", True, 1.0)
    final = LocalMap("r1", 0, 3, 5.0, maps["r1"][0].segments, 40, None, final=True)
    merger.receive(KEYS.localmap("r1"), final.to_msgpack())
    merger.step()
    merger.receive(KEYS.localmap("r1"), _box("r1", version=9).to_msgpack())
    assert merger.pending == 0 and merger.stats.refused["final_submap"] == 1
    assert merger.submaps["r1/0/0"].version == 3


def test_a_second_live_agent_under_an_id_is_refused_and_a_restarted_one_is_taken(maps) -> None:  # type: ignore[no-untyped-def]
    merger = _live()
    merger.presence("r2", True, 1.0)
    merger.receive(KEYS.localmap("r2"), _box("r2").to_msgpack())
    merger.step()
    # started elsewhere while r2 runs: its first epoch (no link to r2's) and the epochs after it
    said = _decoded(merger.receive(KEYS.localmap("r2"), _box("r2", epoch=1).to_msgpack()))
    assert [(e.kind, e.robot, json.loads(e.detail)["epoch"]) for e in said] == [("refused", "r2", 1)]
    kidnapped = _box("r2", epoch=2, previous_epoch_link=EpochLink(1, "lost"))
    merger.receive(KEYS.localmap("r2"), kidnapped.to_msgpack())
    merger.receive(KEYS.scan("r2"), Scan("r2", 2, 7, 1.0, np.zeros((0, 4))).to_msgpack())
    assert merger.pending == 0 and merger.stats.refused["second_agent"] == 3 and merger.robot_epoch("r2") == 0
    # the first agent's own kidnap is its own epoch, linked to its earlier one
    merger.receive(KEYS.localmap("r2"), _box("r2", epoch=3, previous_epoch_link=EpochLink(0, "lost")).to_msgpack())
    assert merger.pending == 1
    # r2 killed and started again: its first epoch after the ones held is taken
    merger.presence("r2", False, 2.0)
    merger.presence("r2", True, 3.0)
    merger.receive(KEYS.scan("r2"), Scan("r2", 4, 0, 1.0, np.zeros((0, 4))).to_msgpack())  # before its first map
    merger.receive(KEYS.localmap("r2"), _box("r2", epoch=4).to_msgpack())
    assert merger.pending == 2


def test_stamps_label_a_robot_s_maps_and_do_not_order_them(maps) -> None:  # type: ignore[no-untyped-def]
    merger = _live()
    merger.presence("r1", True, 1.0)
    now = 1.8e9
    m = maps["r1"][0]
    # a stamp past the skew window is refused; the map's stamp is the step's time
    merger.receive(KEYS.localmap("r1"), replace(m, stamp=9.2e9).to_msgpack(), now=now)
    assert merger.pending == 0 and merger.stats.refused["future_stamp"] == 1
    merger.receive(KEYS.localmap("r1"), replace(m, stamp=now + 3.0).to_msgpack(), now=now)
    merger.step(now=now + 1.0)
    assert merger.global_map.stamp == now + 1.0
    # its clock steps back an hour: its next version still moves its pose
    moved = replace(m, version=1, stamp=now - 3600.0, pose=m.pose.compose(Transform2D(0.5, 0.0, 0.0)))
    merger.receive(KEYS.localmap("r1"), moved.to_msgpack(), now=now)
    out = _decoded(merger.step(now=now + 2.0))
    pose = next(p for p in out if isinstance(p, RobotPose))
    assert pose.stamp == now - 3600.0 and merger.global_map.stamp == now + 2.0


def test_robots_take_turns_at_integration_so_a_flood_delays_only_its_robot(maps) -> None:  # type: ignore[no-untyped-def]
    # 2,000 epochs of one robot left 6,031 pairs queued ahead of the real robots' for a minute
    merger = Merger(KEYS)
    for epoch in range(30):
        link = EpochLink(epoch - 1, "lost") if epoch else None
        merger.receive(KEYS.localmap("f"), _box("f", epoch=epoch, previous_epoch_link=link, final=True).to_msgpack())
    merger.receive(KEYS.localmap("r1"), maps["r1"][0].to_msgpack())
    merger.step(limit=0)  # in the graph and placed: the flood's final submaps search from here on
    out = _decoded(merger.step(limit=2))
    edges = [m for m in out if isinstance(m, MergeEdge)]
    assert merger.queued > 20 and len(edges) == 2
    assert [sorted({e.a.split("/")[0], e.b.split("/")[0]}) for e in edges][1] == ["f", "r1"]  # r1's turn came second


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_the_global_map_is_the_component_of_the_most_robots_not_of_one_robot_s_many_epochs(maps) -> None:  # type: ignore[no-untyped-def]
    # a robot flooding its own key with epochs of one shape made their component the "largest": no
    # real robot was placed any more
    merger = Merger(KEYS)
    for epoch in range(4):
        link = EpochLink(epoch - 1, "lost") if epoch else None
        merger.receive(KEYS.localmap("f"), _box("f", epoch=epoch, previous_epoch_link=link, final=True).to_msgpack())
    for robot in ("r1", "r2"):
        merger.receive(KEYS.localmap(robot), maps[robot][0].to_msgpack())
    while merger.has_work:
        merger.step()
    robots_of = [{k.split("/")[0] for k in c.members} for c in merger.global_map.components]
    assert any(
        len({k.split("/")[1] for k in c.members if k.startswith("f/")}) > 2 for c in merger.global_map.components
    )
    assert robots_of[0] == {"r1", "r2"}


def test_a_robot_s_new_submaps_enter_the_graph_at_a_robot_s_pace_and_the_others_are_not_held_back(maps) -> None:  # type: ignore[no-untyped-def]
    # 500 epochs of one robot took the merger to 2.1x its memory: under the budget a window's worth
    # enters at once, as many again wait their turn, the rest is refused; r1 is not held back,
    # and new versions of what a robot holds are never held back
    merger = Merger(KEYS)
    merger.budget = SubmapBudget.of(merger.config)
    window = int(merger.budget.burst)
    assert window == 36  # 0.6 new submaps a second (3 m/s, a submap every 5 m), over a minute
    for epoch in range(500):
        link = EpochLink(epoch - 1, "lost") if epoch else None
        box = _box("f", epoch=epoch, previous_epoch_link=link, final=epoch > 0)
        merger.receive(KEYS.localmap("f"), box.to_msgpack(), now=100.0)
    merger.receive(KEYS.localmap("r1"), maps["r1"][0].to_msgpack(), now=100.0)
    assert merger.pending == window + 1 and len(merger.waiting) == 2 * window + 1
    assert merger.stats.refused["submap_budget"] == 500 - 2 * window
    merger.receive(KEYS.localmap("f"), _box("f", epoch=0, version=1).to_msgpack(), now=100.0)
    assert merger.pending == window + 1  # a new version of a submap taken: not a new submap
    merger.release(110.0)  # ten seconds on: six more of f's
    assert merger.pending == window + 1 + 6 and len(merger.waiting) == 2 * window + 1
    merger.release(1000.0)
    assert merger.pending == 2 * window + 1 and merger.waiting == list(merger._pending)
