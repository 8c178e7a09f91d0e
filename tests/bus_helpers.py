"""Helpers for tests over a bus: collecting what callbacks receive, and waiting for it (bounded)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from fleetmap.shared.io.bus import Bus, BusError
from fleetmap.shared.io.memory_bus import InMemoryBus
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint, zenoh_config

WAIT = 5.0
"""The longest any test waits for something the bus should deliver (s); it normally takes ms."""


def eventually(predicate: Callable[[], bool], timeout: float) -> bool:
    """Whether ``predicate`` holds within ``timeout`` seconds (asked every 50 ms)."""
    pause = threading.Event()
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.05)
    return True


class Inbox:
    """A callback that keeps its calls' arguments and lets a test wait for them."""

    def __init__(self) -> None:
        self.items: list[tuple[object, ...]] = []
        self._cond = threading.Condition()

    def __call__(self, *args: object) -> None:
        with self._cond:
            self.items.append(args)
            self._cond.notify_all()

    def wait_for(self, n: int, timeout: float = WAIT) -> bool:
        """Whether at least n calls arrived within ``timeout`` seconds."""
        with self._cond:
            return self._cond.wait_for(lambda: len(self.items) >= n, timeout)

    def wait_until(self, predicate: Callable[[list[tuple[object, ...]]], bool], timeout: float = WAIT) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self.items), timeout)


def sync_declarations(declarer: Bus, observer: Bus, name: str = "sync") -> None:
    """Return once ``observer`` has seen everything ``declarer`` declared so far.

    Declarations travel in order on a link, so when a liveliness token declared now reaches the
    observer, the queryables and subscribers declared before it have too.
    """
    seen = threading.Event()
    key = f"fleet/sync/services/{name}"
    watch = observer.subscribe_liveliness(key, lambda _: seen.set(), lambda _: None)
    token = declarer.declare_liveliness(key)
    try:
        if not seen.wait(WAIT):
            raise AssertionError(f"declarations did not propagate within {WAIT} s")
    finally:
        token.close()
        watch.close()


def open_zenoh(options: ZenohOptions) -> ZenohBus:
    """A session as the services open it, minus zenoh's scouting delay: a peer that connects may
    otherwise spend 0.5 s in ``zenoh.open`` looking for more peers, which adds up over a test run."""
    config = zenoh_config(options)
    config.insert_json5("scouting/delay", "0")
    return ZenohBus.open(config)


def open_zenoh_pair(fleet: str = "t") -> tuple[ZenohBus, ZenohBus]:
    """Two sessions on loopback: the first listens on a free port, the second connects to it."""
    endpoint = free_loopback_endpoint()
    listener = open_zenoh(ZenohOptions(listen=(endpoint,), fleet=fleet))
    try:
        return listener, open_zenoh(ZenohOptions(connect=(endpoint,), fleet=fleet))
    except BusError:
        listener.close()
        raise


@contextmanager
def bus_pair(kind: str) -> Iterator[tuple[Bus, Bus]]:
    """Two buses that see each other, closed afterwards: ``zenoh`` sessions on loopback, or
    ``memory`` peers."""
    if kind == "zenoh":
        a, b = open_zenoh_pair()
    else:
        a = InMemoryBus()
        b = a.peer()
    with a, b:
        yield a, b
