"""Reading a session recording: its raw messages, from a finished file or one a crash cut short,
and rewriting a cut-off file as a finished one (``fleetmap recover``).

A recorder flushes its file every second (:mod:`fleetmap.shared.io.recording`), so a file cut
short by a crash still holds everything up to its last complete chunk: the reader reads it up to
there and reports how much it read. Damaged bytes are one :class:`BadInput` line, never a traceback.
"""

from __future__ import annotations

import logging
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Self

from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.recording import CHUNK_SIZE, LIBRARY, MAGIC, PROFILE, RAW_ENCODING
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Message, Metadata
from mcap.records import Schema as McapSchema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from zstandard import ZstdError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecordedMessage:
    """One raw message of a recording: the key it was received on and its exact bytes."""

    topic: str
    payload: bytes
    log_time: int
    """When the recorder received it (ns since the Unix epoch)."""
    publish_time: int
    """The message's own stamp (ns), or log_time when it had none."""
    sequence: int


@dataclass(frozen=True)
class ReadReport:
    """How much of a recording was read."""

    source: str
    complete: bool
    """Whether the file was finished (has its summary); a crashed recorder leaves it incomplete."""
    messages: int
    bytes_read: int
    """For an incomplete file: up to the end of its last complete record."""
    file_bytes: int

    @property
    def warning(self) -> str | None:
        if self.complete:
            return None
        return (
            f"{self.source}: the recording ends abruptly (not finished by its recorder): read {self.messages} "
            f"messages from its complete chunks, {self.bytes_read} of {self.file_bytes} bytes"
        )


class _Truncated(Exception):
    """The stream ended inside a record."""


CORRUPT = (McapError, ValueError, struct.error, KeyError, IndexError, OverflowError, ZstdError, RuntimeError)
"""What the mcap library raises, besides its own errors, on a file whose bytes are damaged (a text
field that is no UTF-8, a length past the end, a chunk that does not decompress: zstd or lz4)."""


class _ExactReader:
    """A stream whose short reads raise _Truncated, so a cut-off file ends in one known way."""

    def __init__(self, stream: IO[bytes]) -> None:
        self._stream = stream
        self.position = 0

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        if size >= 0 and len(data) < size:
            raise _Truncated
        self.position += len(data)
        return data


@dataclass(frozen=True)
class RecoverReport:
    """What :meth:`RecordingReader.recover` rewrote."""

    source: str
    messages: int
    """Messages on every channel (raw and Foxglove views)."""
    channels: int
    bytes_read: int
    """Bytes of the source up to its last complete record ..."""
    size: int
    """... of its size."""


def _corrupt(source: str, exc: Exception) -> BadInput:
    """The one line that says a file's bytes are damaged, in plain words."""
    if isinstance(exc, UnicodeDecodeError):
        why = f"a name in it is not UTF-8 text (byte {exc.start})"
    else:
        why = str(exc) or type(exc).__name__
    return BadInput(source, f"corrupt MCAP file: {why}"[:300])


class RecordingReader:
    """The raw messages of a recording, from a finished file or one a crash cut short.

    ``messages()`` yields them in log-time order (the recorder gives every message a later log
    time than the one before, so file order is log-time order also where no index can be used);
    afterwards ``report`` says how much was read, and ``report.warning`` is set for a cut-off file.
    Foxglove channels are skipped: they are views, not data.
    """

    def __init__(self, source: str | Path | IO[bytes]) -> None:
        self._owned: IO[bytes] | None = None
        if isinstance(source, (str, Path)):
            self.source = str(source)
            try:
                self._owned = open(source, "rb")  # noqa: SIM115 - closed by close()
            except FileNotFoundError:
                raise BadInput(self.source, "no such file") from None
            except OSError as exc:
                raise BadInput(self.source, f"cannot read: {exc.strerror}") from None
            self._stream: IO[bytes] = self._owned
        else:
            self.source = getattr(source, "name", "<stream>")
            self._stream = source
        self._start = self._stream.tell()
        self._size = self._stream.seek(0, 2) - self._start
        if self._size < len(MAGIC) or self._read_at(0, len(MAGIC)) != MAGIC:
            raise BadInput(self.source, "not an MCAP file")
        self.complete = self._size >= 2 * len(MAGIC) and self._read_at(self._size - len(MAGIC), len(MAGIC)) == MAGIC
        self._messages = 0
        self._bytes_read = self._size if self.complete else 0

    def _read_at(self, offset: int, size: int) -> bytes:
        self._stream.seek(self._start + offset)
        return self._stream.read(size)

    @property
    def report(self) -> ReadReport:
        return ReadReport(self.source, self.complete, self._messages, self._bytes_read, self._size)

    def messages(
        self,
        *,
        topics: Iterable[str] | None = None,
        start_time: int | None = None,
        end_time: int | None = None,
        warn: bool = True,
    ) -> Iterator[RecordedMessage]:
        """Raw messages with ``start_time <= log_time < end_time`` (ns), on ``topics`` if given; a
        recording that ends abruptly is logged at WARNING once read (unless ``warn`` is False: the
        caller says it, ``report.warning``)."""
        self._messages = 0
        wanted = set(topics) if topics is not None else None
        records = self._indexed() if self.complete else self._streamed()
        for channel, message in records:
            if channel.message_encoding != RAW_ENCODING or (wanted is not None and channel.topic not in wanted):
                continue
            if (start_time is not None and message.log_time < start_time) or (
                end_time is not None and message.log_time >= end_time
            ):
                continue
            self._messages += 1
            yield RecordedMessage(channel.topic, message.data, message.log_time, message.publish_time, message.sequence)
        if not self.complete and warn:
            log.warning("%s", self.report.warning)

    def _indexed(self) -> Iterator[tuple[Channel, Message]]:
        self._stream.seek(self._start)
        try:
            for _, channel, message in make_reader(self._stream).iter_messages(log_time_order=True):
                yield channel, message
        except CORRUPT as exc:
            raise _corrupt(self.source, exc) from None

    def _records(self, emit_chunks: bool) -> Iterator[Any]:
        """Every complete record of a file with no summary; stops (quietly) at the cut."""
        self._stream.seek(self._start)
        exact = _ExactReader(self._stream)
        self._bytes_read = 0
        try:
            for record in StreamReader(exact, emit_chunks=emit_chunks).records:  # type: ignore[arg-type]
                self._bytes_read = exact.position
                yield record
        except _Truncated:
            return
        except CORRUPT as exc:
            raise _corrupt(self.source, exc) from None

    def _streamed(self) -> Iterator[tuple[Channel, Message]]:
        channels: dict[int, Channel] = {}
        last_log_time = -1
        for record in self._records(emit_chunks=False):
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                if record.log_time < last_log_time:
                    log.warning("%s: messages out of log-time order; replaying them in file order", self.source)
                last_log_time = max(last_log_time, record.log_time)
                yield channels[record.channel_id], record

    def recover(self, target: IO[bytes]) -> RecoverReport:
        """Rewrite every complete record of this file into ``target`` as a finished MCAP file, with
        indexes and a summary, so any reader opens it (as ``mcap recover`` and ``ros2 bag reindex``
        do): schemas, channels (Foxglove views included), messages with their times and sequence
        numbers, metadata and attachments. A finished file is copied the same way."""
        writer = Writer(target, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        writer.start(profile=PROFILE, library=f"{LIBRARY} (recovered)")
        schemas: dict[int, int] = {0: 0}
        channels: dict[int, int] = {}
        messages = 0
        for record in self._records(emit_chunks=False):
            if isinstance(record, McapSchema):
                schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.schema_id in schemas:
                channels[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schemas[record.schema_id], dict(record.metadata)
                )
            elif isinstance(record, Message) and record.channel_id in channels:
                writer.add_message(
                    channels[record.channel_id], record.log_time, record.data, record.publish_time, record.sequence
                )
                messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
        writer.finish()
        return RecoverReport(self.source, messages, len(channels), self._bytes_read, self._size)

    def metadata(self) -> dict[str, dict[str, str]]:
        """Every metadata record of the file, by name (the recorder's config and session)."""
        out: dict[str, dict[str, str]] = {}
        if self.complete:
            self._stream.seek(self._start)
            try:
                for record in make_reader(self._stream).iter_metadata():
                    out[record.name] = dict(record.metadata)
            except CORRUPT as exc:
                raise _corrupt(self.source, exc) from None
            return out
        for record in self._records(emit_chunks=True):
            if isinstance(record, Metadata):
                out[record.name] = dict(record.metadata)
        return out

    def topic_counts(self) -> dict[str, int]:
        """How many raw messages each topic holds (reads the whole file)."""
        return dict(Counter(m.topic for m in self.messages()))

    def close(self) -> None:
        if self._owned is not None:
            self._owned.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
