"""The live view as a library call: a recording's Foxglove channels, live, and the grid now and then."""

from __future__ import annotations

import io

from fleetmap.merger.view import LiveView
from fleetmap.shared.io.foxglove_scene import FoxgloveView
from mcap.reader import make_reader

from tests.merger.test_recorder import KEYS, MALFORMED, SECOND, fleet_traffic, record
from tests.protobuf_wire import Schema


class Sink:
    def __init__(self) -> None:
        self.views: list[tuple[FoxgloveView, int]] = []

    def publish(self, view: FoxgloveView, log_time_ns: int) -> None:
        self.views.append((view, log_time_ns))

    def channels(self) -> set[tuple[str, str]]:
        return {(v.topic, v.schema.name) for v, _ in self.views}


def test_the_view_shows_the_channels_of_a_recording_typed_as_it_types_them() -> None:
    fed = fleet_traffic()
    sink = Sink()
    view = LiveView(sink, KEYS)
    for i, (key, payload) in enumerate(fed):
        view.feed(key, payload, SECOND + i * 1000)
    assert view.tick(2 * SECOND)  # the occupancy grid, which a recording holds once it is finished
    stream, _ = record(fed)
    recorded = set()
    for schema, channel, message in make_reader(io.BytesIO(stream.getvalue())).iter_messages():
        if channel.message_encoding == "protobuf":
            assert schema is not None
            recorded.add((channel.topic, schema.name))
            Schema(schema.data).decode(schema.name, message.data)
    assert sink.channels() == recorded
    assert ("/foxglove/fleet/t/grid", "foxglove.Grid") in recorded
    # each view decodes with its schema, stamped with the time it was received
    for v, t in sink.views:
        Schema(v.schema.data).decode(v.schema.name, v.data)
        assert SECOND <= t <= 2 * SECOND


def test_the_grid_is_drawn_after_a_global_map_at_most_every_grid_period() -> None:
    fed = fleet_traffic()
    sink = Sink()
    view = LiveView(sink, KEYS, grid_period=2.0)
    assert not view.tick(SECOND)  # no global map yet: nothing to draw
    for key, payload in fed:
        view.feed(key, payload, SECOND)
    assert view.tick(SECOND)
    assert not view.tick(SECOND + SECOND // 10)  # the map has not changed since
    globalmap = [(k, p) for k, p in fed if k == KEYS.globalmap]
    view.feed(*globalmap[0], 2 * SECOND)
    assert not view.tick(2 * SECOND)  # changed, but the last grid is 1 s old
    assert view.tick(3 * SECOND)
    assert view.published["foxglove.Grid"] == 2


def test_malformed_messages_are_counted_and_not_shown_and_presence_is_a_fleet_event() -> None:
    sink = Sink()
    view = LiveView(sink, KEYS)
    for key, payload in MALFORMED:
        view.feed(key, payload, SECOND)
    assert view.malformed == len(MALFORMED) and not sink.views
    view.feed_presence(KEYS.alive("r1"), True, 2 * SECOND)
    ((shown, t),) = sink.views
    log = Schema(shown.schema.data).decode("foxglove.Log", shown.data)
    assert shown.topic == "/foxglove/" + KEYS.events and t == 2 * SECOND and "join r1" in log["message"]
