"""The agent on a bus: presence, keys, pacing, republish requests, stopping; then the real
``fleetmap agent`` process over zenoh on loopback (slow)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from fleetmap.agents.agent import Agent
from fleetmap.agents.process import run_agent
from fleetmap.scenarios import load_scenario, robot_stream
from fleetmap.shared.config import FleetmapConfig, TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.memory_bus import InMemoryBus
from fleetmap.shared.io.messages import Component, FleetEvent, GlobalMap, LocalMap, Scan, decode
from fleetmap.shared.io.sources import SourceScan
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

from tests.agents.conftest import kidnap_index, pivot, source_scans
from tests.bus_helpers import WAIT, Inbox, open_zenoh

KEYS = FleetKeys("t")
NO_SEGMENTS = np.zeros((0, 4))


class Observer:
    """A second bus that records what the agent's bus says, in order, with presence."""

    def __init__(self, bus: InMemoryBus) -> None:
        self.bus = bus
        self.log: list[tuple[str, object]] = []
        bus.subscribe(KEYS.everything, lambda key, payload: self.log.append((key, decode(payload))))
        bus.subscribe_liveliness(
            KEYS.all_alive, lambda key: self.log.append(("join", key)), lambda key: self.log.append(("leave", key))
        )

    def messages(self, kind: type) -> list:
        return [m for _, m in self.log if isinstance(m, kind)]


@pytest.fixture
def buses() -> tuple[InMemoryBus, Observer]:
    agent_bus = InMemoryBus()
    return agent_bus, Observer(agent_bus.peer())


@pytest.fixture(scope="module")
def scans(r2_stream) -> list[SourceScan]:
    return source_scans(r2_stream[:4])


def test_a_restarted_robot_starts_after_the_epochs_the_merger_holds_of_it(buses, scans):
    # a robot killed and started again under its id published its new r2/0/0 over the final one of
    # its first run (the map's error went from 0.017 to 2.2 m)
    bus, seen = buses
    held = [("r2/0/0", "r2/0/1"), ("r2/2/0", "r2/2/1"), ("r1/0/0", "r1/7/0")]
    components = [Component(a, (a, b), {a: Transform2D(), b: Transform2D(1.0, 0.0, 0.0)}, NO_SEGMENTS) for a, b in held]
    seen.bus.declare_queryable(KEYS.state, lambda selector: GlobalMap(4, 1.0, tuple(components)).to_msgpack())
    summary = run_agent(scans, Agent("r2"), bus, KEYS, speed=0, stop=threading.Event())
    maps = seen.messages(LocalMap)
    assert maps and {m.epoch for m in maps} == {3} and all(m.previous_epoch_link is None for m in maps)
    assert {m.epoch for m in seen.messages(Scan)} == {3} and summary.epochs == 1


def test_the_agent_joins_publishes_everything_on_its_key_and_leaves(buses, scans):
    bus, seen = buses
    summary = run_agent(scans, Agent("r2"), bus, KEYS, speed=0, stop=threading.Event())
    assert seen.log[0] == ("join", KEYS.alive("r2")) and seen.log[-1] == ("leave", KEYS.alive("r2"))
    published = seen.log[1:-1]
    assert [m.index for k, m in published if isinstance(m, Scan) and k == KEYS.scan("r2")] == [0, 1, 2, 3]
    maps = [(k, m) for k, m in published if isinstance(m, LocalMap)]
    assert {k for k, _ in maps} == {KEYS.localmap("r2")}
    assert maps[-1][1].scans == 4, "the final local map holds every placed scan"
    assert (summary.scans, summary.placed, summary.epochs, summary.stopped) == (4, 4, 1, False)
    assert summary.published == len(published)


@pytest.mark.slow  # starts processes: run in CI, deselected by -m "not slow"
def test_scans_are_paced_by_their_stamps_over_speed(buses, scans):
    bus, _ = buses
    now = [0.0]
    sent_at: list[tuple[int, float]] = []
    bus.subscribe(KEYS.scan("r2"), lambda key, payload: sent_at.append((decode(payload).index, now[0])))

    def sleep(seconds: float) -> None:
        now[0] += seconds

    run_agent(scans, Agent("r2"), bus, KEYS, speed=2.0, stop=threading.Event(), clock=lambda: now[0], sleep=sleep)
    # stamps 0, 0.2, 0.4, 0.6 s at twice their pace; the first waits for the second (were they a
    # burst? fleetmap.agents.bursts)
    assert [i for i, _ in sent_at] == [0, 1, 2, 3]
    assert [t for _, t in sent_at] == pytest.approx([0.1, 0.1, 0.2, 0.3], abs=1e-9)

    never: list[float] = []
    run_agent(scans, Agent("r2"), bus, KEYS, speed=0, stop=threading.Event(), sleep=never.append)
    assert never == [], "speed 0 plays the scans as fast as possible"


def test_an_agent_says_how_far_it_is_every_few_seconds(buses, scans, caplog) -> None:  # type: ignore[no-untyped-def]
    bus, _ = buses
    now = [0.0]

    def sleep(seconds: float) -> None:
        now[0] += seconds

    # four scans 0.2 s apart played 50 times slower, 10 s apart: a status line after each but the
    # first (at least 5 s since the last line)
    with caplog.at_level("INFO", logger="fleetmap.agents.process"):
        run_agent(scans, Agent("r2"), bus, KEYS, speed=0.02, stop=threading.Event(), clock=lambda: now[0], sleep=sleep)
    said = [r.getMessage() for r in caplog.records]
    progress = [m for m in said if m.startswith("r2: ") and "messages published" in m]
    assert [m.split(",")[0] for m in progress] == ["r2: 2 scans", "r2: 3 scans", "r2: 4 scans"], said


def test_a_republish_request_gets_the_latest_map_of_every_epoch_and_bad_events_are_ignored(buses, scans):
    bus, seen = buses
    asking = seen.bus

    def source() -> Iterator[SourceScan]:
        yield from scans[:2]
        asking.publish(KEYS.events, b"\x93not a fleet event")
        asking.publish(KEYS.events, Scan("r9", 0, 0, 0.0, []).to_msgpack())
        asking.publish(KEYS.events, FleetEvent("republish_request", "r7", 1.0).to_msgpack())  # another robot's
        asking.publish(KEYS.events, FleetEvent("republish_request", None, 1.0).to_msgpack())
        yield from scans[2:]

    agent = Agent("r2")
    summary = run_agent(source(), agent, bus, KEYS, speed=0, stop=threading.Event())
    maps = seen.messages(LocalMap)
    # version 0 at the first scan, again on request (the same bytes), then the rest
    assert [m.version for m in maps] == [0, 0, 1]
    assert maps[1].to_msgpack() == maps[0].to_msgpack()
    assert (summary.republished, summary.bad_events) == (1, 2)


@pytest.mark.slow  # starts processes: run in CI, deselected by -m "not slow"
def test_a_relocalized_event_ends_the_lost_robots_every_scan_publishing(buses, kidnapped):
    bus, seen = buses
    stream = list(robot_stream(kidnapped, "r1"))
    kidnap = kidnap_index(stream)

    def source() -> Iterator[SourceScan]:
        for s in source_scans(stream[: kidnap + 9]):
            if s.index == kidnap + 3:  # the merger places the new epoch
                for robot, detail in (("r7", {"epoch": 1}), ("r1", {}), ("r1", {"epoch": 1, "component": 0})):
                    event = FleetEvent("relocalized", robot, 1.0, json.dumps(detail))
                    seen.bus.publish(KEYS.events, event.to_msgpack())
            yield s

    # the pivot front end (its epoch breaks after two scans that do not integrate)
    summary = run_agent(source(), pivot("r1", kidnap_after=2), bus, KEYS, speed=0, stop=threading.Event())
    counts = [m.scans for m in seen.messages(LocalMap) if m.epoch == 1]
    # After every scan while lost (2 and 3 placed scans), then every 3: not at 4 and 5.
    assert counts[:3] == [2, 3, 6], counts
    assert summary.bad_events == 1, "the event without an epoch is counted and ignored"


def test_a_stop_ends_the_run_with_the_final_local_map_and_a_leave(buses, scans):
    bus, seen = buses
    stop = threading.Event()

    def source() -> Iterator[SourceScan]:
        yield from scans[:2]
        stop.set()  # as SIGTERM does
        yield from scans[2:]

    agent = Agent("r2", replace(FleetmapConfig(), tracking=TrackingParams(publish_every=5)))
    summary = run_agent(source(), agent, bus, KEYS, speed=0, stop=stop)
    assert summary.stopped and summary.scans == 2
    final = seen.messages(LocalMap)[-1]
    assert (final.version, final.scans, final.stamp) == (1, 2, scans[1].stamp)
    assert seen.log[-1] == ("leave", KEYS.alive("r2"))


def test_a_stop_cuts_the_wait_for_the_next_scan_short(buses, scans):
    bus, seen = buses
    stop = threading.Event()
    timer = threading.Timer(0.1, stop.set)
    timer.start()
    started = time.monotonic()
    try:
        summary = run_agent(scans, Agent("r2"), bus, KEYS, speed=0.01, stop=stop)  # the next scan is due in 50 s
    finally:
        timer.cancel()
    assert time.monotonic() - started < 2.0
    assert summary.stopped and summary.scans == 1
    assert seen.log[-1] == ("leave", KEYS.alive("r2"))


# --- the fleetmap agent process over zenoh (slow) ---


def start_agent(endpoint: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "fleetmap", "agent", "--connect", endpoint, "--fleet", "t", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


class Fleet:
    """The test's side of the bus: a listening zenoh session that collects an agent's messages."""

    def __init__(self) -> None:
        self.endpoint = free_loopback_endpoint()
        self.bus = open_zenoh(ZenohOptions(listen=(self.endpoint,), fleet="t"))
        self.scans, self.maps = Inbox(), Inbox()
        self.joined, self.left = threading.Event(), threading.Event()
        self.left_at = 0.0
        self.bus.subscribe(KEYS.all_scans, lambda key, payload: self.scans(decode(payload)))
        self.bus.subscribe(KEYS.all_localmaps, lambda key, payload: self.maps(decode(payload)))
        self.bus.subscribe_liveliness(KEYS.all_alive, lambda key: self.joined.set(), self._leave)

    def _leave(self, key: str) -> None:
        self.left_at = time.monotonic()
        self.left.set()


@pytest.fixture
def fleet() -> Iterator[Fleet]:
    f = Fleet()
    with f.bus:
        yield f


@pytest.mark.slow
def test_fleetmap_agent_publishes_its_robot_over_zenoh_and_leaves(fleet):
    agent = start_agent(fleet.endpoint, "--scenario", "department", "--robot", "r2", "--speed", "0")
    try:
        assert fleet.joined.wait(15.0), "the agent's liveliness token did not appear"
        assert agent.wait(30.0) == 0
        stdout = agent.stdout.read() if agent.stdout else ""
        assert fleet.left.wait(WAIT), "the agent did not leave"
    finally:
        agent.kill()
        agent.wait()
    scans = [m for (m,) in fleet.scans.items]
    total = len(list(robot_stream(load_scenario("department"), "r2")))
    assert [s.index for s in scans] == list(range(total)) and {s.robot for s in scans} == {"r2"}
    maps = [m for (m,) in fleet.maps.items]
    by_submap: dict[str, list[LocalMap]] = {}
    for m in maps:
        by_submap.setdefault(m.submap_key, []).append(m)
    assert len(by_submap) >= 2, "the robot's path is longer than one submap"
    for versions in by_submap.values():  # each submap's versions in order, the last one final
        assert [m.version for m in versions] == list(range(len(versions))) and versions[-1].final
        assert not any(m.final for m in versions[:-1])
    assert maps[-1].stamp == scans[-1].stamp, "the final submap comes after the last scan"
    assert f"agent r2 done: {total} scans" in stdout


@pytest.mark.slow
def test_fleetmap_agent_answers_a_republish_request_and_leaves_cleanly_on_sigterm(fleet):
    agent = start_agent(fleet.endpoint, "--scenario", "department", "--robot", "r2", "--speed", "1")
    try:
        assert fleet.maps.wait_for(1, timeout=15.0), "no local map from the agent"
        fleet.bus.publish(KEYS.events, FleetEvent("republish_request", None, 0.0).to_msgpack())
        assert fleet.maps.wait_until(lambda items: any(m.version == 0 for (m,) in items[1:]))
        assert fleet.scans.wait_for(4)
        agent.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        assert fleet.left.wait(2.0), "the agent did not leave within 2 s of SIGTERM"
        assert fleet.left_at - sent < 2.0
        stdout, _ = agent.communicate(timeout=WAIT)
    finally:
        agent.kill()
        agent.wait()
    assert agent.returncode == 0 and "agent r2 stopped" in stdout
    scans = [m for (m,) in fleet.scans.items]
    maps = [m for (m,) in fleet.maps.items]
    assert len(scans) < 33, "it stopped before the end of its path"
    # the active submaps' final local maps come after the last scan, one per submap (the newest may
    # have just begun at the last scan: it holds that one)
    at_end = [m for m in maps if m.final and m.stamp == scans[-1].stamp]
    assert at_end, "a final local map, after the last scan"
    assert max(m.scans for m in at_end) >= 4, "the final local maps hold the robot's scans"
