"""The transport seam: the small bus interface services talk to, and what its implementations share.

Services talk to a :class:`Bus` (publish, subscribe, query, liveliness) and never to zenoh
directly, so their logic can be driven by :class:`~fleetmap.shared.io.memory_bus.InMemoryBus` in a
unit test; the real thing is :class:`~fleetmap.shared.io.zenoh_bus.ZenohBus`, and the
multi-process tests run it on loopback.

Payloads are bytes (fleetmap messages, :mod:`fleetmap.shared.io.messages`); keys come from
:mod:`fleetmap.shared.io.keys`. Callbacks run on the bus's threads (a thread per zenoh subscription,
in arrival order, so a slow one never holds zenoh's receiving thread; zenoh's for liveliness and
queries; the publisher's for the in-memory bus); one that raises is logged and counted in
:attr:`BusStats.callback_errors` and never reaches the transport (:class:`CallbackGuard`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, Self

import zenoh
from fleetmap.shared.errors import BadInput, FleetmapError

log = logging.getLogger(__name__)

Callback = Callable[[str, bytes], None]
"""``callback(key, payload)`` for a subscription."""
QueryHandler = Callable[[str], "bytes | list[bytes]"]
"""``handler(selector) -> payload`` answering a query (a list: one reply per payload)."""
PresenceCallback = Callable[[str], None]
"""``callback(key)`` for a liveliness token that appears or disappears."""
FLUSH_TIMEOUT = 5.0
"""How long ``close`` waits for the other sessions to confirm what was published (s)."""

LOGGED_ERRORS = 10
"""Callback failures logged with a traceback; after that, one line every LOG_EVERY failures."""
LOG_EVERY = 1000


class BusError(FleetmapError):
    """The bus cannot do what was asked: the session could not open, or it is closed."""


class Handle(Protocol):
    """Something declared on a bus (subscription, queryable, liveliness token): close to undeclare."""

    def close(self) -> None: ...


@dataclass
class BusStats:
    """What a bus has done, for a service's summary. Counters only grow."""

    published: int = 0
    received: int = 0
    callback_errors: int = 0
    queries: int = 0
    query_errors: int = 0


class Bus(Protocol):
    """What a fleetmap service needs from the network."""

    stats: BusStats

    def publish(self, key: str, payload: bytes) -> None:
        """Send ``payload`` on ``key`` (reliable; blocks rather than drop when congested)."""

    def subscribe(self, keyexpr: str, callback: Callback) -> Handle:
        """Call ``callback(key, payload)`` for every payload published on a key matching ``keyexpr``."""

    def declare_queryable(self, key: str, handler: QueryHandler) -> Handle:
        """Answer queries on ``key`` with ``handler(selector)``; a handler that raises replies an error."""

    def query(self, selector: str, timeout: float = 2.0) -> list[bytes]:
        """The payloads of every queryable that answers ``selector`` within ``timeout`` seconds."""

    def declare_liveliness(self, key: str) -> Handle:
        """Hold a liveliness token on ``key`` until closed (or until this process dies)."""

    def subscribe_liveliness(
        self, keyexpr: str, on_join: PresenceCallback, on_leave: PresenceCallback, history: bool = True
    ) -> Handle:
        """Call ``on_join(key)``/``on_leave(key)`` as tokens matching ``keyexpr`` appear and disappear;
        with ``history``, tokens that already exist are reported as joins at once."""

    def wait_for_subscribers(self, key: str, timeout: float) -> bool:
        """Whether some subscriber matches ``key``, waiting up to ``timeout`` seconds for one."""

    def flush(self, timeout: float = FLUSH_TIMEOUT) -> bool:
        """Wait until what was published so far has left this session: every session it is connected
        to (its router, or its peers) has it; whether they confirmed within ``timeout`` seconds.
        ``close`` does it first, unless nothing was published since the last flush."""

    def close(self) -> None:
        """Flush, undeclare everything and leave; further calls raise BusError."""

    def __enter__(self) -> Self: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...


def check_keyexpr(keyexpr: str, what: str = "key expression") -> str:
    """``keyexpr`` if zenoh accepts it in canonical form, else BadInput."""
    try:
        zenoh.KeyExpr(keyexpr)
    except (zenoh.ZError, TypeError) as exc:
        raise BadInput(what, f"{str(keyexpr)[:128]!r} is not a valid key expression: {exc}"[:300]) from None
    return keyexpr


class CallbackGuard:
    """Runs user callbacks so that none raises into the transport: log, count, go on."""

    def __init__(self, stats: BusStats, lock: threading.Lock) -> None:
        self._stats = stats
        self._lock = lock

    def run(self, what: str, fn: Callable[..., object], *args: object) -> None:
        try:
            fn(*args)
        except Exception:  # a callback must never raise into zenoh: this is the one place that catches all
            with self._lock:
                self._stats.callback_errors += 1
                n = self._stats.callback_errors
            if n <= LOGGED_ERRORS:
                log.exception("%s callback failed (failure %d)", what, n)
            elif n % LOG_EVERY == 0:
                log.error("%s callback failed: %d callback failures so far", what, n)


class BusBase:
    """What both buses do alike: refuse work once closed, and close at the end of a with block."""

    _closed: bool = False

    def close(self) -> None:
        raise NotImplementedError

    def _check_open(self) -> None:
        if self._closed:
            raise BusError("the bus is closed")

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def replies(answer: bytes | list[bytes]) -> list[bytes]:
    """A query handler's answer as the payloads to reply with, one reply each."""
    return [bytes(a) for a in answer] if isinstance(answer, list) else [bytes(answer)]
