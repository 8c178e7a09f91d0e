"""Offline replay of a live session, and a merger restart that loses nothing."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from fleetmap.scenarios import load_scenario, scenario_to_toml
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.foxglove_scene import ROOT_FRAME
from fleetmap.shared.io.recording_reader import RecordingReader
from mcap.reader import make_reader

from tests.protobuf_wire import Schema

pytestmark = pytest.mark.slow


def fleetmap(*args: str, timeout: float = 480) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "fleetmap", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("live") / "department"
    r = fleetmap("run", "department", "--out", str(out), "--speed", "4", "--no-progress")
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def _poses(global_map: Path) -> dict[str, Transform2D]:
    data = json.loads(global_map.read_text())
    return {k: Transform2D(v["x"], v["y"], v["theta"]) for k, v in data["poses"].items() if v is not None}


def test_a_replay_rebuilds_the_live_global_map_exactly(live: Path, tmp_path: Path) -> None:
    r = fleetmap("replay", str(live / "session.mcap"), "--out", str(tmp_path), "--json", "--no-progress")
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["replay"]["exact"] and report["replay"]["matches_live"] is True
    live_map = json.loads((live / "global_map.json").read_text())
    replayed = json.loads((tmp_path / "global_map.json").read_text())
    assert replayed["segments"] == live_map["segments"] and replayed["poses"] == live_map["poses"]
    live_report = json.loads((live / "report.json").read_text())
    assert report["map_error_mean_m"] == live_report["map_error_mean_m"]
    assert (tmp_path / "global_map.png").stat().st_size > 10_000


def test_a_partial_replay_takes_only_the_chosen_robots_and_times(live: Path, tmp_path: Path) -> None:
    r = fleetmap("replay", str(live / "session.mcap"), "--out", str(tmp_path), "--robots", "r1,r3", "--no-progress")
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["replay"]["exact"] is False
    assert report["maps"] and all(not k.startswith("r2/") for k in report["maps"])
    early = tmp_path / "early"
    r = fleetmap("replay", str(live / "session.mcap"), "--out", str(early), "--to", "2.0", "--no-progress")
    assert r.returncode == 0, r.stderr[-3000:]
    assert (
        json.loads((early / "report.json").read_text())["replay"]["local_maps_fed"]
        < report["replay"]["local_maps_fed"] + 1000
    )  # ran, and fed what the first two seconds held


@pytest.mark.parametrize("kept", [0.3, 0.6])
def test_a_recording_cut_short_replays_up_to_its_last_complete_chunk(live: Path, tmp_path: Path, kept: float) -> None:
    # a recorder killed anywhere: the replay ends, whatever part of the session the file holds
    data = (live / "session.mcap").read_bytes()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(data[: int(len(data) * kept)])
    r = fleetmap("replay", str(cut), "--out", str(tmp_path / "out"), "--no-progress")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "ends abruptly" in r.stdout and "messages" in r.stdout
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["replay"]["warning"] and report["replay"]["local_maps_fed"] > 0


def test_a_recording_cut_by_sigkill_is_recovered_into_a_file_any_reader_opens(live: Path, tmp_path: Path) -> None:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    data = (live / "session.mcap").read_bytes()
    cut, fixed = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with open(cut, "rb") as f, pytest.raises(McapError):  # the ordinary reader refuses a cut file
        list(make_reader(f).iter_messages())
    r = fleetmap("recover", str(cut), str(fixed))
    assert r.returncode == 0, r.stderr[-3000:]
    with RecordingReader(cut) as reader:
        raw = [(m.topic, m.payload, m.log_time) for m in reader.messages(warn=False)]
    with open(fixed, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        got = list(reader.iter_messages(log_time_order=False))
        metadata = {m.name for m in reader.iter_metadata()}
    assert [(c.topic, m.data, m.log_time) for _, c, m in got if c.message_encoding == "msgpack"] == raw
    assert any(c.message_encoding == "protobuf" and s is not None for s, c, _ in got)  # Foxglove views kept
    assert "fleetmap.session" in metadata and f"{len(got)} messages" in r.stdout
    again = fleetmap("recover", str(cut), str(fixed))
    assert again.returncode == 2 and "--overwrite" in again.stderr


def test_bad_replay_inputs_exit_2(tmp_path: Path) -> None:
    r = fleetmap("replay", str(tmp_path / "none.mcap"), "--out", str(tmp_path))
    assert r.returncode == 2 and "none.mcap" in r.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    r = fleetmap("replay", str(junk), "--out", str(tmp_path))
    assert r.returncode == 2 and "junk.mcap" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_replay_of_nothing_or_of_robots_not_there_exits_2_with_one_line(live: Path, tmp_path: Path) -> None:
    # the first 100 bytes of a real recording: a valid start, no message
    stub = tmp_path / "stub.mcap"
    stub.write_bytes((live / "session.mcap").read_bytes()[:100])
    r = fleetmap("replay", str(stub), "--out", str(tmp_path / "a"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "stub.mcap: holds no fleetmap message" in lines[0], r.stderr
    r = fleetmap("replay", str(live / "session.mcap"), "--out", str(tmp_path / "b"), "--robots", "r1,nosuch")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "no robot nosuch" in lines[0] and "r1, r2, r3" in lines[0]
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _relative(poses: dict[str, Transform2D], ref: str) -> dict[str, Transform2D]:
    base = poses[ref].inverse()
    return {k: base.compose(p) for k, p in poses.items()}


def test_a_merger_killed_and_restarted_ends_with_the_uninterrupted_map(tmp_path: Path) -> None:
    restart = load_scenario("department-restart")
    assert any(e.kind == "merger_restart" for e in restart.events)
    calm = dataclasses.replace(restart, events=tuple(e for e in restart.events if e.kind != "merger_restart"))
    calm_file = tmp_path / "calm.toml"
    calm_file.write_text(scenario_to_toml(calm))
    runs = {}
    for name, scenario in (("restart", "department-restart"), ("calm", str(calm_file))):
        out = tmp_path / name
        r = fleetmap("run", scenario, "--out", str(out), "--speed", "3", "--no-progress")
        assert r.returncode == 0, r.stderr[-3000:]
        runs[name] = out
    logs = sorted(p.name for p in (runs["restart"] / "logs").glob("merger*.log"))
    assert len(logs) == 2, logs  # the merger was killed and a second one started
    a, b = _poses(runs["restart"] / "global_map.json"), _poses(runs["calm"] / "global_map.json")
    assert set(a) == set(b), "the same local maps are placed"
    ref = sorted(a)[0]
    ra, rb = _relative(a, ref), _relative(b, ref)
    # A live merger integrates the pairs its time allows: the two runs' graphs differ by a few
    # pairs of submaps, so each map is as right as the other (each submap within about 0.10 m of
    # the truth), not the same to the millimetre: two runs can differ by twice that.
    for key in a:
        dt, dr = ra[key].distance(rb[key])
        assert dt < 0.20 and math.degrees(dr) < 1.0, f"{key}: {dt:.4f} m {math.degrees(dr):.3f} deg"
    restart_report = json.loads((runs["restart"] / "report.json").read_text())
    calm_report = json.loads((runs["calm"] / "report.json").read_text())
    for name, report in (("restart", restart_report), ("calm", calm_report)):
        for key, m in report["maps"].items():
            assert m["placed"] and m["error_m"] < 0.15 and m["error_deg"] < 1.5, f"{name} {key}: {m}"
    # ... and as accurate: both within the few centimetres a live run of the department reaches
    # (a live merger's pairs depend on its timing, so the two means differ by a centimetre or two)
    assert restart_report["map_error_mean_m"] < 0.06 and calm_report["map_error_mean_m"] < 0.06
    assert set(restart_report["maps"]) == set(calm_report["maps"]), "no local map is lost"


def test_every_foxglove_channel_of_a_live_recording_decodes_and_every_frame_reaches_the_root(live: Path) -> None:
    parent: dict[str, str] = {}
    frames: set[str] = set()
    schemas: Counter[str] = Counter()
    with (live / "session.mcap").open("rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages():
            if channel.message_encoding != "protobuf":
                continue
            assert schema is not None
            decoded = Schema(schema.data).decode(schema.name, message.data)
            schemas[schema.name] += 1
            if schema.name == "foxglove.FrameTransform":
                parent[decoded["child_frame_id"]] = decoded["parent_frame_id"]
            frames.update(e["frame_id"] for e in decoded.get("entities", []))
            if decoded.get("frame_id"):
                frames.add(decoded["frame_id"])
    wanted = {"SceneUpdate", "LaserScan", "PosesInFrame", "FrameTransform", "Grid", "Log"}
    assert {f"foxglove.{name}" for name in wanted} <= set(schemas), schemas
    assert schemas["foxglove.Grid"] == 1  # the occupancy grid, once the recording is finished
    assert {"r1", "r2", "r3", "global"} <= frames
    for frame in frames:
        chain = [frame]
        while chain[-1] != ROOT_FRAME:
            assert chain[-1] in parent and len(chain) < 20, chain
            chain.append(parent[chain[-1]])
