"""MCAP recordings: raw round trips, files cut short by a crash, and Foxglove views that decode."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.foxglove_scene import (
    FRAME_TRANSFORM,
    POSES_IN_FRAME,
    ROOT_FRAME,
    SCENE_UPDATE,
    TF_TOPIC,
    FoxgloveScene,
    foxglove_views,
)
from fleetmap.shared.io.messages import (
    Component,
    FleetEvent,
    GlobalMap,
    LaserRanges,
    LocalMap,
    MergeEdge,
    RobotPose,
    Scan,
)
from fleetmap.shared.io.recording import RecordingWriter, config_metadata
from fleetmap.shared.io.recording_reader import RecordingReader
from mcap.reader import make_reader

from tests.protobuf_wire import Schema

TOPICS = ("fleet/t/robots/r1/scan", "fleet/t/robots/r2/scan", "fleet/t/events")
SEGMENTS = np.array([[0.0, 0.0, 2.0, 0.0], [2.0, 0.0, 2.0, 1.5]])


def raw_messages(n: int, start: int = 0) -> list[tuple[str, bytes, int, int]]:
    """(topic, payload, log_time, publish_time), log times 1 ms apart."""
    return [(TOPICS[i % 3], f"payload {i}".encode() * (1 + i % 5), 10**9 + i * 10**6, i) for i in range(start, n)]


def write(stream: io.BytesIO, chunks: list[list[tuple[str, bytes, int, int]]], finish: bool = True) -> list[int]:
    """Write each list of messages as one chunk; the stream's size after each chunk."""
    writer = RecordingWriter(stream)
    writer.add_metadata("fleetmap.session", {"fleet": "t"})
    sizes = []
    for chunk in chunks:
        for topic, payload, log_time, publish_time in chunk:
            writer.write_raw(topic, payload, log_time, publish_time)
        writer.flush()
        sizes.append(len(stream.getvalue()))
    if finish:
        writer.finish()
    return sizes


def read(data: bytes) -> tuple[list[tuple[str, bytes, int, int]], RecordingReader]:
    reader = RecordingReader(io.BytesIO(data))
    return [(m.topic, m.payload, m.log_time, m.publish_time) for m in reader.messages()], reader


def test_round_trip_keeps_every_message_exactly_in_log_time_order():
    stream = io.BytesIO()
    fed = raw_messages(300)
    write(stream, [fed[:100], fed[100:]])
    got, reader = read(stream.getvalue())
    assert got == fed
    assert reader.complete and reader.report.warning is None
    assert reader.report.messages == 300
    assert reader.topic_counts() == {t: 100 for t in TOPICS}
    assert reader.metadata() == {"fleetmap.session": {"fleet": "t"}}


def test_raw_channels_are_msgpack_and_chunks_are_zstd():
    stream = io.BytesIO()
    write(stream, [raw_messages(10)])
    mcap = make_reader(io.BytesIO(stream.getvalue()))
    summary = mcap.get_summary()
    assert summary is not None
    assert {c.message_encoding for c in summary.channels.values()} == {"msgpack"}
    assert {c.schema_id for c in summary.channels.values()} == {0}
    assert {i.compression for i in summary.chunk_indexes} == {"zstd"}


def test_time_and_topic_filters():
    stream = io.BytesIO()
    fed = raw_messages(30)
    write(stream, [fed])
    reader = RecordingReader(io.BytesIO(stream.getvalue()))
    window = list(reader.messages(start_time=fed[10][2], end_time=fed[20][2]))
    assert [m.payload for m in window] == [m[1] for m in fed[10:20]]
    only = list(reader.messages(topics=[TOPICS[2]]))
    assert [m.payload for m in only] == [m[1] for m in fed if m[0] == TOPICS[2]]


def test_a_file_cut_mid_chunk_yields_every_message_of_its_complete_chunks(caplog):
    stream = io.BytesIO()
    fed = raw_messages(90)
    sizes = write(stream, [fed[:30], fed[30:60], fed[60:]], finish=False)
    cut = stream.getvalue()[: (sizes[1] + sizes[2]) // 2]
    got, reader = read(cut)
    assert got == fed[:60]
    report = reader.report
    assert not report.complete and report.messages == 60
    assert report.bytes_read == sizes[1] and report.file_bytes == len(cut)
    assert report.warning is not None
    assert f"read 60 messages from its complete chunks, {sizes[1]} of {len(cut)} bytes" in report.warning
    assert "ends abruptly" in caplog.text
    assert reader.metadata() == {"fleetmap.session": {"fleet": "t"}}


def test_every_cut_point_reads_whole_chunks_and_never_raises():
    stream = io.BytesIO()
    fed = raw_messages(40)
    write(stream, [fed[:10], fed[10:20], fed[20:30], fed[30:]])
    data = stream.getvalue()
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    chunk_ends = sorted(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)
    for cut in range(8, len(data) - 8, 7):
        got, reader = read(data[:cut])
        whole_chunks = sum(1 for end in chunk_ends if end <= cut)
        assert got == fed[: 10 * whole_chunks], f"cut at {cut} of {len(data)} bytes"
        assert not reader.complete


def test_a_finished_file_is_complete_even_without_the_indexes_being_read():
    stream = io.BytesIO()
    write(stream, [raw_messages(5)])
    _, reader = read(stream.getvalue())
    assert reader.report.bytes_read == reader.report.file_bytes == len(stream.getvalue())


def test_not_an_mcap_file_is_bad_input(tmp_path):
    with pytest.raises(BadInput, match="not an MCAP file"):
        RecordingReader(io.BytesIO(b"{}\n"))
    with pytest.raises(BadInput, match="no such file"):
        RecordingReader(tmp_path / "missing.mcap")


def test_a_recording_file_on_disk(tmp_path):
    path = tmp_path / "session.mcap"
    writer = RecordingWriter(path)
    writer.write_raw(TOPICS[0], b"x", 5, 5)
    writer.finish()
    with RecordingReader(path) as reader:
        assert [m.payload for m in reader.messages()] == [b"x"]
        assert reader.report.source == str(path)


def test_config_metadata_holds_every_parameter_and_the_toml():
    meta = config_metadata(FleetmapConfig())
    assert meta["integration.point_distance_tolerance"] == "0.015"
    assert "[extraction]" in meta["toml"]
    assert all(isinstance(v, str) for v in meta.values())


# --- Foxglove views ---


def decoded_views(messages: list[tuple[object, str]]) -> list[tuple[str, str, dict]]:
    """Write the views of (message, key) pairs to MCAP and decode them back with the file's schemas."""
    stream = io.BytesIO()
    writer = RecordingWriter(stream)
    for i, (message, key) in enumerate(messages):
        for view in foxglove_views(message, key):  # type: ignore[arg-type]
            writer.write_foxglove(view.topic, view.schema, view.data, i, i)
    writer.finish()
    out = []
    for schema, channel, message in make_reader(io.BytesIO(stream.getvalue())).iter_messages():
        assert schema is not None and schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
        out.append((channel.topic, schema.name, Schema(schema.data).decode(schema.name, message.data)))
    return out


def points(line: dict) -> list[tuple[float, float]]:
    return [(p.get("x", 0.0), p.get("y", 0.0)) for p in line["points"]]


def test_scans_and_local_maps_are_line_lists_in_their_own_frames():
    scan = Scan("r1", 0, 3, 12.5, SEGMENTS)
    local = LocalMap("r1", 0, 2, 13.0, SEGMENTS, 3, Transform2D(1.0, 0.0, 0.0))
    views = decoded_views([(scan, "fleet/t/robots/r1/scan"), (local, "fleet/t/robots/r1/localmap")])
    assert [(t, s) for t, s, _ in views] == [
        ("/foxglove/fleet/t/robots/r1/scan", "foxglove.SceneUpdate"),
        ("/foxglove/fleet/t/robots/r1/localmap", "foxglove.SceneUpdate"),
    ]
    scan_entity = views[0][2]["entities"][0]
    assert scan_entity["frame_id"] == "r1" and scan_entity["id"] == "scan/r1"
    assert scan_entity["timestamp"] == {"seconds": 12, "nanos": 500_000_000}
    line = scan_entity["lines"][0]
    assert line.get("type") == 2  # LINE_LIST: every two points are one segment
    assert points(line) == [(0.0, 0.0), (2.0, 0.0), (2.0, 0.0), (2.0, 1.5)]
    local_entity = views[1][2]["entities"][0]
    assert local_entity["frame_id"] == "r1/0/0" and local_entity["id"] == "r1/0/0"  # the submap's own frame


def test_a_global_map_draws_its_components_and_places_its_local_maps():
    component = Component(
        "r1/0", ("r1/0", "r2/0"), {"r1/0": Transform2D(), "r2/0": Transform2D(1.0, 2.0, math.pi / 2)}, SEGMENTS
    )
    alone = Component("r3/0", ("r3/0",), {"r3/0": Transform2D()}, SEGMENTS[:1])
    views = decoded_views([(GlobalMap(4, 20.0, (component, alone)), "fleet/t/merger/globalmap")])
    scene = views[0][2]
    assert scene["deletions"][0].get("type") == 1  # ALL: the previous global map's entities go
    assert [(e["id"], e["frame_id"]) for e in scene["entities"]] == [
        ("component/0", "global"),
        ("component/1", "global/1"),
    ]
    transforms = {v["child_frame_id"]: v for t, s, v in views[1:] if t == TF_TOPIC and s == FRAME_TRANSFORM.name}
    assert set(transforms) == {"global", "global/1", "r1/0", "r2/0", "r3/0"}
    placed = transforms["r2/0"]
    assert placed["parent_frame_id"] == "global"
    assert placed["translation"] == {"x": 1.0, "y": 2.0}
    assert placed["rotation"]["z"] == pytest.approx(math.sin(math.pi / 4))
    assert placed["rotation"]["w"] == pytest.approx(math.cos(math.pi / 4))
    assert transforms["r3/0"]["parent_frame_id"] == "global/1"


def test_a_scan_draws_its_beams_and_hangs_the_robots_frame_on_its_submap():
    ranges = LaserRanges(-math.pi / 2, math.pi / 2, 8.0, np.array([1.0, np.nan, 9.0]))
    scan = Scan("r1", 0, 3, 12.5, SEGMENTS, ranges, submap=2, pose=Transform2D(0.5, -0.25, 0.1))
    views = decoded_views([(scan, "fleet/t/robots/r1/scan")])
    assert [(t, s) for t, s, _ in views] == [
        ("/foxglove/fleet/t/robots/r1/scan", "foxglove.SceneUpdate"),
        ("/foxglove/fleet/t/robots/r1/scan/laser", "foxglove.LaserScan"),
        (TF_TOPIC, "foxglove.FrameTransform"),
    ]
    laser = views[1][2]
    assert laser["frame_id"] == "r1" and laser["start_angle"] == pytest.approx(-math.pi / 2)
    assert laser["end_angle"] == pytest.approx(math.pi / 2)
    assert laser["ranges"][0] == 1.0 and all(math.isnan(r) for r in laser["ranges"][1:])  # no return: not drawn
    link = views[2][2]
    assert (link["parent_frame_id"], link["child_frame_id"]) == ("r1/0/2", "r1")
    assert link["translation"] == {"x": 0.5, "y": -0.25}
    # a robot's pose message adds nothing: its frame is where its scans put it
    assert decoded_views([(RobotPose("r2", 1, 30.0, Transform2D(-1.0, 0.5, 0.0), 1), "fleet/t/robots/r2/pose")]) == []


def test_every_frame_of_a_session_reaches_the_root_and_each_robot_has_its_path():
    table = {"scan_indices": np.array([0, 1]), "scan_stamps": np.array([1.0, 1.1]), "scan_poses": np.zeros((2, 3))}
    maps = [LocalMap(r, 0, 0, 1.0, SEGMENTS, 2, Transform2D(), **table) for r in ("r1", "r2", "r3")]  # type: ignore[arg-type]
    together = Component(
        "r1/0/0", ("r1/0/0", "r2/0/0"), {"r1/0/0": Transform2D(), "r2/0/0": Transform2D(1.0, 2.0, 0.0)}, SEGMENTS
    )
    alone = Component("r3/0/0", ("r3/0/0",), {"r3/0/0": Transform2D()}, SEGMENTS)
    scene = FoxgloveScene()
    views = [v for m in maps for v in scene.views(m, f"fleet/t/robots/{m.robot}/localmap")]
    views += scene.views(GlobalMap(1, 2.0, (together, alone)), "fleet/t/merger/globalmap")
    parent = {}
    frames = set()
    for view in views:
        decoded = Schema(view.schema.data).decode(view.schema.name, view.data)
        if view.schema.name == "foxglove.FrameTransform":
            parent[decoded["child_frame_id"]] = decoded["parent_frame_id"]
        frames.update(e["frame_id"] for e in decoded.get("entities", []))
        if "frame_id" in decoded:
            frames.add(decoded["frame_id"])
    for frame in frames:
        seen = [frame]
        while seen[-1] != ROOT_FRAME:
            assert seen[-1] in parent and len(seen) < 10, seen
            seen.append(parent[seen[-1]])
    # the lone component sits beside the first, not on it
    assert parent["global/1"] == ROOT_FRAME
    paths = {v.topic: v for v in views if v.schema.name == "foxglove.PosesInFrame"}
    assert set(paths) == {f"/foxglove/fleet/t/paths/{r}" for r in ("r1", "r2", "r3")}
    r2 = Schema(POSES_IN_FRAME.data).decode("foxglove.PosesInFrame", paths["/foxglove/fleet/t/paths/r2"].data)
    assert r2["frame_id"] == "global" and r2["poses"][0]["position"] == {"x": 1.0, "y": 2.0}


def test_events_are_log_lines_and_edges_have_no_view():
    event = FleetEvent("kidnap", "r1", 5.0, "carried to the lab")
    edge = MergeEdge("r1/0", "r2/0", 0.0, 0.0, 0.0, 3.0, True, 5.0)
    views = decoded_views([(event, "fleet/t/events"), (edge, "fleet/t/merger/edges")])
    assert len(views) == 1
    topic, schema, entry = views[0]
    assert (topic, schema) == ("/foxglove/fleet/t/events", "foxglove.Log")
    assert entry["message"] == "kidnap r1 carried to the lab"


def test_foxglove_schemas_are_the_sdk_ones():
    assert SCENE_UPDATE.name == "foxglove.SceneUpdate" and SCENE_UPDATE.encoding == "protobuf"
    assert "foxglove.SceneUpdate" in Schema(SCENE_UPDATE.data).messages


def test_a_second_writer_of_a_recording_being_written_is_refused_by_name(tmp_path):
    # two recorders started together both found session.mcap free; each wrote into it
    path = tmp_path / "session.mcap"
    first = RecordingWriter(path)
    first.write_raw("fleet/t/events", FleetEvent("recorder_start", None, 1.0).to_msgpack(), 10, 10)
    with pytest.raises(BadInput, match=f"{path}.*another recorder is writing it"):
        RecordingWriter(path)
    first.finish()
    with RecordingReader(path) as reader:
        assert [m.topic for m in reader.messages()] == ["fleet/t/events"]
    RecordingWriter(path).finish()  # once the first is done with it, the file is free again
