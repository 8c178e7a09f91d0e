"""The recorder: every message of the fleet, and every presence change, into one MCAP file.

:class:`Recorder` is the library call: feed it ``(key, payload, receive_time_ns)`` and presence
changes, call :meth:`Recorder.tick` with the time now and then, and :meth:`Recorder.finish` at
the end; it needs no network. :class:`RecorderService` runs it on a bus: it subscribes to
``fleet/<fleet>/**`` and to liveliness under the fleet, ticks on a timer, and holds the
``fleet/<fleet>/services/recorder`` token while it records, so whoever starts it can wait for
it to be ready; its queryable ``fleet/<fleet>/recorder/stats`` answers what it has recorded so
far (:meth:`RecorderSummary.from_msgpack`), so whoever stops it can first wait for it to catch up.

What goes into the file (see :mod:`fleetmap.shared.io.recording`): every payload raw, on a channel
named by its key, and a Foxglove view of every valid one. A malformed payload was on the bus, so
it is recorded raw too; it gets no view and is counted, and it never stops the recorder. Presence
changes are recorded as FleetEvent payloads (join, leave) on the liveliness key's channel.

Every message gets a log time later than the one before (its receive time, or 1 ns after the
previous one when two arrive out of order across zenoh threads), so a replay in log-time order
is the order the recorder saw. The file is flushed when its oldest unflushed message is
``flush_interval`` old (0.5 s) and the service ticks every 0.1 s: a crash loses at most ~0.6 s.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import ClassVar

import msgpack
from fleetmap.merger.listener import FleetListener
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.bus import Bus, Handle
from fleetmap.shared.io.foxglove_scene import FoxgloveScene
from fleetmap.shared.io.keys import ROBOT_KINDS, FleetKeys
from fleetmap.shared.io.messages import (
    BadMessage,
    FleetEvent,
    GlobalMap,
    LocalMap,
    MergeEdge,
    MergerStep,
    Message,
    RobotPose,
    Scan,
    decode,
)
from fleetmap.shared.io.recording import RecordingWriter, seconds_to_ns

log = logging.getLogger(__name__)

FLUSH_INTERVAL = 0.5
"""Seconds a received message may wait in memory before its chunk is written."""
KEY_RATE = 4e6
"""Bytes per second one robot (all its keys together), or one key that is no robot's, may write
into the recording in the long run (``--max-key-rate``): a robot's scans with their raw beams and
its submaps come to tens of kB/s; a flood is cut to this, each message it drops counted. Per robot,
not per key: a robot may put under keys it makes up, each of which would have had a bucket."""
KEY_BURST = 64e6
"""... and in one burst (a merger's state answered at once, a robot republishing every submap)."""
TICK_PERIOD = 0.1
"""How often the service checks whether to flush (s)."""
LOGGED_MALFORMED = 20
"""Malformed messages logged one by one; after that, one line every 1000."""

EXPECTED: dict[str, tuple[type[Message], ...]] = {
    "scan": (Scan,),
    "localmap": (LocalMap,),
    "pose": (RobotPose,),
    "globalmap": (GlobalMap,),
    "edges": (MergeEdge,),
    "steps": (MergerStep,),
    "events": (FleetEvent,),
    "robot_events": (FleetEvent,),
    "state": (Scan, LocalMap, MergeEdge, GlobalMap, RobotPose, FleetEvent),
}
"""The message types each kind of key carries; a payload of another type is malformed there."""


def checked_message(keys: FleetKeys, key: str, payload: bytes) -> tuple[Message | None, str]:
    """The message of a payload received on ``key`` if it is valid there (a message of the kind
    the key carries, of the robot the key names), else None and why not; never raises."""
    try:
        parsed = keys.parse(key)
        message = decode(payload)
    except BadInput as exc:  # BadMessage, or a key that is not the fleet's
        return None, str(exc)
    expected = EXPECTED.get(parsed.kind, ())
    if not isinstance(message, expected):
        return None, f"{message.SCHEMA} is not a message of a {parsed.kind} key"
    robot = getattr(message, "robot", None)
    if parsed.kind in ROBOT_KINDS and robot != parsed.robot:
        return None, f"a message of robot {robot!r} on robot {parsed.robot!r}'s key"
    return message, ""


def presence_event(keys: FleetKeys, key: str, joined: bool, receive_time_ns: int) -> FleetEvent:
    """A liveliness token appearing (``joined``) or disappearing on ``key``, as a FleetEvent (of
    the robot the key names, if it is a robot's)."""
    try:
        parsed = keys.parse(key)
    except BadInput:
        parsed = None
    robot = parsed.robot if parsed is not None and parsed.kind == "alive" else None
    return FleetEvent("join" if joined else "leave", robot, receive_time_ns / 1e9, detail=key)


@dataclass(frozen=True)
class RecorderSummary:
    """What a recorder recorded, per raw topic."""

    messages: dict[str, int]
    payload_bytes: dict[str, int]
    malformed: dict[str, int]
    foxglove_messages: int
    late: int = 0
    """Messages that arrived after the file was finished (dropped)."""
    lost: int = 0
    """Messages the file could not take (a write failed: disk full), and those buffered with them."""
    throttled: int = 0
    """Messages dropped because their key wrote faster than ``--max-key-rate`` allows."""
    error: str = ""
    """Why the recorder stopped writing ("" while it writes)."""

    SCHEMA: ClassVar[str] = "fleetmap.RecorderStats"

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    def to_msgpack(self) -> bytes:
        """The answer of the recorder's stats queryable (``FleetKeys.recorder_stats``)."""
        data = {"schema": self.SCHEMA, "v": 1, **asdict(self)}
        packed: bytes = msgpack.packb(data, use_bin_type=True)
        return packed

    @classmethod
    def from_msgpack(cls, data: bytes) -> RecorderSummary:
        try:
            raw = msgpack.unpackb(data, raw=False)
        except (msgpack.UnpackException, ValueError) as exc:
            raise BadMessage(cls.SCHEMA, None, f"not msgpack: {exc}"[:200]) from None
        if not isinstance(raw, dict) or raw.get("schema") != cls.SCHEMA:
            raise BadMessage(cls.SCHEMA, "schema", "not a recorder stats answer")
        counts = {}
        for name in ("messages", "payload_bytes", "malformed"):
            table = raw.get(name)
            if not isinstance(table, dict) or not all(
                isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) for k, v in table.items()
            ):
                raise BadMessage(cls.SCHEMA, name, "expected a map of topic to count")
            counts[name] = table
        numbers = {}
        for name in ("foxglove_messages", "late", "lost", "throttled"):
            value = raw.get(name, 0)
            if not isinstance(value, int) or isinstance(value, bool):
                raise BadMessage(cls.SCHEMA, name, "expected a count")
            numbers[name] = value
        error = raw.get("error", "")
        if not isinstance(error, str):
            raise BadMessage(cls.SCHEMA, "error", "expected a string")
        return cls(counts["messages"], counts["payload_bytes"], counts["malformed"], **numbers, error=error)

    @property
    def total_malformed(self) -> int:
        return sum(self.malformed.values())

    def table(self) -> str:
        """A summary table: messages, bytes and malformed messages per topic."""
        width = max([len("topic"), *(len(t) for t in self.messages)])
        rows = [
            (t, self.messages[t], self.payload_bytes.get(t, 0), self.malformed.get(t, 0)) for t in sorted(self.messages)
        ]
        rows.append(("total", self.total, sum(self.payload_bytes.values()), self.total_malformed))
        lines = [f"{'topic':<{width}} {'messages':>9} {'bytes':>12} {'malformed':>9}"]
        lines += [f"{t:<{width}} {n:>9} {size:>12} {bad:>9}" for t, n, size, bad in rows]
        if self.throttled:
            lines.append(f"not recorded: {self.throttled} messages of keys writing faster than --max-key-rate")
        if self.error:
            lines.append(f"NOT RECORDED: {self.lost} messages ({self.error})")
        return "\n".join(lines)


@dataclass
class _Counts:
    messages: Counter[str] = field(default_factory=Counter)
    payload_bytes: Counter[str] = field(default_factory=Counter)
    malformed: Counter[str] = field(default_factory=Counter)
    foxglove: int = 0
    late: int = 0
    lost: int = 0
    throttled: int = 0
    unflushed: Counter[str] = field(default_factory=Counter)
    """Raw messages per topic written since the last flush (lost with it if the flush fails) ..."""
    unflushed_bytes: Counter[str] = field(default_factory=Counter)
    """... and their payload bytes."""


class Recorder:
    """Writes what it is fed into a recording; thread-safe, clock given by the caller."""

    def __init__(
        self,
        writer: RecordingWriter,
        keys: FleetKeys,
        *,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        flush_interval: float = FLUSH_INTERVAL,
        foxglove: bool = True,
        key_rate: float = KEY_RATE,
        key_burst: float = KEY_BURST,
    ) -> None:
        self._writer = writer
        self._keys = keys
        self._flush_interval_ns = int(flush_interval * 1e9)
        self._foxglove = foxglove
        self._scene = FoxgloveScene()
        self._lock = threading.Lock()
        self._counts = _Counts()
        self._last_log_time = 0
        self._pending_since: int | None = None
        self._finished = False
        self.error = ""
        """Why the file stopped taking messages (a write failed: disk full); "" while it writes."""
        self._latest: dict[str, tuple[int, bytes]] = {}
        """The newest version of every submap recorded: (version, payload)."""
        self._key_rate, self._key_burst = key_rate, key_burst
        self._buckets: dict[str, tuple[float, int]] = {}
        """Per robot (or key, :meth:`_writer_of`): the bytes it may still write now, and when that was
        worked out (ns)."""
        self._robots_prefix = f"{keys.prefix}/robots/"
        for name, data in (metadata or {}).items():
            writer.add_metadata(name, data)

    def feed(self, key: str, payload: bytes, receive_time_ns: int) -> None:
        """Record one payload received on ``key``; never raises for a bad payload."""
        message, problem = self._check(key, payload)
        with self._lock:
            if not self._admit(key, len(payload), receive_time_ns):
                return
            if isinstance(message, LocalMap) and key == self._keys.localmap(message.robot):
                held = self._latest.get(message.submap_key)
                if held is None or message.version > held[0]:
                    self._latest[message.submap_key] = (message.version, payload)
            if self._finished:
                self._counts.late += 1
                return
            if self.error:
                self._counts.lost += 1
                return
            log_time = self._log_time(receive_time_ns)
            publish_time = seconds_to_ns(message.stamp) if message is not None else log_time
            try:
                self._writer.write_raw(key, payload, log_time, publish_time)
                self._counted(key, len(payload))
                if message is None:
                    self._malformed(key, problem)
                elif self._foxglove:
                    self._write_views(message, key, log_time)
                self._maybe_flush(receive_time_ns)
            except OSError as exc:
                self._fail(exc)

    def latest_maps(self) -> list[bytes]:
        """The newest version of every submap recorded, as received (what a restarted merger
        recalls: the maps of robots that finished while it was down)."""
        with self._lock:
            return [payload for _, payload in self._latest.values()]

    def feed_presence(self, key: str, joined: bool, receive_time_ns: int) -> None:
        """Record a liveliness token appearing (``joined``) or disappearing, as a FleetEvent."""
        event = presence_event(self._keys, key, joined, receive_time_ns)
        payload = event.to_msgpack()
        with self._lock:
            if self._finished:
                self._counts.late += 1
                return
            if self.error:
                self._counts.lost += 1
                return
            log_time = self._log_time(receive_time_ns)
            try:
                self._writer.write_raw(key, payload, log_time, log_time, source="liveliness")
                self._counted(key, len(payload))
                if self._foxglove:
                    self._write_views(event, self._keys.events, log_time)
                self._maybe_flush(receive_time_ns)
            except OSError as exc:
                self._fail(exc)

    def tick(self, now_ns: int) -> bool:
        """Flush if the oldest unflushed message is ``flush_interval`` old; whether it flushed."""
        with self._lock:
            if self._finished or self.error:
                return False
            try:
                return self._maybe_flush(now_ns)
            except OSError as exc:
                self._fail(exc)
                return False

    def summary(self) -> RecorderSummary:
        with self._lock:
            c = self._counts
            messages = {k: n for k, n in c.messages.items() if n}
            sizes = {k: n for k, n in c.payload_bytes.items() if k in messages}
            return RecorderSummary(
                messages, sizes, dict(c.malformed), c.foxglove, c.late, c.lost, c.throttled, self.error
            )

    def finish(self) -> RecorderSummary:
        """Finish the file (indexes and summary); later feeds are counted as late and dropped."""
        with self._lock:
            if not self._finished:
                self._finished = True
                try:
                    if self._foxglove and not self.error:
                        now = self._log_time(self._last_log_time)
                        for view in self._scene.final_views(now * 1e-9):
                            self._writer.write_foxglove(view.topic, view.schema, view.data, now, now)
                            self._counts.foxglove += 1
                    self._writer.finish()
                    self._flushed()
                except OSError as exc:
                    self._fail(exc)
        return self.summary()

    def _writer_of(self, key: str) -> str:
        """Whose rate a message on ``key`` counts against: the robot of any key under
        ``robots/<robot>/`` (made-up keys included), else the key itself."""
        if key.startswith(self._robots_prefix):
            robot = key[len(self._robots_prefix) :].split("/", 1)[0]
            return f"{self._robots_prefix}{robot}"
        return key

    def _admit(self, key: str, size: int, now_ns: int) -> bool:
        """Whether the writer of ``key`` (:meth:`_writer_of`) may write ``size`` more bytes now (a
        token bucket: ``key_rate`` bytes/s, ``key_burst`` at once); a message it may not is dropped
        and counted."""
        if self._key_rate <= 0:
            return True
        writer = self._writer_of(key)
        tokens, since = self._buckets.get(writer, (self._key_burst, now_ns))
        tokens = min(self._key_burst, tokens + max(now_ns - since, 0) * 1e-9 * self._key_rate)
        admitted = size <= tokens
        self._buckets[writer] = (tokens - size if admitted else tokens, now_ns)
        if not admitted:
            self._counts.throttled += 1
            n = self._counts.throttled
            if n <= 10 or n % 1000 == 0:
                log.warning("dropped a message of %d bytes on %s: faster than --max-key-rate (%d so far)", size, key, n)
        return admitted

    def _counted(self, key: str, size: int) -> None:
        c = self._counts
        c.messages[key] += 1
        c.payload_bytes[key] += size
        c.unflushed[key] += 1
        c.unflushed_bytes[key] += size

    def _fail(self, exc: OSError) -> None:
        """A write failed (disk full, file too large, device gone): the file takes nothing more. The
        messages buffered since the last flush are lost with it and counted so, not as recorded."""
        c = self._counts
        c.messages.subtract(c.unflushed)
        c.payload_bytes.subtract(c.unflushed_bytes)
        c.lost += c.unflushed.total()
        self._flushed()
        first = not self.error
        self.error = f"cannot write the recording: {exc.strerror or exc}"
        if first:
            log.error("%s; recording STOPPED, later messages are lost (%d so far)", self.error, c.lost)

    # --- inside the lock, or pure ---

    def _check(self, key: str, payload: bytes) -> tuple[Message | None, str]:
        return checked_message(self._keys, key, payload)

    def _log_time(self, receive_time_ns: int) -> int:
        self._last_log_time = max(int(receive_time_ns), self._last_log_time + 1)
        if self._pending_since is None:
            self._pending_since = int(receive_time_ns)
        return self._last_log_time

    def _write_views(self, message: Message, key: str, log_time: int) -> None:
        # the views are on the recording's clock, their log time (the raw channel keeps the stamp)
        for view in self._scene.views(message, key, log_time * 1e-9):
            self._writer.write_foxglove(view.topic, view.schema, view.data, log_time, log_time)
            self._counts.foxglove += 1

    def _malformed(self, key: str, problem: str) -> None:
        self._counts.malformed[key] += 1
        n = sum(self._counts.malformed.values())
        if n <= LOGGED_MALFORMED:
            log.warning("malformed message on %s (recorded raw): %s", key, problem)
        elif n % 1000 == 0:
            log.warning("%d malformed messages so far (recorded raw); latest on %s: %s", n, key, problem)

    def _maybe_flush(self, now_ns: int) -> bool:
        if self._pending_since is None or now_ns - self._pending_since < self._flush_interval_ns:
            return False
        self._writer.flush()
        self._flushed()
        self._pending_since = None
        return True

    def _flushed(self) -> None:
        self._counts.unflushed.clear()
        self._counts.unflushed_bytes.clear()


ERROR_EVERY = 10.0
"""Seconds between the ERROR lines of a recorder that cannot write."""


class RecorderService(FleetListener):
    """A Recorder on a bus: ``with RecorderService(bus, recorder, keys): ...`` records until closed."""

    def __init__(
        self,
        bus: Bus,
        recorder: Recorder,
        keys: FleetKeys,
        *,
        clock: Callable[[], int] = time.time_ns,
        tick_period: float = TICK_PERIOD,
    ) -> None:
        super().__init__(bus, recorder, keys, clock=clock, tick_period=tick_period, name="recorder-flush")
        self.recorder = recorder
        self._token: Handle | None = None
        self._said = -math.inf

    def start(self) -> None:
        """Subscribe, then announce the recorder (its liveliness token means: recording now)."""
        super().start()
        self._handles.append(self.bus.declare_queryable(self.keys.recorder_stats, self._stats))
        self._handles.append(self.bus.declare_queryable(self.keys.recorder_maps, lambda _: self.recorder.latest_maps()))
        self._token = self.bus.declare_liveliness(self.keys.service("recorder"))
        log.info("recording %s", self.keys.everything)

    def _stats(self, selector: str) -> bytes:
        return self.recorder.summary().to_msgpack()

    def tick(self) -> None:
        self.recorder.tick(self._clock())
        if self.recorder.error:
            # loud: the recorder's presence goes (its token means "recording now"), and it says so
            # every ERROR_EVERY seconds; it still answers queries (the maps it kept, its counts)
            if self._token is not None:
                self._token.close()
                self._token = None
            if time.monotonic() - self._said >= ERROR_EVERY:
                self._said = time.monotonic()
                summary = self.recorder.summary()
                log.error("NOT RECORDING: %s; %d messages lost so far", summary.error, summary.lost)

    def stop(self) -> RecorderSummary:
        """Stop listening and finish the file."""
        self.stop_listening()
        if self._token is not None:
            self._token.close()
            self._token = None
        return self.recorder.finish()


def query_recorder_stats(bus: Bus, keys: FleetKeys, timeout: float = 2.0) -> RecorderSummary | None:
    """What the fleet's recorder has recorded so far, or None when no recorder answers."""
    for payload in bus.query(keys.recorder_stats, timeout):
        try:
            return RecorderSummary.from_msgpack(payload)
        except BadMessage as exc:
            log.warning("recorder stats: %s", exc)
    return None


def wait_until_recorded(bus: Bus, keys: FleetKeys, expected: Mapping[str, int], timeout: float) -> bool:
    """Whether the recorder has recorded at least ``expected[topic]`` messages on every topic,
    asking it every 50 ms for at most ``timeout`` seconds (stop a recorder only once it says so)."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    while True:
        stats = query_recorder_stats(bus, keys, timeout=max(0.05, min(1.0, deadline - time.monotonic())))
        if stats is not None and all(stats.messages.get(t, 0) >= n for t, n in expected.items()):
            return True
        if time.monotonic() >= deadline:
            return False
        pause.wait(0.05)
