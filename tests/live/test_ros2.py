"""fleetmap and ROS 2 over rmw_zenoh, against a peer written by other people: zenoh-ros2-sdk.

The SDK plays the ROS 2 robot (LaserScan, Odometry, tf_static from a real log) and the ROS 2
listener. It loads ROS 2 message definitions from git clones in its cache folder: the Jazzy
definitions in ``tests/data/ros2`` are unpacked into a temporary one. The SDK holds one Zenoh
session per process, opened at the router of its first call, so the tests of this module share one
router and keep apart by ROS domain.

Every test starts the real programs, picks free ports, waits on events with bounded timeouts and
always stops its processes.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tarfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import LocalMap, Scan, decode
from fleetmap.shared.io.sources import CarmenSource, Ros2BagSource, SourceScan
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

from fleetmap.runner import _Child
from tests.agents.test_sources import write_robot_bag
from tests.bus_helpers import Inbox, eventually

pytestmark = pytest.mark.slow
sdk = pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk (the test extra) is not installed")

WAIT = 30.0
MSGS = Path(__file__).resolve().parents[1] / "data" / "ros2" / "ros2-msgs-jazzy.tar.gz"
TF_MESSAGE_MSG = "geometry_msgs/TransformStamped[] transforms\n"
"""tf2_msgs/msg/TFMessage's definition (ros2/geometry2, which the packed definitions do not hold)."""
SPEED = 5.0
"""The SDK robot publishes a log at this many times its pace."""
MOUNT = Transform2D(0.2, 0.05, 0.1)
"""The laser's mounting on the base that the SDK robot publishes on tf_static."""


def fleetmap_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "fleetmap", *args]


class Processes:
    """Programs started by a test, killed (if still running) at the end."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, name: str, *args: str) -> subprocess.Popen[bytes]:
        log = open(self.folder / f"{name}.log", "wb")  # noqa: SIM115 (closed with the process)
        p = subprocess.Popen(fleetmap_cmd(*args), stdout=log, stderr=subprocess.STDOUT)
        log.close()
        self.procs.append(p)
        return p

    def log(self, name: str) -> str:
        return (self.folder / f"{name}.log").read_text()

    def stopped(self, p: subprocess.Popen[bytes], name: str) -> int | None:
        """SIGTERM, and ``p``'s exit code once it stopped, as the session runner stops a service
        (``fleetmap.runner``): one that does not stop within ``WAIT`` writes its threads' stacks to
        its log (SIGUSR1) and is killed, so the failure's log says where it was stuck."""
        return _Child(name, [str(a) for a in p.args], self.folder / f"{name}.log", popen=p).stop(WAIT)

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait(10)


@pytest.fixture(scope="module")
def router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A fleetmap router on a free port, the SDK's message definitions unpacked, and the SDK's
    session closed at the end: the router's endpoint."""
    folder = tmp_path_factory.mktemp("ros2")
    cache = folder / "sdk-cache"
    cache.mkdir()
    with tarfile.open(MSGS) as tar:
        tar.extractall(cache, filter="data")
    previous = os.environ.get("ZENOH_ROS2_SDK_CACHE")
    os.environ["ZENOH_ROS2_SDK_CACHE"] = str(cache)
    endpoint = free_loopback_endpoint()
    procs = Processes(folder)
    try:
        procs.start("router", "router", "--listen", endpoint)
        deadline = time.monotonic() + WAIT
        while True:  # the router may take a moment to listen
            try:
                ZenohBus.open(ZenohOptions(mode="client", connect=(endpoint,), connect_wait=0)).close()
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                threading.Event().wait(0.2)
        yield endpoint
    finally:
        if sdk.ZenohSession._instance is not None:
            sdk.ZenohSession._instance.close()
        procs.stop()
        if previous is None:
            os.environ.pop("ZENOH_ROS2_SDK_CACHE", None)
        else:
            os.environ["ZENOH_ROS2_SDK_CACHE"] = previous


def sdk_args(endpoint: str, domain: int) -> dict[str, Any]:
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    return {"router_ip": host, "router_port": int(port), "domain_id": domain}


def client(endpoint: str) -> ZenohBus:
    return ZenohBus.open(ZenohOptions(mode="client", connect=(endpoint,), fleet="t"))


def fleet_flags(endpoint: str) -> list[str]:
    return ["--mode", "client", "--connect", endpoint, "--fleet", "t"]


def wait_for(predicate: Callable[[], bool], timeout: float = WAIT) -> bool:
    return eventually(predicate, timeout)


def wait_for_subscription(bus: ZenohBus, domain: int, topic: str) -> None:
    """Return once a subscription token for ``topic`` in ``domain`` shows on the bus (its
    subscriber, declared before it, is then known to the router too)."""
    seen = threading.Event()
    mangled = wire.mangle(topic)
    handle = bus.subscribe_liveliness(
        f"@ros2_lv/{domain}/**",
        lambda key: seen.set() if "/MS/" in key and f"/{mangled}/" in key else None,
        lambda key: None,
    )
    try:
        assert seen.wait(WAIT), f"no subscription to {topic} in domain {domain} showed"
    finally:
        handle.close()


class SdkRobot:
    """A ROS 2 robot written with the SDK: LaserScan on <ns>/scan, Odometry on <ns>/odom, the
    laser's mounting on <ns>/tf_static."""

    def __init__(self, endpoint: str, namespace: str, domain: int) -> None:
        where = sdk_args(endpoint, domain)
        # publishers first: the SDK opens its session at the router of its first call
        self.scan = sdk.ROS2Publisher(f"{namespace}/scan", wire.LASER_SCAN, **where)
        self.odom = sdk.ROS2Publisher(f"{namespace}/odom", wire.ODOMETRY, **where)
        self.tf_static = sdk.ROS2Publisher(
            f"{namespace}/tf_static", wire.TF_MESSAGE, msg_definition=TF_MESSAGE_MSG, **where
        )
        self.types = {name: sdk.get_message_class(name) for name in SDK_TYPES}
        self.namespace = namespace.strip("/")

    def header(self, t: float, frame: str) -> Any:
        sec = int(t)
        stamp = self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def quaternion(self, yaw: float) -> Any:
        return self.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))

    def publish_mounting(self) -> None:
        T = self.types
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=MOUNT.x, y=MOUNT.y, z=0.3),
            rotation=self.quaternion(MOUNT.theta),
        )
        stamped = T["geometry_msgs/msg/TransformStamped"](
            header=self.header(0.0, f"{self.namespace}/base_link"),
            child_frame_id=f"{self.namespace}/laser",
            transform=transform,
        )
        self.tf_static.publish(transforms=[stamped])

    def publish(self, s: SourceScan, ranges: np.ndarray | None = None) -> None:
        """The base's odometry at the scan (where the log's laser pose puts the base, the laser
        MOUNT on it), then the scan."""
        T = self.types
        assert s.odometry is not None
        base = s.odometry.compose(MOUNT.inverse())
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=base.x, y=base.y, z=0.0),
            orientation=self.quaternion(base.theta),
        )
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        self.odom.publish(
            header=self.header(s.stamp, f"{self.namespace}/odom"),
            child_frame_id=f"{self.namespace}/base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
            ),
        )
        # the log's no-return readings as inf (REP 117); ``ranges`` as they are
        values = np.where(np.isfinite(s.scan.ranges), s.scan.ranges, np.inf) if ranges is None else ranges
        n = len(values)
        self.scan.publish(
            header=self.header(s.stamp, f"{self.namespace}/laser"),
            angle_min=s.scan.angle_min,
            angle_max=s.scan.angle_min + (n - 1) * s.scan.angle_increment,
            angle_increment=s.scan.angle_increment,
            time_increment=0.0,
            scan_time=0.0,
            range_min=0.0,
            range_max=s.scan.range_max if math.isfinite(s.scan.range_max) else 100.0,
            ranges=np.asarray(values, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32),
        )

    def wait_until_heard(self) -> None:
        """Return once the robot's own session knows a subscriber of its scans and its odometry:
        a client's publisher sends nothing until the router has told it of one, which can come
        after the subscriber's token showed on another session (:func:`wait_for_subscription`)."""
        for publisher in (self.scan, self.odom):
            heard = threading.Event()
            listener = publisher.pub.declare_matching_listener(
                lambda status, heard=heard: heard.set() if status.matching else None
            )
            try:
                if not publisher.pub.matching_status.matching:
                    assert heard.wait(WAIT), f"the robot's {publisher.topic} publisher heard of no subscriber"
            finally:
                listener.undeclare()

    def play(self, scans: list[SourceScan]) -> None:
        """Publish ``scans`` at SPEED times the log's pace, as a robot would (a burst overflows the
        SDK's publishers, which drop when congested)."""
        pause = threading.Event()
        started = time.monotonic()
        for s in scans:
            pause.wait(max(0.0, started + (s.stamp - scans[0].stamp) / SPEED - time.monotonic()))
            self.publish(s)

    def close(self) -> None:
        for p in (self.scan, self.odom, self.tf_static):
            p.close()


SDK_TYPES = (
    "builtin_interfaces/msg/Time",
    "std_msgs/msg/Header",
    "geometry_msgs/msg/Quaternion",
    "geometry_msgs/msg/Vector3",
    "geometry_msgs/msg/Point",
    "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/PoseWithCovariance",
    "geometry_msgs/msg/Twist",
    "geometry_msgs/msg/TwistWithCovariance",
    "geometry_msgs/msg/Transform",
    "geometry_msgs/msg/TransformStamped",
)


def scans_of(inbox: Inbox) -> list[Scan]:
    return [m for _, payload in inbox.items if isinstance(m := decode(payload), Scan)]  # type: ignore[arg-type]


SCANS = 200


def test_an_agent_maps_a_real_log_published_by_a_ros2_robot_on_rmw_zenoh(
    router: str, csail_start: Path, tmp_path: Path
) -> None:
    # zenoh-ros2-sdk publishes mit-csail's first scans with their odometry and the laser's mounting;
    # `fleetmap agent --ros2` hears them through the router and puts the robot on fleetmap's bus
    logged = list(CarmenSource(csail_start, stop=SCANS))
    keys = FleetKeys("t")
    procs = Processes(tmp_path)
    robot = SdkRobot(router, "/r1", 11)
    try:
        with client(router) as bus:
            scans, maps = Inbox(), Inbox()
            bus.subscribe(keys.scan("r1"), scans)
            bus.subscribe(keys.localmap("r1"), maps)
            agent = procs.start(
                "agent", "agent", "--robot", "r1", "--ros2", "--namespace", "r1", "--domain", "11",
                "--wait-for-listener", str(WAIT), *fleet_flags(router),
            )  # fmt: skip
            wait_for_subscription(bus, 11, "/r1/tf_static")
            robot.wait_until_heard()
            robot.publish_mounting()
            robot.play(logged)
            assert scans.wait_for(SCANS, 120), f"{len(scans.items)} of {SCANS} scans reached the bus"
            assert procs.stopped(agent, "agent") == 0, procs.log("agent")[-6000:]
            assert wait_for(lambda: any(decode(p).final for _, p in maps.items)), "no final submap"  # type: ignore[attr-defined]
    finally:
        robot.close()
        procs.stop()
    got = scans_of(scans)
    # the robot's own stamps and the log's order, every scan once
    assert [m.index for m in got] == list(range(SCANS))
    assert [m.stamp for m in got] == pytest.approx([s.stamp for s in logged], abs=1e-6)
    # the odometry the agent used is the base's from nav_msgs/Odometry on the laser mounted by
    # tf_static: the log's laser odometry again (the base's alone is 0.2 m and 0.1 rad off)
    for m, s in zip(got, logged, strict=True):
        assert s.odometry is not None and m.odometry is not None
        assert m.odometry.distance(s.odometry)[0] < 1e-6 and m.odometry.distance(s.odometry)[1] < 1e-6
    assert sum(m.submap is not None for m in got) >= 0.95 * SCANS, "the agent's tracking placed too few scans"
    submaps = [LocalMap.from_msgpack(p) for _, p in maps.items]  # type: ignore[arg-type]
    assert submaps and max(len(m.segments) for m in submaps) > 20
    out = procs.log("agent")
    assert f"agent r1 stopped: {SCANS} scans" in out
    assert "0 dropped" in out


def test_bad_samples_are_dropped_counted_and_named_while_the_agent_goes_on(
    router: str, csail_start: Path, tmp_path: Path
) -> None:
    logged = list(CarmenSource(csail_start, stop=12))
    keys = FleetKeys("t")
    procs = Processes(tmp_path)
    robot = SdkRobot(router, "/r2", 12)
    scan_key = wire.data_key(12, "/r2/scan", wire.LASER_SCAN)
    try:
        with client(router) as bus:
            scans = Inbox()
            bus.subscribe(keys.scan("r2"), scans)
            bus.subscribe(keys.localmap("r2"), Inbox())  # the agent's first scan waits for it to be heard
            agent = procs.start(
                "agent", "agent", "--robot", "r2", "--ros2", "--namespace", "/r2", "--domain", "12",
                "--wait-for-listener", str(WAIT), *fleet_flags(router),
            )  # fmt: skip
            wait_for_subscription(bus, 12, "/r2/scan")
            robot.wait_until_heard()
            robot.play(logged[:4])
            assert scans.wait_for(4, WAIT)
            attachment = wire.Attachment(1, time.time_ns(), bytes(16)).pack()
            bus.session.put(scan_key, b"\x00\x01\x00\x00 not a laser scan", attachment=attachment)
            bus.session.put(scan_key, b"\x00\x01\x00\x00" + bytes(200))  # no attachment
            text = wire.data_key(12, "/r2/scan", "std_msgs/msg/String")
            hello = wire.encode(wire.typestore().types["std_msgs/msg/String"]("hi"), "std_msgs/msg/String")
            bus.session.put(text, hello, attachment=attachment)
            nan = np.full(len(logged[4].scan.ranges), np.nan)
            robot.publish(logged[4], nan)  # nothing but NaN
            negative = np.array(logged[5].scan.ranges, dtype=float)
            negative[3] = -2.0
            robot.publish(logged[5], negative)
            robot.publish(logged[2])  # a stamp gone back
            robot.play(logged[6:])
            assert scans.wait_for(10, WAIT), f"the agent stopped at {len(scans.items)} scans"
            assert agent.poll() is None
            assert procs.stopped(agent, "agent") == 0, procs.log("agent")[-6000:]
    finally:
        robot.close()
        procs.stop()
    got = scans_of(scans)
    assert [m.stamp for m in got] == pytest.approx([s.stamp for s in logged[:4] + logged[6:]], abs=1e-6)
    out = procs.log("agent")
    for why in (
        "undecodable",
        "no rmw_zenoh attachment",
        "not a sensor_msgs/msg/LaserScan",
        "no reading (every range NaN)",
        "negative ranges",
        "stamp not after the previous one",
    ):
        assert out.count(f"/r2/scan: dropped: {why}") == 1, why
    # the scan gone back came with its odometry, gone back too
    assert out.count("/r2/odom: dropped: stamp not after the previous one") == 1
    assert "7 dropped" in out


def bag_messages(bag: Path) -> dict[str, list[Any]]:
    source = Ros2BagSource(bag)
    out: dict[str, list[Any]] = {}
    for topic, _, message in source.messages(sorted(source.topic_types)):
        out.setdefault(topic, []).append(message)
    return out


@pytest.mark.parametrize("odometry", ["odom", "tf"])
def test_a_bag_played_on_ros2_topics_reaches_a_ros2_subscriber_as_it_is_in_the_bag(
    router: str, tmp_path: Path, odometry: str
) -> None:
    bag = tmp_path / "robot.mcap"
    write_robot_bag(bag, odometry)
    expected = bag_messages(bag)
    domain = 13 if odometry == "odom" else 14
    where = sdk_args(router, domain)
    inboxes = {topic: Inbox() for topic in expected}
    types = {"/scan": wire.LASER_SCAN, "/odom": wire.ODOMETRY, "/tf": wire.TF_MESSAGE, "/tf_static": wire.TF_MESSAGE}
    subscribers = [
        sdk.ROS2Subscriber(
            f"/p{topic}",
            types[topic],
            inboxes[topic],
            msg_definition=TF_MESSAGE_MSG if types[topic] == wire.TF_MESSAGE else None,
            **where,
        )
        for topic in expected
    ]
    # the SDK decodes a TFMessage only once it knows TransformStamped (its definition is not loaded
    # with TFMessage's given text)
    sdk.get_message_class("geometry_msgs/msg/TransformStamped")
    procs = Processes(tmp_path)
    attachments: dict[str, list[wire.Attachment]] = {}
    try:
        with client(router) as bus:
            for topic in expected:
                wait_for_subscription(bus, domain, f"/p{topic}")
            raw = bus.session.declare_subscriber(
                f"{domain}/p/**",
                lambda s: attachments.setdefault(str(s.key_expr), []).append(
                    wire.Attachment.unpack(s.attachment.to_bytes() if s.attachment is not None else None)
                ),
            )
            play = procs.start(
                "play", "play", str(bag), "--ros2", "--namespace", "p", "--domain", str(domain), "--speed", "0",
                "--connect", router,  # a client by default
            )  # fmt: skip
            assert play.wait(WAIT) == 0, procs.log("play")
            for topic, messages in expected.items():
                assert inboxes[topic].wait_for(len(messages), WAIT), f"{topic}: {len(inboxes[topic].items)} received"
            raw.undeclare()
    finally:
        for s in subscribers:
            s.close()
        procs.stop()
    for topic, messages in expected.items():
        received = [args[0] for args in inboxes[topic].items]
        assert len(received) == len(messages), topic
        for got, want in zip(received, messages, strict=True):
            assert_same(got, want)
    assert "play done: " in procs.log("play")
    # every sample with its rmw_zenoh attachment: each publisher counts from 1, one GID each
    assert {key.split("/")[2] for key in attachments} == {topic.strip("/") for topic in expected}
    for key, got in attachments.items():
        assert [a.sequence for a in got] == list(range(1, len(got) + 1)), key
        assert len({a.gid for a in got}) == 1
        topic = "/" + key.split("/")[2]
        assert key == wire.data_key(domain, "/p" + topic, types[topic])


def assert_same(got: Any, want: Any) -> None:
    """Two ROS messages (of different type stores) hold the same values, field by field."""
    if isinstance(want, np.ndarray):
        np.testing.assert_array_equal(np.asarray(got), want)
    elif isinstance(want, list):
        assert len(got) == len(want)
        for a, b in zip(got, want, strict=True):
            assert_same(a, b)
    elif hasattr(want, "__dataclass_fields__"):
        for name in want.__dataclass_fields__:
            assert_same(getattr(got, name), getattr(want, name))
    else:
        assert got == want


def test_a_ros2_viewer_started_after_the_map_gets_it_and_the_robots_poses_and_transforms(
    router: str, csail_start: Path, tmp_path: Path
) -> None:
    # `fleetmap merger --ros2` maps a CARMEN robot; an SDK subscriber to /map declared after the
    # map was published (transient local, as RViz or nav2's map server started later) still gets it
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile

    domain = 15
    where = sdk_args(router, domain)
    keys = FleetKeys("t")
    poses, transforms, late = Inbox(), Inbox(), Inbox()
    pose_sub = sdk.ROS2Subscriber("/r1/fleetmap/pose", wire.POSE_WITH_COVARIANCE_STAMPED, poses, **where)
    tf_sub = sdk.ROS2Subscriber("/tf", wire.TF_MESSAGE, transforms, msg_definition=TF_MESSAGE_MSG, **where)
    sdk.get_message_class("geometry_msgs/msg/TransformStamped")
    subscribers = [pose_sub, tf_sub]
    procs = Processes(tmp_path)
    raw_maps: list[Any] = []
    try:
        with client(router) as bus:
            scans, services = Inbox(), Inbox()
            bus.subscribe(keys.scan("r1"), scans)
            raw = bus.session.declare_subscriber(
                f"{domain}/map/*/*", lambda s: raw_maps.append(wire.decode(s.payload.to_bytes(), wire.OCCUPANCY_GRID))
            )
            bus.subscribe_liveliness(keys.all_services, services, lambda k: None)
            procs.start("merger", "merger", "--ros2", "--domain", str(domain), *fleet_flags(router))
            assert services.wait_until(lambda got: any("merger" in str(g) for g in got), WAIT)
            agent = procs.start(
                "agent", "agent", "--robot", "r1", "--carmen", str(csail_start), "--stop", "150", "--speed", "0",
                *fleet_flags(router),
            )  # fmt: skip
            assert agent.wait(120) == 0, procs.log("agent")[-3000:]
            assert wait_for(lambda: len(raw_maps) > 0, 60), "no map on /map"
            assert poses.wait_for(1, WAIT) and transforms.wait_for(1, WAIT)
            map_qos = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)
            subscribers.append(sdk.ROS2Subscriber("/map", wire.OCCUPANCY_GRID, late, qos=map_qos, **where))
            # the SDK queries the publishers' caches as it is made: the map is there when it returns
            assert late.items, "a subscriber that came after the map did not get it"
            raw.undeclare()
    finally:
        for s in subscribers:
            s.close()
        procs.stop()
    grid = late.items[0][0]
    assert grid.header.frame_id == "map"
    stamp = (grid.header.stamp.sec, grid.header.stamp.nanosec)
    same = [m for m in raw_maps if (m.header.stamp.sec, m.header.stamp.nanosec) == stamp]
    assert same, "the late subscriber's map is none of those published"
    assert (grid.info.width, grid.info.height) == (same[0].info.width, same[0].info.height)
    np.testing.assert_array_equal(np.asarray(grid.data), same[0].data)
    cells = np.asarray(grid.data)
    assert len(cells) == grid.info.width * grid.info.height and grid.info.resolution == pytest.approx(0.05)
    assert np.sum(cells == 100) > 100 and np.sum(cells == 0) > np.sum(cells == 100)
    # map -> r1/odom composed with the odometry at a scan is the robot's pose on /r1/fleetmap/pose
    odometry = {round(m.stamp, 6): m.odometry for m in scans_of(scans)}
    at = {(p.header.stamp.sec, p.header.stamp.nanosec): p.pose.pose for (p,) in poses.items}  # type: ignore[misc]
    checked = 0
    for (message,) in transforms.items:  # type: ignore[misc]
        for t in message.transforms:
            assert (t.header.frame_id, t.child_frame_id) == ("map", "r1/odom")
            stamp = (t.header.stamp.sec, t.header.stamp.nanosec)
            pose = at.get(stamp)
            odom = odometry.get(round(stamp[0] + stamp[1] * 1e-9, 6))
            if pose is None or odom is None:
                continue
            yaw = 2 * math.atan2(t.transform.rotation.z, t.transform.rotation.w)
            laser = Transform2D(t.transform.translation.x, t.transform.translation.y, yaw).compose(odom)
            published = Transform2D(
                pose.position.x, pose.position.y, 2 * math.atan2(pose.orientation.z, pose.orientation.w)
            )
            assert laser.distance(published)[0] < 1e-6 and laser.distance(published)[1] < 1e-6
            checked += 1
    assert checked > 10


def read_map_server(folder: Path) -> tuple[np.ndarray, tuple[float, float], float]:
    """(cells -1/0/100 with row 0 the southernmost, origin, resolution) of map.pgm + map.yaml."""
    meta = dict(line.split(": ", 1) for line in (folder / "map.yaml").read_text().splitlines() if ": " in line)
    origin = [float(v) for v in meta["origin"].strip("[]").split(",")]
    raw = (folder / "map.pgm").read_bytes()
    fields: list[bytes] = []
    at = 0
    while len(fields) < 4:  # P5, width, height, maxval; '#' comments between
        line_end = raw.index(b"\n", at)
        line = raw[at:line_end]
        at = line_end + 1
        if not line.startswith(b"#"):
            fields.extend(line.split())
    width, height = int(fields[1]), int(fields[2])
    pixels = np.frombuffer(raw[at : at + width * height], dtype=np.uint8).reshape(height, width)[::-1]
    cells = np.full(pixels.shape, -1, dtype=np.int8)
    cells[pixels == 254] = 0
    cells[pixels == 0] = 100
    return cells, (origin[0], origin[1]), float(meta["resolution"])


def agreement(live: Any, reference: tuple[np.ndarray, tuple[float, float], float]) -> tuple[float, int]:
    """The share of cells known in both grids that agree (free or occupied), and how many there are:
    ``live`` a nav_msgs/OccupancyGrid, laid on ``reference`` by the cells' centres (one frame)."""
    cells, origin, resolution = reference
    width, height = live.info.width, live.info.height
    data = np.asarray(live.data, dtype=np.int8).reshape(height, width)
    rows, cols = np.nonzero(data >= 0)
    x = live.info.origin.position.x + (cols + 0.5) * live.info.resolution
    y = live.info.origin.position.y + (rows + 0.5) * live.info.resolution
    r = np.floor((y - origin[1]) / resolution).astype(int)
    c = np.floor((x - origin[0]) / resolution).astype(int)
    inside = (r >= 0) & (r < cells.shape[0]) & (c >= 0) & (c < cells.shape[1])
    theirs = cells[r[inside], c[inside]]
    ours = data[rows[inside], cols[inside]]
    both = theirs >= 0
    return float(np.mean(ours[both] == theirs[both])), int(np.sum(both))


def test_a_real_log_through_ros2_end_to_end_gives_the_map_fleetmap_map_makes(
    router: str, csail_start: Path, tmp_path: Path
) -> None:
    # the SDK robot publishes mit-csail's scans and odometry at 5x; `fleetmap agent --ros2` and
    # `fleetmap merger --ros2` map it; the map a ROS 2 subscriber gets on /map is the occupancy grid
    # `fleetmap map` makes of the same log, cell for cell where both know the cell
    offline = tmp_path / "offline"
    done = subprocess.run(
        fleetmap_cmd("map", str(csail_start), "--out", str(offline)), capture_output=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    reference = read_map_server(offline)
    logged = list(CarmenSource(csail_start))
    domain = 16
    keys = FleetKeys("t")
    procs = Processes(tmp_path)
    robot = SdkRobot(router, "/r1", domain)
    maps = Inbox()
    viewer = sdk.ROS2Subscriber("/map", wire.OCCUPANCY_GRID, maps, **sdk_args(router, domain))
    try:
        with client(router) as bus:
            scans, submaps, global_maps, services = Inbox(), Inbox(), Inbox(), Inbox()
            bus.subscribe(keys.scan("r1"), scans)
            bus.subscribe(keys.localmap("r1"), submaps)
            bus.subscribe(keys.globalmap, global_maps)
            bus.subscribe_liveliness(keys.all_services, services, lambda k: None)
            procs.start("merger", "merger", "--ros2", "--domain", str(domain), *fleet_flags(router))
            assert services.wait_until(lambda got: any("merger" in str(g) for g in got), WAIT)
            agent = procs.start(
                "agent", "agent", "--robot", "r1", "--ros2", "--namespace", "r1", "--domain", str(domain),
                "--wait-for-listener", str(WAIT), *fleet_flags(router),
            )  # fmt: skip
            wait_for_subscription(bus, domain, "/r1/tf_static")
            robot.wait_until_heard()
            robot.publish_mounting()
            robot.play(logged)
            assert scans.wait_for(len(logged), 120), f"{len(scans.items)} of {len(logged)} scans reached the bus"
            assert procs.stopped(agent, "agent") == 0, procs.log("agent")[-6000:]
            final = {m.submap_key for m in (LocalMap.from_msgpack(p) for _, p in submaps.items) if m.final}  # type: ignore[arg-type]

            def merged() -> float | None:
                """The stamp of the first global map that holds every final submap, if one came."""
                for _, payload in global_maps.items:
                    g = decode(payload)  # type: ignore[arg-type]
                    if final <= {k for c in g.components for k in c.members}:  # type: ignore[attr-defined]
                        return float(g.stamp)  # type: ignore[attr-defined]
                return None

            assert final and wait_for(lambda: merged() is not None, 120), "the merger never took every submap in"
            stamp = merged()
            assert stamp is not None
            assert maps.wait_until(
                lambda got: any(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 >= stamp - 1e-6 for (m,) in got),  # type: ignore[attr-defined]
                WAIT,
            ), "no /map of the merged global map"
    finally:
        viewer.close()
        robot.close()
        procs.stop()
    scan_stamps = [m.stamp for m in scans_of(scans)]
    assert scan_stamps == pytest.approx([s.stamp for s in logged], abs=1e-6)
    last = maps.items[-1][0]
    share, cells = agreement(last, reference)
    assert cells > 10_000
    assert share >= 0.95, f"{share:.3f} of {cells} cells known in both agree"
