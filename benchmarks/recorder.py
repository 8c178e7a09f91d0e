"""Benchmark: the recorder's throughput (run on demand, not in CI).

Local maps of a few hundred segments (what agents publish every few scans) are recorded to an
MCAP file on disk:

- **in-process**: ``Recorder.feed`` called in a loop, no network: the cost of validating,
  writing raw, drawing the Foxglove view, compressing;
- **zenoh loopback**: a publisher process sends them over a real zenoh session to a
  ``RecorderService`` in this process, as fast as it can (reliable, blocking congestion
  control); timed from the recorder's first message to its last.

Prints messages/s and MB/s of payload, with and without the Foxglove views.

    python benchmarks/recorder.py                          # 300-segment maps, 2000 of them
    python benchmarks/recorder.py --segments 100 1000 --messages 500
    python benchmarks/recorder.py --write-results          # and write its result (benchmarks/results/)
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
from fleetmap.merger.recorder import Recorder, RecorderService
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import LocalMap
from fleetmap.shared.io.recording import RecordingWriter
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint
from results import markdown_table, write_result

KEYS = FleetKeys("bench")
ROBOTS = 4


def local_maps(segments: int, count: int, seed: int = 0) -> list[tuple[str, bytes]]:
    """(key, payload) of ``count`` local maps of ``segments`` random wall pieces, 4 robots in turn."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        robot = f"r{i % ROBOTS}"
        start = rng.uniform(-20.0, 20.0, size=(segments, 2))
        angle = rng.uniform(-math.pi, math.pi, size=segments)
        length = rng.uniform(0.2, 3.0, size=segments)
        end = start + np.c_[np.cos(angle), np.sin(angle)] * length[:, None]
        message = LocalMap(robot, 0, i // ROBOTS, float(i), np.c_[start, end], i + 1, Transform2D(0.1 * i, 0.0, 0.0))
        out.append((KEYS.localmap(robot), message.to_msgpack()))
    return out


def in_process(payloads: list[tuple[str, bytes]], path: Path, foxglove: bool) -> float:
    recorder = Recorder(RecordingWriter(path), KEYS, foxglove=foxglove)
    start = time.perf_counter()
    for key, payload in payloads:
        recorder.feed(key, payload, time.time_ns())
    recorder.finish()
    return time.perf_counter() - start


PUBLISHER = """
import sys
import msgpack
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions

with open(sys.argv[2], "rb") as f:
    payloads = msgpack.unpackb(f.read())
with ZenohBus.open(ZenohOptions(connect=(sys.argv[1],), fleet="bench")) as bus:
    if not bus.wait_for_subscribers(payloads[0][0], 10.0):
        sys.exit("no recorder")
    print("publishing", flush=True)
    for key, payload in payloads:
        bus.publish(key, payload)
"""


class _CountingRecorder(Recorder):
    """Notes when the first and the n-th message were recorded."""

    def __init__(self, *args: object, expected: int, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.expected = expected
        self.count = 0
        self.first = 0.0
        self.done = threading.Event()

    def feed(self, key: str, payload: bytes, receive_time_ns: int) -> None:
        super().feed(key, payload, receive_time_ns)
        if key.startswith(KEYS.prefix + "/robots/"):
            self.count += 1
            if self.count == 1:
                self.first = time.perf_counter()
            if self.count == self.expected:
                self.done.set()


def over_zenoh(payloads: list[tuple[str, bytes]], path: Path, foxglove: bool) -> tuple[float, int]:
    """Seconds from the first to the last message recorded, and how many were recorded."""
    endpoint = free_loopback_endpoint()
    source = path.with_suffix(".msgpack")
    source.write_bytes(msgpack.packb(payloads, use_bin_type=True))
    count = len(payloads)
    with ZenohBus.open(ZenohOptions(listen=(endpoint,), fleet="bench")) as bus:
        recorder = _CountingRecorder(RecordingWriter(path), KEYS, expected=count, foxglove=foxglove)
        with RecorderService(bus, recorder, KEYS):
            publisher = subprocess.Popen([sys.executable, "-c", PUBLISHER, endpoint, str(source)])
            finished = recorder.done.wait(60.0)
            end = time.perf_counter()
            publisher.wait(60.0)
        if not finished:
            return math.nan, recorder.count
    return end - recorder.first, recorder.count


Row = tuple[str, int, bool, int, float, float, int]
"""A run: path, segments per map, Foxglove views, messages recorded, seconds, MB of payload sent, file bytes."""
HEADER = ["path", "segments", "foxglove", "messages", "s", "msg/s", "MB/s", "file MB"]
WIDTHS = [-15, 8, 8, 8, 7, 8, 7, 8]
"""The printed columns' widths (negative: left-aligned)."""
EXPLAINED = (
    "Local maps of `--segments` random wall pieces (4 robots in turn), `--messages` of them, recorded to an "
    "MCAP file on disk: in-process (`Recorder.feed` in a loop, no network: validating, writing raw, drawing "
    "the Foxglove view, compressing) and over zenoh loopback (a publisher process sending them as fast as it "
    "can to a `RecorderService`, reliable and blocking). foxglove: with the Foxglove views drawn or not; "
    "messages: those recorded; s: seconds (over zenoh, from the first message recorded to the last); msg/s "
    "and MB/s: messages and megabytes of payload recorded per second; file MB: the MCAP file's size."
)


def cells(row: Row, messages: int) -> list[str]:
    """A run's columns: ``messages`` local maps were sent."""
    path_kind, segments, foxglove, n, seconds, megabytes, size = row
    rate = n / seconds if seconds > 0 else math.nan
    mb_per_s = megabytes * n / messages / seconds
    return [
        path_kind,
        str(segments),
        "yes" if foxglove else "no",
        str(n),
        f"{seconds:.2f}",
        f"{rate:.0f}",
        f"{mb_per_s:.1f}",
        f"{size / 1e6:.2f}",
    ]


def aligned(columns: list[str]) -> str:
    """A printed line: the columns padded to ``WIDTHS``."""
    return " ".join(c.ljust(-w) if w < 0 else c.rjust(w) for c, w in zip(columns, WIDTHS, strict=True))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--segments", type=int, nargs="+", default=[300], help="segments per local map")
    parser.add_argument("--messages", type=int, default=2000, help="local maps per run")
    parser.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    args = parser.parse_args()
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for segments in args.segments:
            payloads = local_maps(segments, args.messages)
            megabytes = sum(len(p) for _, p in payloads) / 1e6
            for foxglove in (True, False):
                path = Path(tmp) / f"in-process-{segments}-{foxglove}.mcap"
                seconds = in_process(payloads, path, foxglove)
                rows.append(("in-process", segments, foxglove, args.messages, seconds, megabytes, path.stat().st_size))
                path = Path(tmp) / f"zenoh-{segments}-{foxglove}.mcap"
                seconds, got = over_zenoh(payloads, path, foxglove)
                counts = RecordingReader(path).topic_counts()
                recorded = sum(n for t, n in counts.items() if t.startswith(KEYS.prefix + "/robots/"))
                if recorded != args.messages:
                    print(f"zenoh run recorded {recorded} of {args.messages} messages", file=sys.stderr)
                rows.append(("zenoh loopback", segments, foxglove, got, seconds, megabytes, path.stat().st_size))
    print(aligned(HEADER))
    for row in rows:
        print(aligned(cells(row, args.messages)))
    if args.write_results:
        table = markdown_table(HEADER, [cells(row, args.messages) for row in rows])
        write_result(
            "recorder",
            "The recorder's throughput (`benchmarks/recorder.py`)",
            EXPLAINED + "\n\n" + table,
            config=None,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
