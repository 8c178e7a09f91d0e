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
from fleetmap.shared.io.bus import ZenohBus
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import LocalMap
from fleetmap.shared.io.recording import RecordingReader, RecordingWriter
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

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
from fleetmap.shared.io.bus import ZenohBus
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--segments", type=int, nargs="+", default=[300], help="segments per local map")
    parser.add_argument("--messages", type=int, default=2000, help="local maps per run")
    args = parser.parse_args()
    rows = []
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
    print(
        f"{'path':<15} {'segments':>8} {'foxglove':>8} {'messages':>8} {'s':>7} {'msg/s':>8} {'MB/s':>7} {'file MB':>8}"
    )
    for path_kind, segments, foxglove, n, seconds, megabytes, size in rows:
        rate = n / seconds if seconds > 0 else math.nan
        print(
            f"{path_kind:<15} {segments:>8} {'yes' if foxglove else 'no':>8} {n:>8} {seconds:>7.2f} {rate:>8.0f} "
            f"{megabytes * n / args.messages / seconds:>7.1f} {size / 1e6:>8.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
