"""The transport seam: a small bus interface, zenoh behind it, and an in-memory one for unit tests.

Services talk to a :class:`Bus` (publish, subscribe, query, liveliness) and never to zenoh
directly, so their logic can be driven by :class:`InMemoryBus` in a unit test; the real thing is
:class:`ZenohBus`, and the multi-process tests run it on loopback.

Payloads are bytes (fleetmap messages, :mod:`fleetmap.shared.io.messages`); keys come from
:mod:`fleetmap.shared.io.keys`. Callbacks run on the bus's threads (a thread per zenoh subscription,
in arrival order, so a slow one never holds zenoh's receiving thread; zenoh's for liveliness and
queries; the publisher's for the in-memory bus); one that raises is logged and counted in
:attr:`BusStats.callback_errors` and never reaches zenoh.

Closing a zenoh session drops what it still has queued, so :meth:`ZenohBus.close` first flushes:
it queries ``fleetmap/barrier/*``, which every ZenohBus answers under its own id, and the replies
come back behind the data. Once every session this one is connected to (its routers and peers) has
answered, nothing it published is left in its own queues: the flush ends there, so a session that
holds a barrier queryable and never answers delays only the sessions connected to it directly (a
client waits for its router alone). A router with access control must allow query and reply on
``fleetmap/barrier/**``.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Protocol, Self

import zenoh
from fleetmap.shared.errors import BadInput, FleetmapError
from fleetmap.shared.io.zenoh_config import ZenohOptions, describe, zenoh_config

log = logging.getLogger(__name__)

MSGPACK = "application/msgpack"
"""The zenoh encoding of every fleetmap payload."""

Callback = Callable[[str, bytes], None]
"""``callback(key, payload)`` for a subscription."""
QueryHandler = Callable[[str], "bytes | list[bytes]"]
"""``handler(selector) -> payload`` answering a query (a list: one reply per payload)."""
PresenceCallback = Callable[[str], None]
"""``callback(key)`` for a liveliness token that appears or disappears."""

BARRIER_PREFIX = "fleetmap/barrier"
"""Every ZenohBus answers queries on ``fleetmap/barrier/<zid>`` (outside any fleet's keys)."""
FLUSH_TIMEOUT = 5.0
"""How long ``close`` waits for the other sessions to confirm what was published (s)."""

LOGGED_ERRORS = 10
"""Callback failures logged with a traceback; after that, one line every LOG_EVERY failures."""
LOG_EVERY = 1000


FIRST_RETRY = 0.5
"""Seconds before a service tries a router that did not answer again; each wait doubles ..."""
LAST_RETRY = 8.0
"""... up to this."""
UNREACHABLE = "Unable to connect"
"""What zenoh says when no --connect endpoint answers (retried; anything else fails at once)."""


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


class _CallbackGuard:
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


class _BusBase:
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


# --- zenoh ---


class _ZenohHandle:
    def __init__(
        self,
        entity: object,
        on_close: Callable[[_ZenohHandle], None],
        dispatcher: _Dispatcher | None = None,
    ) -> None:
        self._entity = entity
        self._on_close = on_close
        self._dispatcher = dispatcher
        self._closed = False

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._on_close(self)
        undeclare = getattr(self._entity, "undeclare", None)
        if undeclare is not None:
            try:
                undeclare()
            except zenoh.ZError as exc:  # the session is already closed: nothing left to undeclare
                log.debug("undeclare after close: %s", exc)
        if self._dispatcher is not None:
            self._dispatcher.stop()


class _Dispatcher:
    """Runs a subscription's callback on a thread of its own, fed by an unbounded queue, so zenoh's
    receiving thread only queues a sample. A callback that held that thread (zenoh queues a few
    hundred samples per subscriber, then waits) would keep the session from reading its peers'
    keep-alives: a slow subscriber's link would lapse at the lease, and what was still on the way
    would be lost (docs/decisions/004-a-live-fleet-that-keeps-up.md). Stopping delivers what was
    received first, waiting up to FLUSH_TIMEOUT."""

    def __init__(self, name: str, deliver: Callable[[str, bytes], None]) -> None:
        self._queue: queue.SimpleQueue[tuple[str, bytes] | None] = queue.SimpleQueue()
        self._deliver = deliver
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def put(self, key: str, payload: bytes) -> None:
        self._queue.put((key, payload))

    def _loop(self) -> None:
        while (item := self._queue.get()) is not None:
            self._deliver(*item)

    def stop(self) -> None:
        self._queue.put(None)
        if threading.current_thread() is self._thread:
            return  # closed from its own callback: the loop ends after it
        self._thread.join(FLUSH_TIMEOUT)
        if self._thread.is_alive():
            log.warning("%s: %d messages still being delivered after close", self._thread.name, self._queue.qsize())


class ZenohBus(_BusBase):
    """The bus over a zenoh session (``with ZenohBus.open(options) as bus: ...``)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.stats = BusStats()
        self._lock = threading.Lock()
        self._guard = _CallbackGuard(self.stats, self._lock)
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._handles: list[_ZenohHandle] = []
        self._closed = False
        self._flushed_at = 0
        """``stats.published`` at the last flush (close does not flush again what one flushed)."""
        # Answers other sessions' flush(): the query travels behind their data, so its reply means
        # their data has left them. Without it, zenoh drops what is still queued when a session closes.
        barrier_key = f"{BARRIER_PREFIX}/{session.zid()}"
        barrier = session.declare_queryable(barrier_key, lambda query: _answer_barrier(query, barrier_key))
        self._handles.append(_ZenohHandle(barrier, self._forget))

    @classmethod
    def open(cls, options: ZenohOptions | zenoh.Config) -> ZenohBus:
        """Open a session from the shared flags (or a ready zenoh.Config)."""
        config = zenoh_config(options) if isinstance(options, ZenohOptions) else options
        wait = options.connect_wait if isinstance(options, ZenohOptions) and _connects(config) else 0.0
        deadline = time.monotonic() + wait
        pause = FIRST_RETRY
        while True:
            try:
                session = zenoh.open(config)
                break
            except zenoh.ZError as exc:
                left = deadline - time.monotonic()
                if left <= 0 or UNREACHABLE not in str(exc) or not isinstance(options, ZenohOptions):
                    raise BusError(f"cannot open a zenoh session ({describe(config)}): {_short(exc)}") from None
                pause = min(pause, left)
                log.warning(
                    "nothing answers at %s yet (or it refuses these credentials); trying again in %.1f s (for %.0f s "
                    "more, --connect-wait)",
                    describe(config).get("connect/endpoints", "the --connect endpoints"),
                    pause,
                    left,
                )
                time.sleep(pause)  # nothing else to do until the router answers
                pause = min(2 * pause, LAST_RETRY)
                config = zenoh_config(options)  # a zenoh.Config is consumed by zenoh.open
        log.info("zenoh session %s open: %s", session.zid(), describe(config))
        return cls(session)

    def _track(self, entity: object, dispatcher: _Dispatcher | None = None) -> _ZenohHandle:
        handle = _ZenohHandle(entity, self._forget, dispatcher)
        with self._lock:
            self._handles.append(handle)
        return handle

    def _forget(self, handle: _ZenohHandle) -> None:
        with self._lock:
            if handle in self._handles:
                self._handles.remove(handle)

    def _publisher(self, key: str) -> zenoh.Publisher:
        with self._lock:
            publisher = self._publishers.get(key)
        if publisher is None:
            check_keyexpr(key, "key")
            publisher = self.session.declare_publisher(
                key,
                encoding=zenoh.Encoding(MSGPACK),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            with self._lock:
                publisher = self._publishers.setdefault(key, publisher)
        return publisher

    def publish(self, key: str, payload: bytes) -> None:
        self._check_open()
        try:
            self._publisher(key).put(payload)
        except zenoh.ZError as exc:
            raise BusError(f"cannot publish on {key}: {_short(exc)}") from None
        with self._lock:
            self.stats.published += 1

    def subscribe(self, keyexpr: str, callback: Callback) -> Handle:
        self._check_open()
        check_keyexpr(keyexpr)

        what = f"subscriber {keyexpr}"
        dispatcher = _Dispatcher(what, lambda key, payload: self._guard.run(what, callback, key, payload))

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            with self._lock:
                self.stats.received += 1
            dispatcher.put(str(sample.key_expr), sample.payload.to_bytes())

        try:
            subscriber = self.session.declare_subscriber(keyexpr, on_sample)
        except BaseException:
            dispatcher.stop()
            raise
        return self._track(subscriber, dispatcher)

    def declare_queryable(self, key: str, handler: QueryHandler) -> Handle:
        self._check_open()
        check_keyexpr(key, "key")

        def on_query(query: zenoh.Query) -> None:
            # leaving the with block ends the query; without it, the querier waits for its timeout
            # whenever something (a logged traceback) still holds the Query object
            with query:
                selector = str(query.selector)
                try:
                    payload = handler(selector)
                except Exception as exc:  # a handler must never raise into zenoh: answer with the error instead
                    with self._lock:
                        self.stats.callback_errors += 1
                    log.exception("queryable %s failed on %s", key, selector)
                    query.reply_err(f"{type(exc).__name__}: {exc}"[:500].encode())
                    return
                for one in _replies(payload):
                    query.reply(key, one, encoding=zenoh.Encoding(MSGPACK))

        return self._track(self.session.declare_queryable(key, on_query, complete=True))

    def query(self, selector: str, timeout: float = 2.0) -> list[bytes]:
        self._check_open()
        check_keyexpr(selector.split("?", 1)[0], "selector")
        out: list[bytes] = []
        with self._lock:
            self.stats.queries += 1
        replies = self.session.get(
            selector, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout
        )
        for reply in replies:
            if reply.ok is not None:
                out.append(reply.ok.payload.to_bytes())
            else:
                with self._lock:
                    self.stats.query_errors += 1
                error = reply.err.payload.to_bytes() if reply.err is not None else b""
                log.warning("query %s: error reply %r", selector, error[:200])
        return out

    def declare_liveliness(self, key: str) -> Handle:
        self._check_open()
        check_keyexpr(key, "key")
        return self._track(self.session.liveliness().declare_token(key))

    def subscribe_liveliness(
        self, keyexpr: str, on_join: PresenceCallback, on_leave: PresenceCallback, history: bool = True
    ) -> Handle:
        self._check_open()
        check_keyexpr(keyexpr)

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if sample.kind == zenoh.SampleKind.PUT:
                self._guard.run(f"liveliness {keyexpr} join", on_join, key)
            else:
                self._guard.run(f"liveliness {keyexpr} leave", on_leave, key)

        subscriber = self.session.liveliness().declare_subscriber(keyexpr, on_sample, history=history)
        return self._track(subscriber)

    def wait_for_subscribers(self, key: str, timeout: float) -> bool:
        self._check_open()
        publisher = self._publisher(key)
        matched = threading.Event()
        listener = publisher.declare_matching_listener(lambda status: matched.set() if status.matching else None)
        try:
            # zenoh's stub says bool; 1.10 returns a MatchingStatus
            status = publisher.matching_status
            return bool(getattr(status, "matching", status)) or matched.wait(timeout)
        finally:
            listener.undeclare()

    def flush(self, timeout: float = FLUSH_TIMEOUT) -> bool:
        self._check_open()
        started = time.monotonic()
        with self._lock:
            self._flushed_at = self.stats.published
        info = self.session.info
        neighbours = {f"{BARRIER_PREFIX}/{zid}" for zid in [*info.routers_zid(), *info.peers_zid()]}
        replies = self.session.get(
            f"{BARRIER_PREFIX}/*",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        answered = 0
        for reply in replies:
            if reply.ok is None:
                continue
            answered += 1
            neighbours.discard(str(reply.ok.key_expr))
            if not neighbours:
                return True  # the next hops have it all: this session's queues are empty
        if time.monotonic() - started >= timeout:
            log.warning(
                "flush: only %d sessions confirmed within %.1f s; what is still queued may be lost", answered, timeout
            )
            return False
        return True

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            unflushed = self.stats.published > self._flushed_at
        if unflushed:
            self.flush()
        with self._lock:
            self._closed = True
            handles = list(self._handles)
            publishers = list(self._publishers.values())
        for handle in handles:
            handle.close()
        for publisher in publishers:
            publisher.undeclare()
        self.session.close()


def _replies(answer: bytes | list[bytes]) -> list[bytes]:
    return [bytes(a) for a in answer] if isinstance(answer, list) else [bytes(answer)]


def _connects(config: zenoh.Config) -> bool:
    """Whether a session of ``config`` connects somewhere (from the flags or its config file)."""
    try:
        endpoints = json.loads(config.get_json("connect/endpoints"))
    except (zenoh.ZError, ValueError):
        return False
    if isinstance(endpoints, dict):  # per mode: {"router": [...], "peer": [...], "client": [...]}
        return any(endpoints.values())
    return bool(endpoints)


def _answer_barrier(query: zenoh.Query, key: str) -> None:
    """Reply under this session's own barrier key, so the flushing session knows who answered."""
    with query:
        query.reply(key, b"")


def _short(exc: Exception) -> str:
    """zenoh's error text without the Rust source locations it appends."""
    return str(exc).split(" at /")[0][:300]


# --- in memory ---


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


class InMemoryBus(_BusBase):
    """A bus inside one process, for fast unit tests of service logic: delivery is synchronous,
    in the publisher's thread, in publication order. ``peer()`` gives another bus on the same
    network (another "process"): closing it makes its liveliness tokens leave."""

    def __init__(self, hub: _Hub | None = None) -> None:
        self._hub = hub if hub is not None else _Hub()
        self.stats = BusStats()
        self._lock = threading.Lock()
        self._guard = _CallbackGuard(self.stats, self._lock)
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
                out += _replies(handler(selector))
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
