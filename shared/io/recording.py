"""Session recordings in MCAP: the file's channels, and the writer.

A recording holds two kinds of channels:

- **raw** channels, one per key expression seen on the bus: topic = the key, message encoding
  ``msgpack``, no schema, the exact payload bytes; ``log_time`` is when the recorder received the
  message, ``publish_time`` the message's own stamp. Replays read these.
- **Foxglove** channels, so a person can open the session in Foxglove (which does not decode
  msgpack): ``foxglove.SceneUpdate`` line lists on ``/foxglove/<key>`` for scans, local maps and
  global maps, ``foxglove.FrameTransform`` on ``/tf`` for where local maps and robots are, and
  ``foxglove.Log`` on ``/foxglove/<fleet events key>`` for fleet events.

Files are chunked and ZSTD-compressed; the recorder flushes every second, so a file cut short by
a crash still holds everything up to its last complete chunk, and
:class:`~fleetmap.shared.io.recording_reader.RecordingReader` reads such a file up to there and
reports how much it read. What the Foxglove channels show of each message, and in which frames, is
:mod:`fleetmap.shared.io.foxglove_scene`'s.
"""

from __future__ import annotations

import fcntl
import os
from collections import Counter
from collections.abc import Mapping
from importlib.metadata import version as package_version
from pathlib import Path
from typing import IO

from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.errors import BadInput
from foxglove import Schema
from mcap.writer import CompressionType, Writer

LIBRARY = f"fleetmap {package_version('fleetmap')}"
"""What a recording names as the library that wrote it (the installed package's version: this
layer imports nothing of fleetmap above ``shared``)."""

RAW_ENCODING = "msgpack"
"""The message encoding of the raw channels (registered in the MCAP well-known encodings)."""
PROFILE = ""
"""MCAP profile: none of the registered ones (ros1, ros2) applies."""
CHUNK_SIZE = 1024 * 1024
MAGIC = b"\x89MCAP0\r\n"


def seconds_to_ns(stamp: float) -> int:
    return round(stamp * 1e9)


def _open_alone(path: Path) -> IO[bytes]:
    """``path`` opened for writing, emptied, and locked for as long as it is open: a second writer
    of the same file (two recorders started together, both finding it free) is refused, not left
    to interleave its records with the first's. The lock goes with the process, however it ends."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    except OSError as exc:
        raise BadInput(str(path), f"cannot write: {exc.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise BadInput(str(path), "another recorder is writing it; give this one another --out") from None
    os.ftruncate(fd, 0)
    return os.fdopen(fd, "wb")


class RecordingWriter:
    """An MCAP file of raw and Foxglove channels. Channels and schemas are registered on first use."""

    def __init__(
        self,
        output: str | Path | IO[bytes],
        *,
        chunk_size: int = CHUNK_SIZE,
        compression: CompressionType = CompressionType.ZSTD,
    ) -> None:
        self._owned: IO[bytes] | None = None
        if isinstance(output, (str, Path)):
            self._owned = _open_alone(Path(output))
            stream: IO[bytes] = self._owned
        else:
            stream = output
        self._writer = Writer(stream, chunk_size=chunk_size, compression=compression)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: Counter[int] = Counter()
        self._finished = False

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def _channel(self, topic: str, encoding: str, schema: Schema | None, metadata: Mapping[str, str]) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            schema_id = 0
            if schema is not None:
                schema_id = self._schemas.get(schema.name, 0)
                if schema_id == 0:
                    schema_id = self._writer.register_schema(schema.name, schema.encoding, schema.data)
                    self._schemas[schema.name] = schema_id
            channel_id = self._writer.register_channel(topic, encoding, schema_id, dict(metadata))
            self._channels[topic] = channel_id
        return channel_id

    def write_raw(self, topic: str, payload: bytes, log_time: int, publish_time: int, source: str = "zenoh") -> None:
        """One message of the bus, bytes as received (``source``: zenoh sample or liveliness change)."""
        channel_id = self._channel(topic, RAW_ENCODING, None, {"source": source})
        self._add(channel_id, payload, log_time, publish_time)

    def write_foxglove(self, topic: str, schema: Schema, data: bytes, log_time: int, publish_time: int) -> None:
        channel_id = self._channel(topic, schema.encoding, schema, {})
        self._add(channel_id, data, log_time, publish_time)

    def _add(self, channel_id: int, data: bytes, log_time: int, publish_time: int) -> None:
        self._sequence[channel_id] += 1
        self._writer.add_message(channel_id, log_time, data, publish_time, sequence=self._sequence[channel_id])

    def flush(self) -> None:
        """End the chunk in progress and push it to the file, so a crash cannot lose it."""
        self._writer.flush()

    def finish(self) -> None:
        """Write the indexes and the summary; closes the file if this writer opened it."""
        if self._finished:
            return
        self._finished = True
        self._writer.finish()
        if self._owned is not None:
            self._owned.close()


def config_metadata(config: FleetmapConfig) -> dict[str, str]:
    """A config as MCAP metadata: every ``section.field`` and the whole TOML."""
    out = {name: str(value) for name, value in config.flat().items()}
    out["toml"] = config.to_toml()
    return out
