"""The live view: the fleet as it maps, served over the Foxglove WebSocket protocol.

:class:`LiveView` is the library call: feed it ``(key, payload, receive_time_ns)`` and presence
changes as the recorder is fed (:func:`~fleetmap.merger.recorder.checked_message`,
:func:`~fleetmap.merger.recorder.presence_event`), and it hands the same Foxglove views a
recording holds (:class:`~fleetmap.shared.io.foxglove_scene.FoxgloveScene`: scans, laser scans, submaps,
the global map, robot paths, fleet events, one TF tree) to a sink, stamped with their receive
time; :meth:`LiveView.tick` adds the occupancy grid of the largest component, which a recording
writes only at its end, at most every ``grid_period`` seconds after a global map changed it. It
needs no network.

:class:`FoxgloveServer` is the sink of a live session: a ``foxglove-sdk`` WebSocket server on its
own :class:`foxglove.Context`, one channel per topic, with the schema the recording gives it. A
client that subscribes to a channel gets its latest message again (except ``/tf``, whose frames
come again with every scan and global map), so Foxglove opened in the middle of a session shows
the map at once. :class:`ViewService` runs both on a bus: it subscribes to ``fleet/<fleet>/**``
and to liveliness under the fleet, as the recorder does, and ticks on a timer.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Protocol

import foxglove
from fleetmap.merger.listener import FleetListener
from fleetmap.merger.recorder import LOGGED_MALFORMED, checked_message, presence_event
from fleetmap.shared.io.bus import Bus
from fleetmap.shared.io.foxglove_scene import TF_TOPIC, FoxgloveScene, FoxgloveView
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import GlobalMap
from foxglove.websocket import ChannelView, Client, ServerListener, WebSocketServer

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's own default for a WebSocket connection."""
GRID_PERIOD = 2.0
"""Seconds between two occupancy grids of a live view (a long session's grid takes a few seconds
to cast from all its beams; the global map changes every few seconds)."""
TICK_PERIOD = 0.1
"""How often the service looks for a grid due and for clients to catch up (s)."""


class ViewSink(Protocol):
    """Where a live view's Foxglove messages go."""

    def publish(self, view: FoxgloveView, log_time_ns: int) -> None: ...


class LiveView:
    """The Foxglove views of what the fleet publishes, as it publishes it; thread-safe, clock given
    by the caller (module docstring)."""

    def __init__(self, sink: ViewSink, keys: FleetKeys, *, grid_period: float = GRID_PERIOD) -> None:
        self._sink = sink
        self._keys = keys
        self._grid_period_ns = int(grid_period * 1e9)
        self._scene = FoxgloveScene()
        self._lock = threading.Lock()
        self._grid_due = False
        self._last_grid_ns: int | None = None
        self.published: Counter[str] = Counter()
        """Messages handed to the sink, by schema name."""
        self.malformed = 0

    def feed(self, key: str, payload: bytes, receive_time_ns: int) -> None:
        """View one payload received on ``key``; a malformed one is counted and logged, never raised."""
        message, problem = checked_message(self._keys, key, payload)
        if message is None:
            with self._lock:
                self.malformed += 1
                n = self.malformed
            if n <= LOGGED_MALFORMED or n % 1000 == 0:
                log.warning("malformed message on %s (not shown, %d so far): %s", key, n, problem)
            return
        with self._lock:
            self._publish(self._scene.views(message, key, receive_time_ns * 1e-9), receive_time_ns)
            if isinstance(message, GlobalMap):
                self._grid_due = True

    def feed_presence(self, key: str, joined: bool, receive_time_ns: int) -> None:
        """A liveliness token appearing (``joined``) or disappearing, shown as a fleet event."""
        event = presence_event(self._keys, key, joined, receive_time_ns)
        with self._lock:
            self._publish(self._scene.views(event, self._keys.events, receive_time_ns * 1e-9), receive_time_ns)

    def tick(self, now_ns: int) -> bool:
        """Publish the occupancy grid if a global map changed it and the last one is ``grid_period``
        old; whether it did."""
        with self._lock:
            if not self._grid_due:
                return False
            if self._last_grid_ns is not None and now_ns - self._last_grid_ns < self._grid_period_ns:
                return False
            self._grid_due = False
            self._last_grid_ns = now_ns
            views = self._scene.grid_views(now_ns * 1e-9)
            self._publish(views, now_ns)
            return bool(views)

    def _publish(self, views: list[FoxgloveView], log_time_ns: int) -> None:
        for view in views:
            self._sink.publish(view, log_time_ns)
            self.published[view.schema.name] += 1


class FoxgloveServer(ServerListener):
    """A ``foxglove-sdk`` WebSocket server that publishes live views (module docstring). Call
    :meth:`catch_up` now and then: it sends the latest message of each channel a client has just
    subscribed to (not from the server's own callback, which must not block)."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, name: str = "fleetmap") -> None:
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._latest: dict[str, tuple[bytes, int]] = {}
        self._subscribed: set[str] = set()
        self._lock = threading.Lock()
        self.server: WebSocketServer = foxglove.start_server(
            name=name, host=host, port=port, context=self._context, server_listener=self
        )

    @property
    def port(self) -> int:
        return self.server.port

    def publish(self, view: FoxgloveView, log_time_ns: int) -> None:
        with self._lock:
            channel = self._channels.get(view.topic)
            if channel is None:
                channel = foxglove.Channel(
                    view.topic, schema=view.schema, message_encoding=view.schema.encoding, context=self._context
                )
                self._channels[view.topic] = channel
            if view.topic != TF_TOPIC:
                self._latest[view.topic] = (view.data, log_time_ns)
        channel.log(view.data, log_time=log_time_ns)

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self._lock:
            self._subscribed.add(channel.topic)

    def catch_up(self) -> None:
        """Send again the latest message of every channel subscribed to since the last call."""
        with self._lock:
            due = [(self._channels[t], *self._latest[t]) for t in self._subscribed if t in self._latest]
            self._subscribed.clear()
        for channel, data, log_time_ns in due:
            channel.log(data, log_time=log_time_ns)

    def stop(self) -> None:
        self.server.stop()


class ViewService(FleetListener):
    """A LiveView on a bus, serving a FoxgloveServer: ``with ViewService(bus, view, server, keys): ...``."""

    def __init__(
        self,
        bus: Bus,
        view: LiveView,
        server: FoxgloveServer,
        keys: FleetKeys,
        *,
        clock: Callable[[], int] = time.time_ns,
        tick_period: float = TICK_PERIOD,
    ) -> None:
        super().__init__(bus, view, keys, clock=clock, tick_period=tick_period, name="view-tick")
        self.view = view
        self.server = server

    def start(self) -> None:
        super().start()
        log.info("viewing %s on ws port %d", self.keys.everything, self.server.port)

    def tick(self) -> None:
        try:
            self.view.tick(self._clock())
            self.server.catch_up()
        except Exception:  # a view that cannot be drawn must not stop the others
            log.exception("live view tick failed")
