"""The recorder: everything fed is in the file, malformed messages too, flushed in time; over a bus
in memory, over zenoh on loopback, and as the ``fleetmap record`` process."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import threading
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
from fleetmap.merger.recorder import (
    Recorder,
    RecorderService,
    RecorderSummary,
    query_recorder_stats,
    wait_until_recorded,
)
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.bus import Bus
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import (
    BadMessage,
    Component,
    FleetEvent,
    GlobalMap,
    LocalMap,
    MergeEdge,
    RobotPose,
    Scan,
    decode,
)
from fleetmap.shared.io.recording import RecordingWriter
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from tests.bus_helpers import WAIT, Inbox, bus_pair, open_zenoh
from tests.protobuf_wire import Schema
from tests.shared.test_messages import FIELD_VALUES

KEYS = FleetKeys("t")
SECOND = 10**9
SEGMENTS = np.array([[0.0, 0.0, 3.0, 0.0], [3.0, 0.0, 3.0, 2.0], [3.0, 2.0, 0.5, 2.0]])


def fleet_traffic(robots: int = 3, scans: int = 20) -> list[tuple[str, bytes]]:
    """(key, payload) of a small session: scans, local maps, edges, a global map, poses, events."""
    out: list[tuple[str, bytes]] = []
    for i in range(scans):
        for r in range(robots):
            robot = f"r{r}"
            out.append((KEYS.scan(robot), Scan(robot, 0, i, float(i), SEGMENTS + r).to_msgpack()))
            if i % 5 == 4:
                local = LocalMap(robot, 0, i // 5, float(i), SEGMENTS + r, i + 1, Transform2D(0.1 * i, 0.0, 0.0))
                out.append((KEYS.localmap(robot), local.to_msgpack()))
    out.append((KEYS.edges, MergeEdge("r0/0", "r1/0", 1.0, 1.0, 0.0, 8.0, True, 20.0).to_msgpack()))
    poses = {"r0/0": Transform2D(), "r1/0": Transform2D(1.0, 1.0, 0.0)}
    component = Component("r0/0", ("r0/0", "r1/0"), poses, SEGMENTS)
    out.append((KEYS.globalmap, GlobalMap(1, 20.0, (component,)).to_msgpack()))
    out.append((KEYS.pose("r0"), RobotPose("r0", 0, 20.0, Transform2D(1.9, 0.0, 0.0), 0).to_msgpack()))
    out.append((KEYS.pose("r2"), RobotPose("r2", 0, 20.0, None, None).to_msgpack()))
    out.append((KEYS.events, FleetEvent("kidnap", "r2", 20.5, "scenario").to_msgpack()))
    return out


MALFORMED = [
    (KEYS.localmap("r0"), b"\x93not msgpack"),  # not msgpack at all
    (KEYS.localmap("r0"), Scan("r0", 0, 0, 0.0, SEGMENTS).to_msgpack()),  # a scan on a local map key
    (KEYS.scan("r1"), Scan("r2", 0, 0, 0.0, SEGMENTS).to_msgpack()),  # r2's scan on r1's key
    ("fleet/t/robots/r0/odom", Scan("r0", 0, 0, 0.0, SEGMENTS).to_msgpack()),  # a key fleetmap does not define
]


def record(fed: list[tuple[str, bytes]], **kwargs: object) -> tuple[io.BytesIO, Recorder]:
    stream = io.BytesIO()
    recorder = Recorder(RecordingWriter(stream), KEYS, **kwargs)  # type: ignore[arg-type]
    for i, (key, payload) in enumerate(fed):
        recorder.feed(key, payload, SECOND + i * 1000)
    recorder.finish()
    return stream, recorder


def test_every_message_fed_is_in_the_file_exactly_and_in_order():
    fed = fleet_traffic()
    stream, recorder = record(fed)
    reader = RecordingReader(io.BytesIO(stream.getvalue()))
    got = [(m.topic, m.payload) for m in reader.messages()]
    assert got == fed
    expected_counts = dict(Counter(key for key, _ in fed))
    summary = recorder.summary()
    assert summary.messages == expected_counts
    assert reader.topic_counts() == expected_counts
    assert summary.payload_bytes == {k: sum(len(p) for kk, p in fed if kk == k) for k in expected_counts}
    assert summary.total_malformed == 0


def test_publish_time_is_the_message_stamp_and_log_time_the_receive_time():
    fed = fleet_traffic(robots=1, scans=3)
    stream, _ = record(fed)
    messages = list(RecordingReader(io.BytesIO(stream.getvalue())).messages())
    first = messages[0]
    assert first.log_time == SECOND
    assert first.publish_time == int(decode(first.payload).stamp * 1e9)


def test_log_times_always_increase_even_when_receive_times_do_not():
    stream = io.BytesIO()
    recorder = Recorder(RecordingWriter(stream), KEYS)
    scan = Scan("r0", 0, 0, 0.0, SEGMENTS).to_msgpack()
    for t in (5 * SECOND, 4 * SECOND, 4 * SECOND, 6 * SECOND):  # two zenoh threads can race
        recorder.feed(KEYS.scan("r0"), scan, t)
    recorder.finish()
    times = [m.log_time for m in RecordingReader(io.BytesIO(stream.getvalue())).messages()]
    assert times == [5 * SECOND, 5 * SECOND + 1, 5 * SECOND + 2, 6 * SECOND]


def test_malformed_messages_are_recorded_raw_counted_and_not_drawn(caplog):
    fed = fleet_traffic(robots=2, scans=5)
    mixed = fed[:3] + MALFORMED + fed[3:]
    stream, recorder = record(mixed)
    summary = recorder.summary()
    assert summary.malformed == {KEYS.localmap("r0"): 2, KEYS.scan("r1"): 1, "fleet/t/robots/r0/odom": 1}
    assert summary.messages == dict(Counter(key for key, _ in mixed))
    raw = [(m.topic, m.payload) for m in RecordingReader(io.BytesIO(stream.getvalue())).messages()]
    assert raw == mixed
    # the views: one per valid scan and local map, none for the malformed ones
    views = Counter(
        channel.topic
        for _, channel, _ in make_reader(io.BytesIO(stream.getvalue())).iter_messages()
        if channel.message_encoding == "protobuf"
    )
    valid_scans_r1 = sum(1 for k, _ in fed if k == KEYS.scan("r1"))
    assert views["/foxglove/" + KEYS.scan("r1")] == valid_scans_r1
    assert views["/foxglove/fleet/t/robots/r0/odom"] == 0
    assert "a message of robot 'r2' on robot 'r1'" in caplog.text
    assert "fleetmap.Scan is not a message of a localmap key" in caplog.text


def test_presence_changes_are_recorded_as_fleet_events():
    stream = io.BytesIO()
    recorder = Recorder(RecordingWriter(stream), KEYS)
    recorder.feed_presence(KEYS.alive("r1"), True, 2 * SECOND)
    recorder.feed_presence(KEYS.service("merger"), True, 3 * SECOND)
    recorder.feed_presence(KEYS.alive("r1"), False, 4 * SECOND)
    recorder.finish()
    events = [(m.topic, decode(m.payload)) for m in RecordingReader(io.BytesIO(stream.getvalue())).messages()]
    assert [(t, e.kind, e.robot, e.stamp) for t, e in events] == [  # type: ignore[union-attr]
        (KEYS.alive("r1"), "join", "r1", 2.0),
        (KEYS.service("merger"), "join", None, 3.0),
        (KEYS.alive("r1"), "leave", "r1", 4.0),
    ]


def test_metadata_is_stored():
    stream = io.BytesIO()
    Recorder(RecordingWriter(stream), KEYS, metadata={"fleetmap.config": {"toml": "[merge]\n"}}).finish()
    assert RecordingReader(io.BytesIO(stream.getvalue())).metadata() == {"fleetmap.config": {"toml": "[merge]\n"}}


def test_a_message_is_on_disk_within_the_flush_interval_of_its_arrival():
    stream = io.BytesIO()
    recorder = Recorder(RecordingWriter(stream), KEYS, flush_interval=0.5)
    scan = Scan("r0", 0, 0, 0.0, SEGMENTS).to_msgpack()
    recorder.feed(KEYS.scan("r0"), scan, 10 * SECOND)

    def on_disk() -> int:
        """What a crash now would leave: the messages of the bytes written so far."""
        return len(list(RecordingReader(io.BytesIO(stream.getvalue())).messages()))

    assert not recorder.tick(10 * SECOND + SECOND // 4)
    assert on_disk() == 0
    assert recorder.tick(10 * SECOND + SECOND // 2)
    assert on_disk() == 1
    recorder.feed(KEYS.scan("r0"), scan, 11 * SECOND)
    recorder.feed(KEYS.scan("r0"), scan, 11 * SECOND + SECOND // 2)  # a busy bus flushes as it goes
    assert on_disk() == 3
    assert not recorder.tick(12 * SECOND)  # nothing new to flush


FIELDS = ["messages", "payload_bytes", "malformed", "foxglove_messages", "late", "lost", "error"]


def _stats_payload(fields: dict) -> bytes:  # type: ignore[type-arg]
    """A recorder stats answer with some fields replaced by anything."""
    whole = msgpack.unpackb(RecorderSummary({"a": 1}, {"a": 2}, {}, 0).to_msgpack())
    return msgpack.packb({**whole, **fields}, use_bin_type=True)


class FullDisk(io.BytesIO):
    """A file on a disk that fills up after ``room`` bytes: writes then fail with ENOSPC."""

    def __init__(self, room: int) -> None:
        super().__init__()
        self.room = room

    def write(self, data) -> int:  # type: ignore[no-untyped-def, override]
        if self.tell() + len(data) > self.room:
            raise OSError(28, "No space left on device")
        return super().write(data)


def test_a_full_disk_stops_the_recording_loudly_and_counts_only_what_the_file_holds(caplog):
    fed = fleet_traffic(robots=3, scans=40)
    stream = FullDisk(room=6000)
    recorder = Recorder(RecordingWriter(stream), KEYS, flush_interval=0.0)  # a flush after every message
    with caplog.at_level("ERROR"):
        for i, (key, payload) in enumerate(fed):
            recorder.feed(key, payload, SECOND + i * 1000)
        summary = recorder.finish()
    assert "No space left on device" in summary.error and "recording STOPPED" in caplog.text
    held = list(RecordingReader(io.BytesIO(stream.getvalue())).messages())
    assert 0 < len(held) < len(fed)
    # what the counts say was recorded is what the file holds; the rest is counted lost
    assert summary.total == len(held) and summary.total + summary.lost == len(fed)
    assert [(m.topic, m.payload) for m in held] == fed[: len(held)]
    assert sum(summary.payload_bytes.values()) == sum(len(m.payload) for m in held)
    assert "NOT RECORDED" in summary.table()
    # the maps it heard are still there for a restarted merger to recall
    newest = {}
    for key, payload in fed:
        if key.endswith("/localmap"):
            newest[key] = payload
    assert sorted(recorder.latest_maps()) == sorted(newest.values())


@pytest.mark.slow  # a fuzz test
@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=256) | st.dictionaries(st.sampled_from(FIELDS), FIELD_VALUES, max_size=8).map(_stats_payload))
def test_any_stats_answer_decodes_or_raises_bad_message(payload: bytes) -> None:
    try:
        summary = RecorderSummary.from_msgpack(payload)
    except BadMessage:
        return
    assert isinstance(summary.total, int) and isinstance(summary.table(), str)


@pytest.mark.parametrize("made_up_keys", [1, 12])
def test_a_robot_flooding_the_recorder_is_cut_to_its_rate_and_the_others_are_not(made_up_keys):
    # one key, or keys the robot made up under its own prefix (each had its own burst when the
    # rate was per key): the robot's flood is cut to one rate either way
    stream = io.BytesIO()
    recorder = Recorder(RecordingWriter(stream), KEYS, key_rate=1e5, key_burst=2e5, foxglove=False)
    junk = b"\x00" * 10_000
    legit = Scan("r2", 0, 0, 0.0, SEGMENTS).to_msgpack()
    flood_keys = [KEYS.scan("r1")] if made_up_keys == 1 else [f"{KEYS.prefix}/robots/r1/k{k}" for k in range(12)]
    for i in range(1000):  # 10 s of a 1 MB/s flood by r1, r2 scanning at 10 Hz beside it
        t = SECOND + i * SECOND // 100
        recorder.feed(flood_keys[i % len(flood_keys)], junk, t)
        if i % 10 == 0:
            recorder.feed(KEYS.scan("r2"), legit, t)
    summary = recorder.finish()
    flood = sum(summary.payload_bytes.get(k, 0) for k in flood_keys)
    assert flood <= 2e5 + 10 * 1e5 + len(junk)  # the burst plus the rate over 10 s
    assert summary.messages[KEYS.scan("r2")] == 100  # nothing of r2's is lost
    assert summary.throttled == 1000 - sum(summary.messages.get(k, 0) for k in flood_keys)
    assert "--max-key-rate" in summary.table()


def test_nothing_is_fed_after_finish():
    _, recorder = record(fleet_traffic(robots=1, scans=1))
    recorder.feed(KEYS.scan("r0"), b"late", 99 * SECOND)
    assert recorder.summary().late == 1


def test_summary_table_lists_every_topic():
    _, recorder = record(fleet_traffic(robots=2, scans=5) + MALFORMED[:1])
    table = recorder.summary().table()
    assert KEYS.scan("r1") in table and KEYS.globalmap in table
    assert table.splitlines()[-1].split()[:2] == ["total", str(recorder.summary().total)]


# --- on a bus ---


class NotifyingRecorder(Recorder):
    """A Recorder that tells the test what it has recorded (so it can wait for it, bounded)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.seen = Inbox()

    def feed(self, key: str, payload: bytes, receive_time_ns: int) -> None:
        super().feed(key, payload, receive_time_ns)
        self.seen(key)

    def feed_presence(self, key: str, joined: bool, receive_time_ns: int) -> None:
        super().feed_presence(key, joined, receive_time_ns)
        self.seen(key)


def run_session(recorder_bus: Bus, robot_bus: Bus) -> tuple[io.BytesIO, list[tuple[str, bytes]], NotifyingRecorder]:
    stream = io.BytesIO()
    recorder = NotifyingRecorder(RecordingWriter(stream), KEYS)
    fed = fleet_traffic() + MALFORMED
    ready = Inbox()
    robot_bus.subscribe_liveliness(KEYS.service("recorder"), ready, lambda key: None)
    with RecorderService(recorder_bus, recorder, KEYS):
        assert ready.wait_for(1), "the recorder's token says it is recording"
        token = robot_bus.declare_liveliness(KEYS.alive("r0"))
        for key, payload in fed:
            robot_bus.publish(key, payload)
        token.close()
        # everything published, two presence changes of r0, and the recorder's own join
        assert recorder.seen.wait_for(len(fed) + 3)
    return stream, fed, recorder


@pytest.fixture(params=["zenoh", "memory"])
def buses(request: pytest.FixtureRequest) -> Iterator[tuple[Bus, Bus]]:
    with bus_pair(request.param) as pair:
        yield pair


def test_the_service_answers_what_it_has_recorded(buses):
    recorder_bus, robot_bus = buses
    recorder = Recorder(RecordingWriter(io.BytesIO()), KEYS)
    with RecorderService(recorder_bus, recorder, KEYS):
        fed = fleet_traffic(robots=2, scans=5)
        ready = Inbox()
        robot_bus.subscribe_liveliness(KEYS.service("recorder"), ready, lambda key: None)
        assert ready.wait_for(1)
        for key, payload in fed:
            robot_bus.publish(key, payload)
        assert wait_until_recorded(robot_bus, KEYS, Counter(key for key, _ in fed), WAIT)
        stats = query_recorder_stats(robot_bus, KEYS)
        assert stats is not None and stats.total >= len(fed)
    assert query_recorder_stats(robot_bus, KEYS, timeout=0.2) is None  # stopped: nobody answers


def test_stats_round_trip():
    _, recorder = record(fleet_traffic(robots=1, scans=2) + MALFORMED[:1])
    summary = recorder.summary()
    assert RecorderSummary.from_msgpack(summary.to_msgpack()) == summary


def test_the_service_records_what_is_published_and_who_comes_and_goes(buses):
    recorder_bus, robot_bus = buses
    stream, fed, recorder = run_session(recorder_bus, robot_bus)
    reader = RecordingReader(io.BytesIO(stream.getvalue()))
    assert reader.complete
    raw = [(m.topic, m.payload) for m in reader.messages()]
    assert [r for r in raw if not r[0].startswith(("fleet/t/alive/", "fleet/t/services/"))] == fed
    presence = [(t, decode(p).kind) for t, p in raw if t == KEYS.alive("r0")]  # type: ignore[union-attr]
    assert presence == [(KEYS.alive("r0"), "join"), (KEYS.alive("r0"), "leave")]
    assert recorder.summary().total_malformed == len(MALFORMED)


# --- the fleetmap record process (slow) ---


def start_record(out: Path, endpoint: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "fleetmap", "record", "--out", str(out), "--listen", endpoint, "--fleet", "t"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def publish_to_recorder(endpoint: str, fed: list[tuple[str, bytes]]) -> None:
    """Publish once the recorder is up, and return once it says it has recorded everything."""
    with open_zenoh(ZenohOptions(connect=(endpoint,), fleet="t")) as bus:
        ready = threading.Event()
        bus.subscribe_liveliness(KEYS.service("recorder"), lambda key: ready.set(), lambda key: None)
        assert ready.wait(15.0), "fleetmap record did not come up"
        for key, payload in fed:
            bus.publish(key, payload)
        assert wait_until_recorded(bus, KEYS, Counter(key for key, _ in fed), WAIT)


def record_until_sigterm(out: Path, fed: list[tuple[str, bytes]]) -> str:
    """``fleetmap record --out OUT`` until it has recorded ``fed``, then SIGTERM: its stdout (it
    must exit 0)."""
    endpoint = free_loopback_endpoint()
    process = start_record(out, endpoint)
    try:
        publish_to_recorder(endpoint, fed)
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=WAIT)
    finally:
        process.kill()
    assert process.returncode == 0, stderr
    return stdout


@pytest.mark.slow
def test_fleetmap_record_stops_on_sigterm_with_a_complete_file_and_a_summary(tmp_path):
    out = tmp_path / "session.mcap"
    fed = fleet_traffic() + MALFORMED
    stdout = record_until_sigterm(out, fed)
    reader = RecordingReader(out)
    assert reader.complete
    counts = reader.topic_counts()
    for key, n in Counter(key for key, _ in fed).items():
        assert counts[key] == n
        assert f"{key} " in stdout
    assert f"{len(MALFORMED)} malformed messages" in stdout
    assert reader.metadata()["fleetmap.session"]["fleet"] == "t"
    assert "toml" in reader.metadata()["fleetmap.config"]


@pytest.mark.slow
def test_a_killed_recorder_leaves_a_file_with_everything_but_its_last_second(tmp_path):
    out, endpoint = tmp_path / "session.mcap", free_loopback_endpoint()
    process = start_record(out, endpoint)
    try:
        fed = fleet_traffic()
        publish_to_recorder(endpoint, fed)
        threading.Event().wait(1.0)  # the guarantee under test: what was recorded a second ago is on disk
        process.send_signal(signal.SIGKILL)
        process.wait(WAIT)
    finally:
        process.kill()
    reader = RecordingReader(out)
    assert not reader.complete
    messages = [(m.topic, m.payload) for m in reader.messages()]
    assert [m for m in messages if not m[0].startswith(("fleet/t/alive/", "fleet/t/services/"))] == fed
    assert reader.report.warning is not None


@pytest.mark.slow
def test_a_recorder_restarted_twice_leaves_three_readable_files(tmp_path):
    # what docker's restart: unless-stopped does to a recorder that dies: every start gets a file of
    # its own beside the last, and each holds what was published while it ran
    out = tmp_path / "session.mcap"
    feeds = [fleet_traffic(robots=1, scans=k + 1) for k in range(3)]
    for fed in feeds:
        record_until_sigterm(out, fed)
    files = [out, tmp_path / "session-1.mcap", tmp_path / "session-2.mcap"]
    assert sorted(tmp_path.iterdir()) == sorted(files)
    for path, fed in zip(files, feeds, strict=True):
        reader = RecordingReader(path)
        assert reader.complete
        messages = [(m.topic, m.payload) for m in reader.messages()]
        assert [m for m in messages if not m[0].startswith(("fleet/t/alive/", "fleet/t/services/"))] == fed


def test_the_foxglove_views_are_on_the_recordings_clock_and_the_raw_channel_keeps_the_stamp():
    # a simulated robot stamps from 0 (1970 to Foxglove), the recording's log times are wall clock:
    # a view stamped with its message's stamp would never meet its frames on Foxglove's timeline
    stream = io.BytesIO()
    recorder = Recorder(RecordingWriter(stream), KEYS)
    wall = 1_764_000_000 * SECOND  # November 2025
    for i, (key, payload) in enumerate(fleet_traffic(robots=1, scans=2)):
        recorder.feed(key, payload, wall + i * 1000)
    recorder.finish()
    seen = 0
    for schema, channel, message in make_reader(io.BytesIO(stream.getvalue())).iter_messages():
        if channel.message_encoding == "protobuf":
            assert message.publish_time == message.log_time
            decoded = Schema(schema.data).decode(schema.name, message.data)
            stamps = [decoded.get("timestamp")] + [e.get("timestamp") for e in decoded.get("entities", [])]
            for ts in filter(None, stamps):
                assert abs(ts.get("seconds", 0) * 10**9 + ts.get("nanos", 0) - message.log_time) < 1000  # 1 us
                seen += 1
        elif channel.topic.endswith("/scan"):
            assert message.publish_time < wall // 2  # the scan's own stamp, seconds after 1970
    assert seen > 5
