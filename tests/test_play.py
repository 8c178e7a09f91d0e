"""``fleetmap play --ros2``'s pacing and topics, on a zenoh session of its own (the wire is tested live)."""

from __future__ import annotations

import threading

import pytest
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.ros2_node import Ros2Node
from fleetmap.shared.io.sources import Ros2BagSource
from fleetmap.shared.io.zenoh_config import ZenohOptions

from fleetmap.commands.play import play_bag
from tests.agents.test_sources import write_robot_bag
from tests.bus_helpers import open_zenoh


class SteppedClock(threading.Event):
    """A stop event whose waits move a clock instead of sleeping."""

    def __init__(self) -> None:
        super().__init__()
        self.now = 100.0
        self.waits: list[float] = []

    def wait(self, timeout: float | None = None) -> bool:
        assert timeout is not None
        self.waits.append(timeout)
        self.now += timeout
        return False

    def clock(self) -> float:
        return self.now


@pytest.mark.parametrize("speed", [1.0, 4.0])
def test_a_bag_is_played_at_its_log_times_pace_on_its_topics_under_the_namespace(tmp_path, speed):
    bag = tmp_path / "robot.mcap"
    write_robot_bag(bag, "odom")  # /tf_static at 1 ns, /odom at 50 Hz from 50 s, 5 scans
    stop = SteppedClock()
    with open_zenoh(ZenohOptions(listen=("tcp/127.0.0.1:0",))) as bus, Ros2Node(bus.session, "play", "/r1") as node:
        summary = play_bag(Ros2BagSource(bag), node, "r1", speed, stop, stop.clock)
    assert summary.published == {"/r1/tf_static": 1, "/r1/odom": 60, "/r1/scan": 5}
    assert not summary.stopped
    last = 50.0 + 0.02 * 59  # the last odometry's log time (s); the first message's (tf_static) is 1 ns
    assert stop.now - 100.0 == pytest.approx((last - 1e-9) / speed, abs=1e-6)


def test_a_bad_speed_is_refused(tmp_path):
    bag = tmp_path / "robot.mcap"
    write_robot_bag(bag, "tf")
    with (
        open_zenoh(ZenohOptions(listen=("tcp/127.0.0.1:0",))) as bus,
        Ros2Node(bus.session, "play") as node,
        pytest.raises(BadInput, match="--speed"),
    ):
        play_bag(Ros2BagSource(bag), node, "", -1.0, threading.Event())
