"""A bus inside one process, for fast unit tests of service logic.

Delivery is synchronous, in the publisher's thread, in publication order; key expressions match as
zenoh matches them. Buses made by :meth:`InMemoryBus.peer` share one network, each as another
"process" would: closing one makes its liveliness tokens leave. The real transport is
:class:`~fleetmap.shared.io.zenoh_bus.ZenohBus`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh
from fleetmap.shared.io.bus import (
    FLUSH_TIMEOUT,
    BusBase,
    BusStats,
    Callback,
    CallbackGuard,
    Handle,
    PresenceCallback,
    QueryHandler,
    check_keyexpr,
    replies,
)

log = logging.getLogger(__name__)


@dataclass
class _Hub:
    """What the in-memory buses of one test share: subscriptions, queryables, tokens."""

    lock: threading.RLock = field(default_factory=threading.RLock)
    subscriptions: dict[int, tuple[InMemoryBus, str, Callback]] = field(default_factory=dict)
    queryables: dict[int, tuple[InMemoryBus, str, QueryHandler]] = field(default_factory=dict)
    tokens: dict[int, tuple[InMemoryBus, str]] = field(default_factory=dict)
    presence: dict[int, tuple[InMemoryBus, str, PresenceCallback, PresenceCallback]] = field(default_factory=dict)
    next_id: int = 0

    def new_id(self) -> int:
        self.next_id += 1
        return self.next_id


def _intersects(keyexpr: str, key: str) -> bool:
    return bool(zenoh.KeyExpr(keyexpr).intersects(key))


class _MemoryHandle:
    def __init__(self, close: Callable[[], object]) -> None:
        self._close = close
        self._closed = False

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close()


class InMemoryBus(BusBase):
    """A bus inside one process, for fast unit tests of service logic: delivery is synchronous,
    in the publisher's thread, in publication order. ``peer()`` gives another bus on the same
    network (another "process"): closing it makes its liveliness tokens leave."""

    def __init__(self, hub: _Hub | None = None) -> None:
        self._hub = hub if hub is not None else _Hub()
        self.stats = BusStats()
        self._lock = threading.Lock()
        self._guard = CallbackGuard(self.stats, self._lock)
        self._closed = False

    def peer(self) -> InMemoryBus:
        return InMemoryBus(self._hub)

    def publish(self, key: str, payload: bytes) -> None:
        self._check_open()
        check_keyexpr(key, "key")
        with self._hub.lock:
            targets = [(bus, cb) for bus, expr, cb in self._hub.subscriptions.values() if _intersects(expr, key)]
        self.stats.published += 1
        for bus, callback in targets:
            bus.stats.received += 1
            bus._guard.run(f"subscriber on {key}", callback, key, bytes(payload))

    def subscribe(self, keyexpr: str, callback: Callback) -> Handle:
        self._check_open()
        check_keyexpr(keyexpr)
        with self._hub.lock:
            sid = self._hub.new_id()
            self._hub.subscriptions[sid] = (self, keyexpr, callback)
        return _MemoryHandle(lambda: self._hub.subscriptions.pop(sid, None))

    def declare_queryable(self, key: str, handler: QueryHandler) -> Handle:
        self._check_open()
        check_keyexpr(key, "key")
        with self._hub.lock:
            qid = self._hub.new_id()
            self._hub.queryables[qid] = (self, key, handler)
        return _MemoryHandle(lambda: self._hub.queryables.pop(qid, None))

    def query(self, selector: str, timeout: float = 2.0) -> list[bytes]:
        self._check_open()
        keyexpr = check_keyexpr(selector.split("?", 1)[0], "selector")
        with self._hub.lock:
            targets = [(bus, h) for bus, key, h in self._hub.queryables.values() if _intersects(keyexpr, key)]
        self.stats.queries += 1
        out = []
        for bus, handler in targets:
            try:
                out += replies(handler(selector))
            except Exception:  # as over zenoh: a failing handler is an error reply, not an exception here
                bus.stats.callback_errors += 1
                self.stats.query_errors += 1
                log.exception("queryable failed on %s", selector)
        return out

    def declare_liveliness(self, key: str) -> Handle:
        self._check_open()
        check_keyexpr(key, "key")
        with self._hub.lock:
            tid = self._hub.new_id()
            self._hub.tokens[tid] = (self, key)
            watchers = [(b, j) for b, expr, j, _ in self._hub.presence.values() if _intersects(expr, key)]
        for bus, on_join in watchers:
            bus._guard.run(f"liveliness join {key}", on_join, key)

        def leave() -> None:
            with self._hub.lock:
                if self._hub.tokens.pop(tid, None) is None:
                    return
                watchers = [(b, g) for b, expr, _, g in self._hub.presence.values() if _intersects(expr, key)]
            for bus, on_leave in watchers:
                bus._guard.run(f"liveliness leave {key}", on_leave, key)

        return _MemoryHandle(leave)

    def subscribe_liveliness(
        self, keyexpr: str, on_join: PresenceCallback, on_leave: PresenceCallback, history: bool = True
    ) -> Handle:
        self._check_open()
        check_keyexpr(keyexpr)
        with self._hub.lock:
            pid = self._hub.new_id()
            self._hub.presence[pid] = (self, keyexpr, on_join, on_leave)
            present = [key for _, key in self._hub.tokens.values() if _intersects(keyexpr, key)] if history else []
        for key in present:
            self._guard.run(f"liveliness join {key}", on_join, key)
        return _MemoryHandle(lambda: self._hub.presence.pop(pid, None))

    def flush(self, timeout: float = FLUSH_TIMEOUT) -> bool:
        self._check_open()
        return True  # delivery is synchronous: nothing is ever in flight

    def wait_for_subscribers(self, key: str, timeout: float) -> bool:
        self._check_open()
        with self._hub.lock:
            return any(_intersects(expr, key) for _, expr, _ in self._hub.subscriptions.values())

    def close(self) -> None:
        if self._closed:
            return
        with self._hub.lock:
            mine = [(tid, key) for tid, (bus, key) in self._hub.tokens.items() if bus is self]
            for table in (self._hub.subscriptions, self._hub.queryables, self._hub.presence):
                for entry_id in [i for i, entry in table.items() if entry[0] is self]:
                    del table[entry_id]
            for tid, _ in mine:
                del self._hub.tokens[tid]
            watchers = [(b, expr, g) for b, expr, _, g in self._hub.presence.values()]
        self._closed = True
        for key in [k for _, k in mine]:
            for bus, expr, on_leave in watchers:
                if _intersects(expr, key):
                    bus._guard.run(f"liveliness leave {key}", on_leave, key)
