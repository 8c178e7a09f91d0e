"""What the recorder and the live view share on the bus: every message and every presence of the
fleet fed to a sink, and the sink ticked on a thread of its own."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Protocol, Self

from fleetmap.shared.io.bus import Bus, Handle
from fleetmap.shared.io.keys import FleetKeys


class FleetSink(Protocol):
    def feed(self, key: str, payload: bytes, now_ns: int) -> None: ...

    def feed_presence(self, key: str, alive: bool, now_ns: int) -> None: ...


class FleetListener:
    """Feeds a sink everything on the fleet's keys (samples, and liveliness as presence, the tokens
    already there included) and calls :meth:`tick` every ``tick_period`` seconds until stopped.
    ``with listener: ...`` starts and stops it."""

    def __init__(
        self,
        bus: Bus,
        sink: FleetSink,
        keys: FleetKeys,
        *,
        clock: Callable[[], int] = time.time_ns,
        tick_period: float,
        name: str,
    ) -> None:
        self.bus = bus
        self.keys = keys
        self._sink = sink
        self._clock = clock
        self._tick_period = tick_period
        self._handles: list[Handle] = []
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick_loop, name=name, daemon=True)

    def start(self) -> None:
        self._handles.append(self.bus.subscribe(self.keys.everything, self._on_sample))
        self._handles.append(
            self.bus.subscribe_liveliness(
                self.keys.everything,
                lambda key: self._sink.feed_presence(key, True, self._clock()),
                lambda key: self._sink.feed_presence(key, False, self._clock()),
                history=True,
            )
        )
        self._ticker.start()

    def tick(self) -> None:
        """What the ticker does every period (nothing here)."""

    def _on_sample(self, key: str, payload: bytes) -> None:
        self._sink.feed(key, payload, self._clock())

    def _tick_loop(self) -> None:
        while not self._stop.wait(self._tick_period):
            self.tick()

    def stop_listening(self) -> None:
        """Unsubscribe (and close what was added to the handles) and stop the ticker."""
        for handle in reversed(self._handles):
            handle.close()
        self._handles.clear()
        self._stop.set()
        if self._ticker.is_alive():
            self._ticker.join()

    def stop(self) -> object:
        self.stop_listening()
        return None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
