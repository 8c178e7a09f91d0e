"""The bus over a zenoh session: the real transport of every fleetmap service.

Every payload is published reliably, blocking rather than dropping when congested, with the
``application/msgpack`` encoding; each subscription delivers on a thread of its own
(:class:`_Dispatcher`). A service that connects to a router which does not answer yet tries
again, waiting longer each time, for ``--connect-wait`` seconds.

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

import zenoh
from fleetmap.shared.io.bus import (
    FLUSH_TIMEOUT,
    BusBase,
    BusError,
    BusStats,
    Callback,
    CallbackGuard,
    Handle,
    PresenceCallback,
    QueryHandler,
    check_keyexpr,
    replies,
)
from fleetmap.shared.io.zenoh_config import ZenohOptions, describe, zenoh_config

log = logging.getLogger(__name__)

MSGPACK = "application/msgpack"
"""The zenoh encoding of every fleetmap payload."""

BARRIER_PREFIX = "fleetmap/barrier"
"""Every ZenohBus answers queries on ``fleetmap/barrier/<zid>`` (outside any fleet's keys)."""

FIRST_RETRY = 0.5
"""Seconds before a service tries a router that did not answer again; each wait doubles ..."""
LAST_RETRY = 8.0
"""... up to this."""
UNREACHABLE = "Unable to connect"
"""What zenoh says when no --connect endpoint answers (retried; anything else fails at once)."""


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


class ZenohBus(BusBase):
    """The bus over a zenoh session (``with ZenohBus.open(options) as bus: ...``)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.stats = BusStats()
        self._lock = threading.Lock()
        self._guard = CallbackGuard(self.stats, self._lock)
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
                for one in replies(payload):
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
