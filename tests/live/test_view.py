"""``fleetmap run --view``: a Foxglove WebSocket client sees the fleet live, every channel typed."""

from __future__ import annotations

import base64
import json
import signal
import socket
import struct
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from fleetmap.shared.io.foxglove_scene import ROOT_FRAME
from websockets.exceptions import ConnectionClosed, InvalidHandshake
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from tests.protobuf_wire import Schema

pytestmark = pytest.mark.slow

SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
"""The Foxglove WebSocket protocol (github.com/foxglove/ws-protocol, docs/spec.md: JSON ops, binary
message data) under the name foxglove-sdk's server accepts; the Foxglove app offers it."""
MESSAGE_DATA = 0x01
"""Opcode of a server's binary message: subscription id (uint32 LE), log time (uint64 LE), payload."""
WANTED = {"SceneUpdate", "LaserScan", "PosesInFrame", "FrameTransform", "Grid", "Log"}
"""Every kind of view a recording holds, the occupancy grid included."""
ROBOTS = {"r1", "r2", "r3", "global"}
"""The department's robots' frames, and the global map's."""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port


def _connect(port: int, run: subprocess.Popen[bytes], timeout: float) -> ClientConnection:
    """The client, once the view serves (asked every 0.2 s for at most ``timeout`` s)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=2.0)
        except (OSError, InvalidHandshake, TimeoutError):
            if time.monotonic() > deadline:
                raise
            try:  # a refused connection returns at once: the next try after 0.2 s, or the run's end
                run.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                continue
            raise


def _unrooted(frames: set[str], parent: dict[str, str]) -> list[str]:
    """The frames whose chain of parents does not reach the root frame (yet)."""
    out = []
    for f in frames:
        chain = [f]
        while chain[-1] != ROOT_FRAME and chain[-1] in parent and len(chain) < 20:
            chain.append(parent[chain[-1]])
        if chain[-1] != ROOT_FRAME:
            out.append(f)
    return out


class Client:
    """A Foxglove WebSocket client that subscribes to every channel the server advertises and
    decodes every message with its channel's schema (nothing else: no generated code)."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.channels: dict[int, dict[str, Any]] = {}
        self.decoders: dict[int, Schema] = {}
        self.received: Counter[int] = Counter()
        self.schemas: Counter[str] = Counter()
        self.messages: list[tuple[str, dict[str, Any]]] = []
        self._subscriptions: dict[int, int] = {}
        self._asked: dict[int, float] = {}

    def subscribe(self, channel: int) -> None:
        # a subscription that races the channel's advertisement is refused (the server logs an
        # unknown channel): one that has brought nothing after a second is asked for again
        sub = len(self._subscriptions) + 1
        self._subscriptions[sub] = channel
        self._asked[channel] = time.monotonic()
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": sub, "channelId": channel}]}))

    def silent(self) -> list[str]:
        return [str(ch["topic"]) for c, ch in self.channels.items() if not self.received[c]]

    def step(self) -> None:
        """Take what the server sent in the next second."""
        for c in self.channels:
            if not self.received[c] and time.monotonic() - self._asked[c] > 1.0:
                self.subscribe(c)
        try:
            frame = self.ws.recv(timeout=1.0)
        except TimeoutError:
            return
        if isinstance(frame, str):
            op = json.loads(frame)
            if op["op"] == "advertise":
                for ch in op["channels"]:
                    # every channel is typed: a protobuf schema Foxglove decodes it by
                    assert ch["encoding"] == "protobuf" and ch["schemaName"].startswith("foxglove."), ch
                    self.channels[ch["id"]] = ch
                    self.decoders[ch["id"]] = Schema(base64.b64decode(ch["schema"]))
                    self.subscribe(ch["id"])
            return
        assert frame[0] == MESSAGE_DATA
        sub, _ = struct.unpack_from("<IQ", frame, 1)
        channel = self._subscriptions[sub]
        name = str(self.channels[channel]["schemaName"])
        self.messages.append((name, self.decoders[channel].decode(name, frame[13:])))
        self.received[channel] += 1
        self.schemas[name.removeprefix("foxglove.")] += 1


def test_a_foxglove_client_receives_every_channel_typed_while_a_session_runs(tmp_path: Path) -> None:
    port = _free_port()
    out = tmp_path / "run"
    log = (tmp_path / "run.log").open("wb")
    argv = ["run", "department", "--out", str(out), "--speed", "1", "--no-progress", "--view", "--view-port", str(port)]
    run = subprocess.Popen([sys.executable, "-m", "fleetmap", *argv], stdout=log, stderr=subprocess.STDOUT)
    parent: dict[str, str] = {}
    frames: set[str] = set()
    try:
        with _connect(port, run, timeout=120.0) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            client = Client(ws)
            deadline = time.monotonic() + 240.0
            while time.monotonic() < deadline and run.poll() is None:
                try:
                    client.step()
                except ConnectionClosed:
                    break
                for name, decoded in client.messages:
                    if name == "foxglove.FrameTransform":
                        parent[decoded["child_frame_id"]] = decoded["parent_frame_id"]
                    frames.update(e["frame_id"] for e in decoded.get("entities", []))
                    if decoded.get("frame_id"):
                        frames.add(decoded["frame_id"])
                    if name == "foxglove.Grid":
                        # the occupancy grid: int8 cells, row by row, some free and some occupied
                        cells, cols = decoded["data"], decoded["column_count"]
                        assert decoded["row_stride"] == cols and len(cells) % cols == 0 and len(cells) > cols
                        assert b"\x00" in cells and b"\x64" in cells
                client.messages.clear()
                done = set(client.schemas) >= WANTED and frames >= ROBOTS and not client.silent()
                if done and not _unrooted(frames, parent):  # a robot's first scans come before its frame's
                    break
        # every channel advertised delivered messages that decode with its schema, of every kind
        assert set(client.schemas) >= WANTED, client.schemas
        assert client.channels and not client.silent(), client.silent()
        topics = {str(ch["topic"]) for ch in client.channels.values()}
        assert "/tf" in topics and any(t.endswith("/grid") for t in topics), topics
        assert frames >= ROBOTS, frames
        # one TF tree: every frame drawn reaches the root
        assert not _unrooted(frames, parent), _unrooted(frames, parent)
        # the session itself is unharmed by its viewer
        assert run.wait(timeout=300) == 0, (tmp_path / "run.log").read_text()[-3000:]
        assert (out / "session.mcap").is_file() and (out / "map.pgm").is_file()
        view_log = (out / "logs" / "view.log").read_text()
        assert "serving" in view_log and "Traceback" not in view_log, view_log[-3000:]
    finally:
        # the session ends by itself (an interrupt while it stops its children would leave some
        # running); interrupted only if it does not, then killed
        for stop in (None, signal.SIGINT, signal.SIGKILL):
            if stop is not None and run.poll() is None:
                run.send_signal(stop)
            try:
                run.wait(timeout=120)
                break
            except subprocess.TimeoutExpired:
                continue
        log.close()


def test_a_view_whose_port_is_taken_exits_2_naming_it() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = ["view", "--port", str(port), "--listen", "tcp/127.0.0.1:0", "--duration", "5"]
        r = subprocess.run([sys.executable, "-m", "fleetmap", *argv], capture_output=True, text=True, timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and f"127.0.0.1:{port}: cannot serve there" in lines[0], r.stderr
    assert "in use" in lines[0] and "Error" not in lines[0], lines[0]
