"""``fleetmap run``: a live multi-robot session of a scenario, every part a real process.

The runner starts a zenoh router on a free loopback port, the recorder, the merger and one agent
process per robot (the same commands a deployment runs, see docker-compose.yml), all connected
to the router. It plays the scenario's events on the scenario clock (scaled by ``speed``): a
robot joins when its agent starts, leaves with SIGTERM, crashes with SIGKILL; a merger restart
is a SIGKILL and a new merger on the same state file after ``down_for``; kidnaps happen inside
the robots' simulated streams. When every robot is done and the merger has integrated every
local map published, it stops the merger and the recorder (after the recorder has every message
the runner saw on the bus) and writes the outputs from the recording (:mod:`fleetmap.report`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from fleetmap.merger.recorder import wait_until_recorded
from fleetmap.report import latency_figures, log_from_recording, make_truth, merge_latencies, write_outputs
from fleetmap.scenarios import Scenario, scenario_to_toml
from fleetmap.scenarios.fleet import Crash, Leave, MergerRestart, scenario_end
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.warmup import warm
from fleetmap.shared.errors import FleetmapError
from fleetmap.shared.io import ros2_wire as wire
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import BadMessage, FleetEvent, LocalMap, MergerStep, Scan, decode
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.security import write_fleet_security
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

log = logging.getLogger(__name__)

READY_TIMEOUT = 30.0
"""Seconds a service may take to start (python, numpy, zenoh) before the run gives up."""
ROS2_QUIET = 10.0
"""Seconds without a Scan after which a ROS 2 session's robot whose bag is played is taken as done."""
CATCH_UP_TIMEOUT = 300.0
"""Seconds the merger may take, after the robots are done, to integrate the last local maps."""


class SessionError(FleetmapError):
    """A part of the session failed (a service did not start, died, or never caught up)."""


@dataclass
class _Child:
    name: str
    argv: list[str]
    log_path: Path
    popen: subprocess.Popen[bytes] | None = None
    log_file: IO[bytes] | None = None

    def start(self) -> None:
        self.log_file = open(self.log_path, "ab")  # noqa: SIM115  (closed in stop())
        self.popen = subprocess.Popen(self.argv, stdout=self.log_file, stderr=subprocess.STDOUT)

    @property
    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def signal(self, sig: int) -> None:
        if self.popen is not None and self.popen.poll() is None:
            self.popen.send_signal(sig)

    def stop(self, timeout: float = 20.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``; the exit code."""
        if self.popen is None:
            return None
        if self.running:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                # a service writes its threads' stacks on SIGUSR1 (fleetmap.cli): where it was stuck
                self.popen.send_signal(signal.SIGUSR1)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.popen.wait(1.0)
                log.warning(
                    "%s did not stop within %.0f s of SIGTERM (its stacks: %s)", self.name, timeout, self.log_path
                )
                self.popen.kill()
                self.popen.wait(5)
        if self.log_file is not None:
            self.log_file.close()
            self.log_file = None
        return self.popen.returncode


@dataclass
class _Watch:
    """What the runner hears on the bus: messages per topic, local maps published and integrated."""

    counts: Counter[str] = field(default_factory=Counter)
    published: dict[str, int] = field(default_factory=dict)
    integrated: dict[str, int] = field(default_factory=dict)
    last_step: int = -1
    queued: int = 0
    """Pairs of maps the merger still had to integrate after its last step."""
    services: set[str] = field(default_factory=set)
    robots: frozenset[str] | None = None
    """The session's robots: only their local maps are waited for (anyone may publish on a fleet)."""
    refused: set[str] = field(default_factory=set)
    """Epochs (``robot/epoch``) the merger said it refuses: their maps are not waited for."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    changed: threading.Event = field(default_factory=threading.Event)

    def on_message(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.counts[key] += 1
        try:
            message = decode(payload)
        except BadMessage:
            return
        with self.lock:
            if isinstance(message, LocalMap) and (self.robots is None or message.robot in self.robots):
                self.published[message.submap_key] = max(self.published.get(message.submap_key, -1), message.version)
            elif isinstance(message, FleetEvent) and message.kind == "refused" and message.robot is not None:
                with contextlib.suppress(ValueError, KeyError, TypeError):
                    self.refused.add(f"{message.robot}/{int(json.loads(message.detail)['epoch'])}")
            elif isinstance(message, MergerStep):
                for k, v in zip(message.maps, message.versions, strict=True):
                    self.integrated[k] = max(self.integrated.get(k, -1), v)
                if message.seq >= self.last_step:
                    self.last_step, self.queued = message.seq, message.queued or 0
        self.changed.set()

    def caught_up(self) -> bool:
        """Every local map version published is in the merger's graph, and integrated with the
        others (no pairs queued after its last step)."""
        with self.lock:
            return self.queued == 0 and all(
                self.integrated.get(k, -1) >= v or k.rsplit("/", 1)[0] in self.refused
                for k, v in self.published.items()
            )


class _Ros2Feeds:
    """What the runner hears of a ROS 2 session's robots: whose agent subscribes to its scans now
    (its ``MS`` liveliness token for ``/<robot>/scan``), and whether a robot's agent has mapped
    every scan of its bag (a live agent numbers the scans it takes from 0: its last one's Scan
    message names the bag's last index). The runner's own subscriber may miss a message a busy
    machine drops; after :data:`ROS2_QUIET` seconds without a Scan of a robot whose bag is played,
    its agent is taken to have mapped all it heard."""

    def __init__(self, bus: ZenohBus, keys: FleetKeys, bags: dict[str, tuple[Path, int]]) -> None:
        self.bags = bags
        self.keys = keys
        self.stopped: set[str] = set()
        """Robots whose agent was told to stop."""
        self.played: dict[str, float] = {}
        """When the runner saw each robot's player done (monotonic)."""
        self.changed = threading.Event()
        self._topics = {wire.mangle(f"/{robot}/scan"): robot for robot in bags}
        self._listening: set[str] = set()
        self._lock = threading.Lock()
        self._last: dict[str, tuple[int, float]] = {}
        """Each robot's newest Scan message heard: its index, and when it came (monotonic)."""
        bus.subscribe_liveliness(f"{wire.LIVELINESS_PREFIX}/0/**", self._on_token, lambda key: None)
        bus.subscribe(keys.all_scans, self._on_scan)

    def _on_scan(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload)
        except BadMessage:
            return
        if isinstance(message, Scan):
            with self._lock:
                index = max(message.index, self._last.get(message.robot, (-1, 0.0))[0])
                self._last[message.robot] = (index, time.monotonic())

    def _on_token(self, key: str) -> None:
        chunks = key.split("/")  # @ros2_lv/domain/session/node/entity/kind/enclave/namespace/name/topic/...
        if len(chunks) > 9 and chunks[5] == "MS" and (robot := self._topics.get(chunks[9])) is not None:
            with self._lock:
                self._listening.add(robot)
            self.changed.set()

    def listening(self) -> set[str]:
        with self._lock:
            return set(self._listening)

    def all_mapped(self, robot: str, played_since: float) -> bool:
        """Whether ``robot``'s agent has published its bag's last scan, or has been quiet
        :data:`ROS2_QUIET` s since ``played_since`` (monotonic) and since its last Scan."""
        with self._lock:
            index, at = self._last.get(robot, (-1, 0.0))
        if index >= self.bags[robot][1] - 1:
            return True
        if time.monotonic() - max(at, played_since) < ROS2_QUIET:
            return False
        log.warning(
            "%s: quiet for %.0f s after its bag was played, scan %d of %d heard last",
            robot,
            ROS2_QUIET,
            index,
            self.bags[robot][1],
        )
        return True


def _wait(predicate: Callable[[], bool], timeout: float, what: str, event: threading.Event | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        left = deadline - time.monotonic()
        if left <= 0:
            raise SessionError(f"timed out after {timeout:.0f} s waiting for {what}")
        if event is not None:
            event.wait(min(left, 0.2))
            event.clear()
        else:
            time.sleep(min(left, 0.05))


@dataclass
class Session:
    """One live run of a scenario (see the module docstring)."""

    scenario: Scenario
    out_dir: Path
    config: FleetmapConfig
    speed: float = 2.0
    fleet: str = "run"
    progress: bool = True
    secure: bool = False
    """Authentication and access control: every process logs in to the router with its own
    credentials from ``fleetmap secure`` (written into ``out_dir/secure``), and may do only what its
    role may."""
    tls: bool = False
    """With ``secure``: over mutual TLS."""
    view_port: int | None = None
    """Serve the session live to Foxglove on this WebSocket port (``fleetmap view``), if given."""
    merger_options: tuple[str, ...] = ("--executor", "inline")
    """Flags of ``fleetmap merger``. A session runs every robot on this machine: integration
    workers would only take CPU from the robots and the merger's solve (decision record 004), so
    the merger integrates in its own process unless these say otherwise."""
    ros2: bool = False
    """Feed each robot through ROS 2 topics over rmw_zenoh instead of its agent's own simulation:
    the robot's scans and odometry are written as a bag (:func:`~fleetmap.ros2_robots.write_robot_bag`),
    ``fleetmap agent --ros2 --namespace <robot>`` is its agent and, once the agent's scan
    subscription shows on the bus, ``fleetmap play BAG --ros2 --namespace <robot>`` publishes the
    bag at ``speed``. A live agent runs until stopped: it is stopped when play is done and its
    Scan of the bag's last scan is heard (or it has been quiet :data:`ROS2_QUIET` s). Events are
    not played, and a secure session is refused (rmw_zenoh's keys are outside the fleet's rules)."""
    python: str = sys.executable
    children: list[_Child] = field(default_factory=list)
    _zenoh: Callable[[str], list[str]] = field(init=False, repr=False)

    def _fleetmap(self, *args: str) -> list[str]:
        return [self.python, "-m", "fleetmap", *args]

    def _child(self, name: str, *args: str) -> _Child:
        child = _Child(name, self._fleetmap(*args), self.out_dir / "logs" / f"{name}.log")
        self.children.append(child)
        child.start()
        return child

    def run(self) -> dict[str, Any]:
        if self.speed <= 0:
            raise SessionError("--speed must be positive: the scenario's events are played on its clock")
        out = self.out_dir
        (out / "logs").mkdir(parents=True, exist_ok=True)
        scenario_file = out / "scenario.toml"
        scenario_file.write_text(scenario_to_toml(self.scenario), encoding="utf-8")
        config_file = out / "config.toml"
        config_file.write_text(self.config.to_toml(), encoding="utf-8")
        state_file = out / "merger.state"
        state_file.unlink(missing_ok=True)
        bags = self._ros2_bags() if self.ros2 else {}
        endpoint = free_loopback_endpoint()
        if self.tls:
            endpoint = endpoint.replace("tcp/", "tls/")
        self._zenoh = self._zenoh_args(endpoint)
        warm()  # the compiled loops built once, here, not by every process at its first scans
        started = time.monotonic()
        try:
            self._child("router", "router", *self._zenoh("router"))
            if self.secure:
                options = ZenohOptions(config_file=str(out / "secure" / "viewer.json5"), fleet=self.fleet)
            else:
                options = ZenohOptions(mode="client", connect=(endpoint,), fleet=self.fleet)
            _wait(lambda: _port_open(endpoint), READY_TIMEOUT, "the zenoh router")
            with ZenohBus.open(options) as bus:
                keys = options.keys
                watch = _Watch(robots=frozenset(r.id for r in self.scenario.robots))
                bus.subscribe(keys.everything, watch.on_message)
                bus.subscribe_liveliness(
                    keys.all_services, lambda k: watch.services.add(k.rsplit("/", 1)[-1]), lambda k: None
                )
                record = self._child(
                    "recorder",
                    "record",
                    "--out",
                    str(out / "session.mcap"),
                    "--overwrite",  # the run's own folder: a new run replaces its outputs
                    "--config",
                    str(config_file),
                    "--scenario",
                    str(scenario_file),
                    *self._zenoh("recorder"),
                )
                _wait(lambda: "recorder" in watch.services or not record.running, READY_TIMEOUT, "the recorder")
                if self.view_port is not None:
                    view = self._child("view", "view", "--port", str(self.view_port), *self._zenoh("viewer"))
                    # the view subscribes to the fleet before it opens its port
                    where = f"tcp/127.0.0.1:{self.view_port}"
                    _wait(lambda: _port_open(where) or not view.running, READY_TIMEOUT, "the live view")
                    if not view.running:
                        raise SessionError(f"the live view did not start (see {view.log_path})")
                merger_args: tuple[str, ...] = ("merger", "--state", str(state_file), "--config", str(config_file))
                merger_args += tuple(self._zenoh("merger")) + self.merger_options
                merger = self._child("merger", *merger_args)
                _wait(lambda: "merger" in watch.services or not merger.running, READY_TIMEOUT, "the merger")
                for c in (record, merger):
                    if not c.running:
                        raise SessionError(f"the {c.name} did not start (see {c.log_path})")
                feeds = _Ros2Feeds(bus, keys, bags) if self.ros2 else None
                merger = self._play(scenario_file, config_file, merger_args, merger, feeds)
                _wait(watch.caught_up, CATCH_UP_TIMEOUT, "the merger to integrate every local map", watch.changed)
                with watch.lock:
                    expected = dict(watch.counts)
                if not wait_until_recorded(bus, keys, expected, timeout=30.0):
                    log.warning("the recorder did not confirm every message the runner saw")
                merger.stop()
                record.stop()
        finally:
            for c in reversed(self.children):
                c.stop()
        return self._report(options.keys, time.monotonic() - started, expected)

    def _report(self, keys: FleetKeys, seconds: float, expected: dict[str, int]) -> dict[str, Any]:
        """The session's outputs from its recording, and report.json with the run's own figures
        (``expected``: the messages the runner saw, per topic)."""
        out = self.out_dir
        reader = RecordingReader(out / "session.mcap")
        with reader:
            session = log_from_recording(((m.topic, m.payload) for m in reader.messages()), keys)
            latencies = merge_latencies((m.payload, m.log_time) for m in reader.messages(warn=False))
            counts = reader.topic_counts()
        report = write_outputs(session, make_truth(self.scenario), out, f"fleetmap run: {self.scenario.name}")
        report["seconds"] = seconds
        report.update(latency_figures(latencies))
        report["messages_seen"] = sum(expected.values())
        # Of the messages the runner saw on each topic, how many the recording holds.
        report["messages_recorded"] = sum(min(counts.get(k, 0), n) for k, n in expected.items())
        report["speed"] = self.speed
        _write_json(out / "report.json", report)
        return report

    def _zenoh_args(self, endpoint: str) -> Callable[[str], list[str]]:
        """The zenoh flags of each role's process (``router``, ``merger``, ``recorder`` or a robot)."""
        if not self.secure:
            return lambda role: (
                ["--listen", endpoint]
                if role == "router"
                else ["--connect", endpoint, "--mode", "client", "--fleet", self.fleet]
            )
        folder = self.out_dir / "secure"
        robots = [r.id for r in self.scenario.robots]
        write_fleet_security(folder, self.fleet, robots, listen=[endpoint], tls=self.tls)
        return lambda role: (
            ["--zenoh-config", str(folder / f"{role}.json5")] + ([] if role == "router" else ["--fleet", self.fleet])
        )

    def _ros2_bags(self) -> dict[str, tuple[Path, int]]:
        """Each robot's bag for ``fleetmap play --ros2`` (written before the session starts)."""
        from fleetmap.ros2_robots import write_robot_bag

        if self.secure:
            raise SessionError("a ROS 2 session is an open one: rmw_zenoh's keys are outside the fleet's access rules")
        if self.scenario.events:
            raise SessionError("a ROS 2 session plays no events: its robots' agents run until their bags are played")
        bags = {}
        for robot in self.scenario.robots:
            bag = self.out_dir / "ros2" / robot.id
            if bag.exists():
                shutil.rmtree(bag)  # the run's own folder: a new run replaces its outputs
            bag.parent.mkdir(parents=True, exist_ok=True)
            bags[robot.id] = (bag, write_robot_bag(self.scenario, robot.id, bag))
        return bags

    def _start_agent(self, robot: str, scenario_file: Path, config_file: Path, ros2: bool) -> _Child:
        source = (
            ("--ros2", "--namespace", robot) if ros2 else ("--scenario", str(scenario_file), "--speed", str(self.speed))
        )
        return self._child(
            f"agent-{robot}", "agent", "--robot", robot, *source, "--config", str(config_file), *self._zenoh(robot)
        )

    def _start_players(self, feeds: _Ros2Feeds, players: dict[str, _Child], agents: dict[str, _Child]) -> None:
        """``fleetmap play`` for each robot whose agent listens now (and not yet played)."""
        for robot in feeds.listening() - players.keys():
            if robot in agents:
                where = self._zenoh(robot)[:4]  # --connect and --mode: play is on no fleet
                bag = str(feeds.bags[robot][0])
                players[robot] = self._child(
                    f"play-{robot}", "play", bag, "--ros2", "--namespace", robot, "--speed", str(self.speed), *where
                )

    def _stop_played(self, feeds: _Ros2Feeds, players: dict[str, _Child], agents: dict[str, _Child]) -> None:
        """Stop the agent of each robot whose bag is played and whose scans all reached the fleet."""
        for robot, player in players.items():
            if player.running or robot in feeds.stopped:
                continue
            if player.popen is not None and player.popen.returncode != 0:
                raise SessionError(
                    f"play {robot} failed with exit code {player.popen.returncode} (see {player.log_path})"
                )
            played_since = feeds.played.setdefault(robot, time.monotonic())
            if feeds.all_mapped(robot, played_since):
                agents[robot].signal(signal.SIGTERM)
                feeds.stopped.add(robot)

    def _play(
        self,
        scenario_file: Path,
        config_file: Path,
        merger_args: tuple[str, ...],
        merger: _Child,
        feeds: _Ros2Feeds | None = None,
    ) -> _Child:
        """Start the agents and play the events on the scenario clock; returns the current merger."""
        sc = self.scenario
        players: dict[str, _Child] = {}
        actions: list[tuple[float, int, str, Any]] = []
        for r in sc.robots:
            actions.append((r.start, 0, "start", r.id))
        for e in sc.events:
            if isinstance(e, Leave):
                actions.append((e.t, 1, "leave", e.robot))
            elif isinstance(e, Crash):
                actions.append((e.t, 1, "crash", e.robot))
            elif isinstance(e, MergerRestart):
                actions.append((e.t, 2, "merger_kill", None))
                actions.append((e.t + e.down_for, 3, "merger_start", None))
        actions.sort(key=lambda a: (a[0], a[1]))
        end = scenario_end(sc)
        agents: dict[str, _Child] = {}
        t0 = time.monotonic()
        bar = _progress(end, self.progress)
        try:
            for at, _, what, robot in actions:
                while (now := (time.monotonic() - t0) * self.speed) < at:
                    bar(now)
                    if feeds is not None:
                        self._start_players(feeds, players, agents)
                    time.sleep(min(0.1, (at - now) / self.speed))
                if what == "start":
                    agents[robot] = self._start_agent(robot, scenario_file, config_file, feeds is not None)
                elif what == "leave":
                    agents[robot].signal(signal.SIGTERM)
                elif what == "crash":
                    agents[robot].signal(signal.SIGKILL)
                elif what == "merger_kill":
                    merger.signal(signal.SIGKILL)
                    merger.stop()
                elif what == "merger_start":
                    merger = self._child(f"merger-{len(self.children)}", *merger_args)
            deadline = time.monotonic() + end / self.speed + READY_TIMEOUT + 60.0
            while any(a.running for a in agents.values()):
                bar((time.monotonic() - t0) * self.speed)
                if feeds is not None:
                    self._start_players(feeds, players, agents)
                    self._stop_played(feeds, players, agents)
                if time.monotonic() > deadline:
                    raise SessionError("the robots did not finish their scenario in time")
                if feeds is not None:
                    feeds.changed.wait(0.1)
                    feeds.changed.clear()
                else:
                    time.sleep(0.1)
            bar(end)
        finally:
            bar(None)
        for name, a in agents.items():
            code = a.popen.returncode if a.popen is not None else None
            if code not in (0, -signal.SIGKILL, -signal.SIGTERM):
                raise SessionError(f"agent {name} failed with exit code {code} (see {a.log_path})")
        if not merger.running:
            raise SessionError(f"the merger died (see {merger.log_path})")
        return merger


def _progress(total: float, enabled: bool) -> Callable[[float | None], None]:
    """A progress bar over scenario seconds (tqdm on stderr); call with None to close it."""
    if not enabled:
        return lambda t: None
    from tqdm import tqdm

    bar = tqdm(
        total=round(total, 1), unit="s", desc="scenario", leave=False, bar_format="{l_bar}{bar}| {n:.1f}/{total} s"
    )

    def update(t: float | None) -> None:
        if t is None:
            bar.close()
            return
        bar.n = round(min(t, total), 1)
        bar.refresh()

    return update


def _port_open(endpoint: str) -> bool:
    import socket

    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    try:
        with socket.create_connection((host, int(port)), timeout=0.2):
            return True
    except OSError:
        return False


def _write_json(path: Path, data: dict[str, Any]) -> None:
    import json

    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, path)
