"""The live ROS 2 source over real zenoh sessions on loopback: a robot's topics as rmw_zenoh puts them."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from fleetmap.agents.agent import Agent
from fleetmap.agents.process import run_agent
from fleetmap.agents.ros2_source import Ros2LiveSource, Ros2Topics
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.memory_bus import InMemoryBus
from fleetmap.shared.io.messages import decode
from fleetmap.shared.io.ros2_node import Ros2Node
from fleetmap.shared.io.sources import SourceScan
from fleetmap.shared.io.zenoh_bus import ZenohBus

from tests.bus_helpers import WAIT, Inbox, open_zenoh_pair

T = wire.typestore().types
KEYS = FleetKeys("t")


def header(t: float, frame: str) -> object:
    sec = int(t)
    return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](sec, round((t - sec) * 1e9)), frame)


def quaternion(yaw: float) -> object:
    return T["geometry_msgs/msg/Quaternion"](0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def laser_scan(t: float, ranges: list[float], frame: str = "r1/laser") -> object:
    return T[wire.LASER_SCAN](
        header(t, frame), -math.pi / 2, math.pi / 2, math.pi / (len(ranges) - 1), 0.0, 0.1, 0.1, 8.0,
        np.array(ranges, dtype=np.float32), np.zeros(0, dtype=np.float32),
    )  # fmt: skip


def odometry(t: float, x: float, yaw: float) -> object:
    vector = T["geometry_msgs/msg/Vector3"]
    pose = T["geometry_msgs/msg/Pose"](T["geometry_msgs/msg/Point"](x, 0.0, 0.0), quaternion(yaw))
    twist = T["geometry_msgs/msg/Twist"](vector(1.0, 0.0, 0.0), vector(0.0, 0.0, 0.5))
    return T[wire.ODOMETRY](
        header(t, "r1/odom"),
        "r1/base_link",
        T["geometry_msgs/msg/PoseWithCovariance"](pose, np.zeros(36)),
        T["geometry_msgs/msg/TwistWithCovariance"](twist, np.zeros(36)),
    )


def mounting() -> object:
    transform = T["geometry_msgs/msg/Transform"](T["geometry_msgs/msg/Vector3"](0.2, 0.0, 0.1), quaternion(0.0))
    stamped = T["geometry_msgs/msg/TransformStamped"](header(0.0, "r1/base_link"), "r1/laser", transform)
    return T[wire.TF_MESSAGE]([stamped])


@contextmanager
def live_source(robot_bus: ZenohBus, agent_bus: ZenohBus, topics: Ros2Topics) -> Iterator[tuple[Ros2LiveSource, list]]:
    """The source iterating on a thread of its own into a list, stopped and joined at the end."""
    stop = threading.Event()
    source = Ros2LiveSource(agent_bus.session, topics, stop, "r1")
    got: list[SourceScan] = []
    thread = threading.Thread(target=lambda: got.extend(source), daemon=True)
    thread.start()
    try:
        assert source.ready.wait(WAIT)
        yield source, got
    finally:
        stop.set()
        thread.join(WAIT)
        assert not thread.is_alive()


def wait_for(predicate, timeout: float = WAIT) -> bool:  # type: ignore[no-untyped-def]
    done = threading.Event()
    for _ in range(int(timeout / 0.02)):
        if predicate():
            return True
        done.wait(0.02)
    return predicate()


def sync(robot: ZenohBus, source: Ros2LiveSource) -> None:
    """Return once the robot's session sees the source's subscription tokens (so its subscribers)."""
    seen = threading.Event()
    watch = robot.session.liveliness().declare_subscriber(
        f"@ros2_lv/{source.topics.domain}/**/MS/**", lambda s: seen.set(), history=True
    )
    try:
        assert seen.wait(WAIT), "the source's subscriptions never showed"
    finally:
        watch.undeclare()


def test_scans_come_with_the_robots_stamps_and_odometry_on_the_laser_mounted_from_tf_static():
    robot_bus, agent_bus = open_zenoh_pair()
    topics = Ros2Topics.of("/r1", domain=7)
    with robot_bus, agent_bus, Ros2Node(robot_bus.session, "robot", "/r1", domain=7) as node:
        # published before the agent listens: transient local, as tf2's static broadcaster does
        node.publisher(topics.tf_static, wire.TF_MESSAGE, wire.TF_STATIC).publish(mounting())
        odom = node.publisher(topics.odom, wire.ODOMETRY, wire.Qos(depth=10))
        scan = node.publisher(topics.scan, wire.LASER_SCAN, wire.SENSOR_DATA)
        with live_source(robot_bus, agent_bus, topics) as (source, got):
            sync(robot_bus, source)
            assert wait_for(lambda: source.received[topics.tf_static] == 1), "tf_static's history never came"
            stamps = [1.7e9 + 0.1 * k for k in range(1, 6)]
            for k in range(0, 30):
                t = 1.7e9 + 0.02 * k
                odom.publish(odometry(t, 0.02 * k, 0.01 * k))
                if any(abs(t - s) < 1e-6 for s in stamps):
                    scan.publish(laser_scan(t, [2.0] * 181))
            assert wait_for(lambda: len(got) == 5)
    assert [s.stamp for s in got] == pytest.approx(stamps, abs=1e-6)
    assert [s.index for s in got] == [0, 1, 2, 3, 4]
    for s in got:
        k = (s.stamp - 1.7e9) / 0.02
        laser = Transform2D(0.02 * k, 0.0, 0.01 * k).compose(Transform2D(0.2, 0.0, 0.0))
        assert s.odometry is not None
        assert s.odometry.distance(laser)[0] < 1e-6 and s.odometry.distance(laser)[1] < 1e-6
        np.testing.assert_allclose(s.scan.ranges, 2.0)
    assert not source.dropped


def test_bad_samples_are_dropped_counted_and_named_and_good_ones_still_come(caplog):
    robot_bus, agent_bus = open_zenoh_pair()
    topics = Ros2Topics.of("r1", domain=8)
    scan_key = wire.data_key(8, topics.scan, wire.LASER_SCAN)
    with robot_bus, agent_bus, Ros2Node(robot_bus.session, "robot", "/r1", domain=8) as node:
        scan = node.publisher(topics.scan, wire.LASER_SCAN, wire.SENSOR_DATA)
        text = node.publisher(topics.scan, "std_msgs/msg/String", wire.Qos())  # a topic of the wrong type
        with live_source(robot_bus, agent_bus, topics) as (source, got):
            sync(robot_bus, source)
            good = wire.encode(laser_scan(10.0, [2.0] * 181), wire.LASER_SCAN)
            robot_bus.session.put(scan_key, good)  # no attachment
            scan.publish_cdr(b"\x00\x01\x00\x00garbage")  # does not decode
            text.publish(T["std_msgs/msg/String"]("hello"))
            scan.publish(laser_scan(11.0, [2.0, -1.0] + [2.0] * 179))  # a negative range
            scan.publish(laser_scan(12.0, [math.nan] * 181))  # nothing but NaN
            scan.publish(laser_scan(13.0, [2.0, math.nan] + [2.0] * 179))  # a NaN beam: no return
            scan.publish(laser_scan(12.5, [2.0] * 181))  # before the previous one
            scan.publish(laser_scan(14.0, [2.0] * 181))
            assert wait_for(lambda: len(got) == 2 and sum(source.dropped.values()) == 6)
    assert [s.stamp for s in got] == [13.0, 14.0]
    assert math.isnan(got[0].scan.ranges[1])
    name = "/r1/scan"
    assert source.dropped == {
        (name, "no rmw_zenoh attachment"): 1,
        (name, "undecodable"): 1,
        (name, "not a sensor_msgs/msg/LaserScan"): 1,
        (name, "negative ranges"): 1,
        (name, "no reading (every range NaN)"): 1,
        (name, "stamp not after the previous one"): 1,
    }
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(w.startswith("/r1/scan: dropped: negative ranges") for w in warnings)
    assert any("std_msgs::msg::dds_::String_" in w for w in warnings)


def test_without_odometry_a_scan_goes_on_without_after_a_short_wait():
    robot_bus, agent_bus = open_zenoh_pair()
    topics = Ros2Topics.of("", domain=9)
    with robot_bus, agent_bus, Ros2Node(robot_bus.session, "robot", domain=9) as node:
        scan = node.publisher(topics.scan, wire.LASER_SCAN, wire.SENSOR_DATA)
        with live_source(robot_bus, agent_bus, topics) as (source, got):
            sync(robot_bus, source)
            scan.publish(laser_scan(5.0, [3.0] * 181, "laser"))
            assert wait_for(lambda: len(got) == 1)
    assert got[0].odometry is None and got[0].stamp == 5.0


def clocked_source(
    step: float,
) -> tuple[Ros2Topics, Ros2LiveSource, Callable[[str, str, object], list[SourceScan]], list[float]]:
    """A source without a session on a clock the test moves (``now[0]``), and ``feed(topic,
    typename, message)``, which hands it a sample as the router would, ``step`` seconds after the last."""
    topics = Ros2Topics.of("r1", domain=3)
    now = [100.0]
    source = Ros2LiveSource(None, topics, threading.Event(), "r1", clock=lambda: now[0])  # type: ignore[arg-type]
    attachment = wire.Attachment(1, 0, bytes(16)).pack()

    def feed(topic: str, typename: str, message: object) -> list[SourceScan]:
        now[0] += step
        return source.feed(topic, wire.data_key(3, topic, typename), wire.encode(message, typename), attachment)

    return topics, source, feed, now


def test_odometry_heard_late_on_a_busy_machine_still_goes_with_its_scan():
    # the agent hears the robot's samples when its machine lets it: here the scan, then a second of
    # its own time and another sample (a tf), and only then the odometry at the scan's stamp. The
    # robot's clock has not moved on, so the odometry is not late: the scan waits and gets it
    topics, source, feed, now = clocked_source(0.0)
    assert feed(topics.scan, wire.LASER_SCAN, laser_scan(20.0, [2.0] * 181)) == []
    now[0] += 1.0
    assert feed(topics.tf, wire.TF_MESSAGE, T[wire.TF_MESSAGE]([])) == []
    got = feed(topics.odom, wire.ODOMETRY, odometry(20.0, 1.0, 0.0))
    assert len(got) == 1 and got[0].odometry is not None
    # a robot whose odometry stopped: its next scans go without, once its own clock is past the wait
    got = [s for t in (21.0, 21.2, 21.4, 21.6) for s in feed(topics.scan, wire.LASER_SCAN, laser_scan(t, [2.0] * 181))]
    assert [s.stamp for s in got] == [21.0] and got[0].odometry is None
    assert not source.dropped


def test_odometry_behind_the_scans_on_a_busy_machine_still_goes_with_its_scan():
    # the robot publishes each scan's odometry just before it, at five times its pace; on a busy
    # machine the agent hears the odometry topic behind the scan topic: the scan at 20.0, then
    # scans 0.6 s of the robot's time on, while the readings still coming are older than the scan.
    # The odometry is behind, not stopped: the scan waits for its reading
    topics, _source, feed, _now = clocked_source(0.01)
    assert feed(topics.odom, wire.ODOMETRY, odometry(19.6, 0.0, 0.0)) == []
    got = feed(topics.scan, wire.LASER_SCAN, laser_scan(20.0, [2.0] * 181))
    for t, behind in ((20.2, 19.7), (20.4, 19.8), (20.6, 19.9)):
        got += feed(topics.scan, wire.LASER_SCAN, laser_scan(t, [2.0] * 181))
        got += feed(topics.odom, wire.ODOMETRY, odometry(behind, 0.0, 0.0))
    got += feed(topics.odom, wire.ODOMETRY, odometry(20.0, 1.0, 0.0))
    assert [s.stamp for s in got][:1] == [20.0] and got[0].odometry is not None
    assert abs(got[0].odometry.x - 1.0) < 1e-6


@contextmanager
def listening_source(domain: int) -> Iterator[tuple[Ros2Topics, threading.Event, Ros2LiveSource, Ros2Node, Callable]]:
    """A source subscribed on a real session but not yet iterating, a robot's node to publish
    with, and ``heard()``: returns once everything the robot published so far waits in the source's
    channels (a marker put after it came through the agent's session: one link keeps the order).
    The marker's publisher matches its subscriber before any test uses it: a put before the robot's
    session knows of the subscriber goes nowhere (it did, once, on a busy machine)."""
    robot_bus, agent_bus = open_zenoh_pair()
    topics = Ros2Topics.of("r1", domain=domain)
    stop = threading.Event()
    source = Ros2LiveSource(agent_bus.session, topics, stop, "r1", clock=lambda: 100.0)
    marks: list[int] = []
    came = threading.Condition()

    def on_mark(sample: object) -> None:
        with came:
            marks.append(1)
            came.notify_all()

    with robot_bus, agent_bus, Ros2Node(robot_bus.session, "robot", "/r1", domain=domain) as node:
        source.listen()
        mark = agent_bus.session.declare_subscriber(f"test/mark/{domain}", on_mark)
        marker = robot_bus.session.declare_publisher(f"test/mark/{domain}")
        sync(robot_bus, source)
        assert wait_for(lambda: marker.matching_status.matching), "the marker's subscriber never showed"

        def heard() -> None:
            wanted = len(marks) + 1
            marker.put(b"")
            with came:
                assert came.wait_for(lambda: len(marks) >= wanted, WAIT), "the marker never came"

        try:
            yield topics, stop, source, node, heard
        finally:
            stop.set()
            marker.undeclare()
            mark.undeclare()


def test_odometry_heard_behind_later_scans_still_goes_with_its_scan():
    # a busy machine: the agent's loop comes back to its channels to find the scan at 20.0, scans
    # 0.6 s of the robot's time after it, and only then the odometry at 20.0, all heard at once.
    # Taken and released one sample at a time, the scan went without its reading (the robot's
    # clock said the odometry was late); everything heard is taken first
    with listening_source(5) as (topics, _stop, source, node, heard):
        odom = node.publisher(topics.odom, wire.ODOMETRY, wire.Qos(depth=10))
        scan = node.publisher(topics.scan, wire.LASER_SCAN, wire.SENSOR_DATA)
        odom.publish(odometry(19.9, 0.0, 0.0))
        for t in (20.0, 20.2, 20.4, 20.6):
            scan.publish(laser_scan(t, [2.0] * 181))
        odom.publish(odometry(20.0, 1.0, 0.0))
        heard()
        scans = iter(source)
        first = next(scans)
        scans.close()  # type: ignore[attr-defined]
    assert first.stamp == 20.0 and first.odometry is not None and abs(first.odometry.x - 1.0) < 1e-6


def test_a_stop_while_scans_wait_for_odometry_or_to_be_taken_still_puts_every_one_on_the_bus():
    # SIGTERM comes while the robot's last scans are in the agent: one waits for the odometry at
    # its stamp, one is heard and not yet taken. Neither may be lost: the source gives them back as
    # it ends, and the run tracks and publishes them before the final local maps
    with listening_source(4) as (topics, stop, source, node, heard):
        odom = node.publisher(topics.odom, wire.ODOMETRY, wire.Qos(depth=10))
        scan = node.publisher(topics.scan, wire.LASER_SCAN, wire.SENSOR_DATA)
        odom.publish(odometry(19.9, 0.0, 0.0))
        scan.publish(laser_scan(20.0, [2.0] * 181))
        heard()
        released = source._take_heard(source._declared[1])  # type: ignore[index]
        assert released == 2 and list(source._released()) == []  # the scan waits for its odometry
        scan.publish(laser_scan(20.2, [2.0] * 181))  # heard, not yet taken
        heard()
        stop.set()
        bus = InMemoryBus()
        scans = Inbox()
        bus.peer().subscribe(KEYS.scan("r1"), scans)
        summary = run_agent(
            source, Agent("r1"), bus, KEYS, speed=0, stop=stop, start_after_known=False, source_ends_at_stop=True
        )  # as `fleetmap agent --ros2` runs it
    assert summary.stopped and summary.scans == 2
    got = [decode(payload) for _, payload in scans.items]
    assert [(m.index, m.stamp) for m in got] == [(0, 20.0), (1, 20.2)]  # type: ignore[attr-defined]


def test_topic_names_and_domains_arechecked_scan():
    t = Ros2Topics.of("/robot_a", "front/scan", "/odom", 3)
    assert (t.scan, t.odom, t.tf, t.tf_static) == ("/robot_a/front/scan", "/odom", "/robot_a/tf", "/robot_a/tf_static")
    with pytest.raises(Exception, match="domain"):
        Ros2Topics.of("", domain=500)


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["agent", "--robot", "r1", "--ros2", "--domain", "300"], "--domain: must be a ROS domain id"),
        (["agent", "--robot", "r1", "--ros2", "--speed", "2"], "--speed: does not apply to --ros2"),
        (["agent", "--robot", "r1", "--ros2", "--carmen", "x.clf"], "not allowed with argument"),
        (["agent", "--robot", "r1", "--scenario", "department", "--namespace", "r1"], "apply to --ros2 only"),
        (["agent", "--robot", "r1", "--ros2", "--topic", "/scan"], "apply to --ros2-bag only"),
        (["merger", "--domain", "3"], "--domain: applies to --ros2 only"),
        (["merger", "--ros2", "--domain", "-1"], "must be a ROS domain id"),
    ],
)
def test_bad_ros2_flags_exit_2_with_one_line_before_any_session(argv, says, capsys):
    from fleetmap.cli import main

    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = int(exc.code or 0)
    assert code == 2
    assert says in capsys.readouterr().err


def test_a_ros2_session_is_a_client_of_the_router_unless_told_otherwise():
    from fleetmap.shared.io.ros2_node import ros2_options
    from fleetmap.shared.io.zenoh_config import ZenohOptions

    assert ros2_options(ZenohOptions(connect=("tcp/10.0.0.5:7447",))).mode == "client"
    assert ros2_options(ZenohOptions(mode="peer")).mode == "peer"
    assert ros2_options(ZenohOptions(config_file="z.json5")).mode is None  # the file says


SLOW_HANDLER = """
import signal, threading, time
import zenoh
from fleetmap.agents.ros2_source import POLL, Ros2LiveSource, Ros2Topics
stop = threading.Event()
with zenoh.open(zenoh.Config()) as session:
    source = Ros2LiveSource(session, Ros2Topics.of("r1", domain=42), stop, "r1")
    def on_term(signum, frame):
        time.sleep(4 * POLL)  # longer than the source's poll, as a loaded machine can make any step
        stop.set()
    signal.signal(signal.SIGTERM, on_term)
    main = threading.get_ident()
    threading.Timer(0.5, lambda: signal.pthread_kill(main, signal.SIGTERM)).start()
    got = list(source)
print("stopped", len(got), flush=True)
"""


@pytest.mark.slow
def test_the_source_ends_at_stop_even_when_the_signal_took_longer_than_its_poll():
    # SIGTERM comes while the source waits for a sample that never comes (the robot's run is over),
    # and its handler runs longer than the source's poll. A timed SimpleQueue.get (CPython 3.11 and
    # 3.12) interrupted that way waits forever once its deadline has passed: the agent never
    # stopped, and SIGKILL was the only way out. The source waits on the stop event instead
    done = subprocess.run([sys.executable, "-c", SLOW_HANDLER], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "stopped 0" in done.stdout
