"""Replaying a recorded session through a fresh merger (fleetmap.replay), without processes."""

from __future__ import annotations

from pathlib import Path

import pytest
from fleetmap.merger.engine import Merger, Outgoing
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import FleetEvent, LocalMap
from fleetmap.shared.io.recording import RecordingWriter

from fleetmap.replay import replay
from tests.helpers import true_local_map

KEYS = FleetKeys("t")


@pytest.mark.slow  # a whole session merged, restored and replayed: run in CI, deselected by -m "not slow"
def test_a_restarted_mergers_repeated_step_is_replayed_once(tmp_path: Path) -> None:
    # A live session: two robots' maps, a step; r2's map grows and r1 starts an epoch, a step
    # that stops short (pairs still queued); the merger is killed and restored from its state,
    # says where it stands (its last step again, the same bytes), and takes the rest.
    small = [true_local_map("department", r, 0, 8)[0] for r in ("r1", "r2")]
    grown = true_local_map("department", "r2", 0, 16, version=1)[0]
    lost = LocalMap("r1", 1, 0, 99.0, grown.segments, 15, grown.pose)
    merger = Merger(KEYS)
    bus: list[Outgoing] = []

    def publish(m: LocalMap) -> None:
        bus.append(Outgoing(KEYS.localmap(m.robot), m.to_msgpack()))
        merger.receive(KEYS.localmap(m.robot), m.to_msgpack())

    for m in small:
        publish(m)
    bus += merger.step()
    for m in (grown, lost):
        publish(m)
    bus += merger.step(limit=1)
    merger.save_state(tmp_path / "merger.state")
    restored = Merger(KEYS)
    restored.load_state(tmp_path / "merger.state")
    bus += restored.where_it_stands()
    while restored.has_work:
        bus += restored.step()
    path = tmp_path / "session.mcap"
    writer = RecordingWriter(path)
    writer.add_metadata("fleetmap.session", {"fleet": "t"})
    for n, o in enumerate(bus):
        writer.write_raw(o.key, o.payload, 10**9 + n * 10**6, 10**9 + n * 10**6)
    writer.finish()

    result = replay(path, tmp_path / "replay")
    # Each map version fed once, every step followed once, and the live global map rebuilt.
    assert result.inputs == ["r1/0/0@0", "r2/0/0@0", "r2/0/0@1", "r1/1/0@0"]
    assert result.exact and result.report["replay"]["matches_live"] is True
    assert result.steps == restored.stats.steps + merger.stats.steps


def _record(path: Path, bus: list[Outgoing]) -> None:
    writer = RecordingWriter(path)
    writer.add_metadata("fleetmap.session", {"fleet": "t"})
    for n, o in enumerate(bus):
        writer.write_raw(o.key, o.payload, 10**9 + n * 10**6, 10**9 + n * 10**6)
    writer.finish()


@pytest.mark.slow  # up to nine submaps merged, restarted and replayed: about 5 s in all
@pytest.mark.parametrize("resumed", [True, False], ids=["from its state", "afresh"])
def test_a_session_whose_merger_restarted_replays_to_the_live_map(tmp_path: Path, resumed: bool) -> None:
    # The live merger takes three robots' first submaps one integration a step (pairs left queued,
    # each robot's turn noted), saves its state and stops. The new one resumes from that state, or
    # starts empty, says where it stands, asks for the robots' maps and takes the rest. The replay
    # restarts its merger at the same step, in the same way: a resumed merger's schedule is what the
    # state file kept (not whose turn it was), and an empty one has none of the maps before.
    robots = ("r1", "r2", "r3")
    epochs, before = (3, 5) if resumed else (2, 3)
    maps = [true_local_map("department", r, 8 * e, 8 * e + 10, epoch=e)[0] for e in range(epochs) for r in robots]
    bus: list[Outgoing] = []

    def event(kind: str) -> None:
        bus.append(Outgoing(KEYS.events, FleetEvent(kind, None, 1.0).to_msgpack()))

    def publish(merger: Merger, m: LocalMap) -> None:
        bus.append(Outgoing(KEYS.localmap(m.robot), m.to_msgpack()))
        merger.receive(KEYS.localmap(m.robot), m.to_msgpack())

    live = Merger(KEYS)
    event("merger_start")
    event("republish_request")
    for m in maps[:before]:
        publish(live, m)
        bus.extend(live.step(limit=1, now=len(bus)))
    live.save_state(tmp_path / "merger.state")
    event("merger_stop")
    again = Merger(KEYS)
    if resumed:
        again.load_state(tmp_path / "merger.state")
    event("merger_start")
    bus.extend(again.where_it_stands())
    event("republish_request")
    for m in maps if not resumed else maps[before:]:
        publish(again, m)
        bus.extend(again.step(limit=1, now=len(bus)))
    while again.has_work:
        bus.extend(again.step(limit=1, now=len(bus)))
    _record(tmp_path / "session.mcap", bus)

    result = replay(tmp_path / "session.mcap", tmp_path / "replay")
    assert result.exact and result.report["replay"]["merger_restarts"] == 1
    assert result.report["replay"]["matches_live"] is True, "the replay DIFFERS from the live map"
    assert result.steps == live.stats.steps + again.stats.steps
