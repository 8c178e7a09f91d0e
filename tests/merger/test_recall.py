"""A robot that leaves: the versions of its submaps the merger did not hear are recalled from the
recorder (decision record 073), over real zenoh sessions on loopback."""

from __future__ import annotations

import io
import time
from collections.abc import Callable

import numpy as np
from fleetmap.merger.engine import Merger
from fleetmap.merger.recorder import Recorder, RecorderService
from fleetmap.merger.service import MergerService
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import LocalMap
from fleetmap.shared.io.recording import RecordingWriter
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

from tests.bus_helpers import open_zenoh

KEYS = FleetKeys("recall")
WAIT = 15.0

BOX = np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [4.0, 3.0, 0.0, 3.0]])


def _submap(robot: str, version: int, walls: np.ndarray, final: bool = False) -> LocalMap:
    return LocalMap(robot, 0, version, 1.0 + version, walls, len(walls), Transform2D(), submap=0, final=final)


def _until(svc: MergerService, done: Callable[[], bool]) -> bool:
    deadline = time.monotonic() + WAIT
    while not done():
        if time.monotonic() > deadline:
            return False
        if not svc.run_once():
            time.sleep(0.02)
    return True


def _version(svc: MergerService, key: str) -> int:
    held = svc.merger.submaps.get(key)
    return -1 if held is None else held.version


def test_a_version_the_merger_did_not_hear_is_recalled_from_the_recorder_when_its_robot_leaves() -> None:
    endpoint = free_loopback_endpoint()
    merger_bus = open_zenoh(ZenohOptions(listen=(endpoint,), fleet=KEYS.fleet))
    others = [open_zenoh(ZenohOptions(connect=(endpoint,), fleet=KEYS.fleet)) for _ in range(2)]
    recorder_bus, robot_bus = others
    recorder = Recorder(RecordingWriter(io.BytesIO()), KEYS)
    svc = MergerService(merger_bus, Merger(KEYS))
    try:
        with RecorderService(recorder_bus, recorder, KEYS):
            svc.start()
            tokens = {r: robot_bus.declare_liveliness(KEYS.alive(r)) for r in ("r1", "r2")}
            # (a live merger takes maps of robots whose token it has seen; the subscription may
            # reach the robots' session a moment after the merger starts: sent until taken)
            assert _until(svc, lambda: set(svc.merger.robots) == {"r1", "r2"})

            def both_held() -> bool:
                for robot in ("r1", "r2"):
                    robot_bus.publish(KEYS.localmap(robot), _submap(robot, 0, BOX).to_msgpack())
                return _version(svc, "r1/0/0") == 0 and _version(svc, "r2/0/0") == 0

            assert _until(svc, both_held)
            # r1's last version, with a fourth wall: the recorder has it, the merger never heard
            # it (as when the bus lost it on the way there)
            closed = np.vstack([BOX, [[0.0, 3.0, 0.0, 0.0]]])
            recorder.feed(KEYS.localmap("r1"), _submap("r1", 1, closed, final=True).to_msgpack(), time.time_ns())
            for robot in ("r1", "r2"):  # both leave; r2 left nothing unheard
                tokens[robot].close()
            assert _until(svc, lambda: _version(svc, "r1/0/0") == 1), "r1's last version was never taken"
            assert len(svc.merger.submaps["r1/0/0"].segments) == 4
            # r2's recalled version was the one held: dropped as stale, nothing said
            assert _until(svc, lambda: svc._recalling is None and not svc.run_once())
            assert _version(svc, "r2/0/0") == 0 and svc.recalled_at_leave == 1
    finally:
        svc.close()
        for bus in (*others, merger_bus):
            bus.close()
