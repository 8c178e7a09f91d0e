"""The bus: the same contract over real zenoh sessions on loopback and in memory; zenoh flags.

The zenoh tests open two sessions in this process, one listening on a free loopback port and one
connecting to it; the slow ones run the other side in a child process and kill it.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.bus import FLUSH_TIMEOUT, Bus, BusError
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.memory_bus import InMemoryBus
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import (
    DEFAULT_ENDPOINT,
    ZenohOptions,
    add_zenoh_arguments,
    endpoints_argv,
    free_loopback_endpoint,
    zenoh_config,
    zenoh_options_from_args,
)

from tests.bus_helpers import WAIT, Inbox, bus_pair, open_zenoh, open_zenoh_pair, sync_declarations

KEYS = FleetKeys("t")


@pytest.fixture(params=["zenoh", "memory"])
def pair(request: pytest.FixtureRequest) -> Iterator[tuple[Bus, Bus]]:
    with bus_pair(request.param) as buses:
        yield buses


def test_published_payloads_arrive_exactly_in_order_with_their_keys(pair):
    a, b = pair
    inbox = Inbox()
    a.subscribe(KEYS.all_scans, inbox)
    assert b.wait_for_subscribers(KEYS.scan("r1"), WAIT)
    payloads = [bytes([i % 256]) * (i + 1) for i in range(100)]
    for payload in payloads:
        b.publish(KEYS.scan("r1"), payload)
    b.publish(KEYS.localmap("r1"), b"not a scan")  # another key: not for this subscriber
    assert inbox.wait_for(100)
    assert inbox.items == [(KEYS.scan("r1"), p) for p in payloads]
    assert a.stats.received == 100 and b.stats.published == 101


def test_a_callback_that_raises_is_counted_and_the_next_message_still_arrives(pair):
    a, b = pair
    inbox = Inbox()

    def fragile(key: str, payload: bytes) -> None:
        if payload == b"bad":
            raise ValueError("cannot handle this")
        inbox(key, payload)

    a.subscribe(KEYS.events, fragile)
    assert b.wait_for_subscribers(KEYS.events, WAIT)
    b.publish(KEYS.events, b"bad")
    b.publish(KEYS.events, b"good")
    assert inbox.wait_for(1)
    assert inbox.items == [(KEYS.events, b"good")]
    assert a.stats.callback_errors == 1


def test_a_closed_subscription_receives_nothing_more(pair):
    a, b = pair
    closed, open_ = Inbox(), Inbox()
    handle = a.subscribe(KEYS.events, closed)
    a.subscribe(KEYS.events, open_)
    assert b.wait_for_subscribers(KEYS.events, WAIT)
    b.publish(KEYS.events, b"1")
    assert closed.wait_for(1) and open_.wait_for(1)
    handle.close()
    b.publish(KEYS.events, b"2")
    assert open_.wait_for(2)
    assert closed.items == [(KEYS.events, b"1")]


def test_query_returns_the_queryables_answer(pair):
    a, b = pair
    a.declare_queryable(KEYS.state, lambda selector: b"state for " + selector.encode())
    sync_declarations(a, b)
    assert b.query(KEYS.state, timeout=WAIT) == [b"state for " + KEYS.state.encode()]


def test_a_failing_queryable_answers_an_error_not_an_exception(pair):
    a, b = pair

    def broken(selector: str) -> bytes:
        raise RuntimeError("no state yet")

    a.declare_queryable(KEYS.state, broken)
    sync_declarations(a, b)
    assert b.query(KEYS.state, timeout=WAIT) == []
    assert b.stats.query_errors == 1
    assert a.stats.callback_errors == 1


def test_query_without_queryable_returns_nothing(pair):
    _, b = pair
    assert b.query(KEYS.state, timeout=0.2) == []


def test_liveliness_join_history_and_leave(pair):
    a, b = pair
    early = b.declare_liveliness(KEYS.alive("r1"))
    joins, leaves = Inbox(), Inbox()
    a.subscribe_liveliness(KEYS.all_alive, joins, leaves, history=True)
    assert joins.wait_for(1), "a token that existed before the subscription is reported (history)"
    late = b.declare_liveliness(KEYS.alive("r2"))
    assert joins.wait_for(2)
    assert sorted(k for (k,) in joins.items) == [KEYS.alive("r1"), KEYS.alive("r2")]
    early.close()
    assert leaves.wait_for(1)
    assert leaves.items == [(KEYS.alive("r1"),)]
    late.close()
    assert leaves.wait_for(2)


def test_closing_a_bus_makes_its_tokens_leave(pair):
    a, b = pair
    joins, leaves = Inbox(), Inbox()
    a.subscribe_liveliness(KEYS.all_alive, joins, leaves)
    b.declare_liveliness(KEYS.alive("r1"))
    assert joins.wait_for(1)
    b.close()
    assert leaves.wait_for(1)
    with pytest.raises(BusError, match="closed"):
        b.publish(KEYS.events, b"x")


def test_bad_key_expressions_are_bad_input(pair):
    a, _ = pair
    with pytest.raises(BadInput, match="not a valid key expression"):
        a.publish("fleet//t", b"x")
    with pytest.raises(BadInput, match="not a valid key expression"):
        a.subscribe("fleet/t/**/**/", Inbox())


@pytest.mark.slow  # the subscriber takes 7.5 s over what it receives
def test_closing_right_after_publishing_loses_nothing_even_to_a_slow_subscriber():
    """zenoh drops what a closing session still has queued; close() flushes first. The subscriber
    takes 7.5 s over what it receives, beyond the 2 s lease: had its callback held zenoh's receiving
    thread, the session could not read the publisher's keep-alives, the link would lapse and the
    messages still on the way would be lost (docs/decisions/004-a-live-fleet-that-keeps-up.md)."""
    a, b = open_zenoh_pair()
    with a:
        inbox = Inbox()

        def slow(key: str, payload: bytes) -> None:
            threading.Event().wait(0.005)  # a subscriber doing real work per message
            inbox(key, payload)

        a.subscribe(KEYS.all_scans, slow)
        assert b.wait_for_subscribers(KEYS.scan("r1"), WAIT)
        for i in range(1500):
            b.publish(KEYS.scan("r1"), i.to_bytes(4, "little") * 2500)
        b.close()
        assert inbox.wait_for(1500, timeout=30.0), f"{len(inbox.items)} of 1500 arrived"
        assert [int.from_bytes(p[:4], "little") for _, p in inbox.items] == list(range(1500)), "in order"


def test_zenoh_payloads_carry_the_msgpack_encoding():
    a, b = open_zenoh_pair()
    with a, b:
        encodings = Inbox()
        a.session.declare_subscriber(KEYS.events, lambda sample: encodings(str(sample.encoding)))
        assert b.wait_for_subscribers(KEYS.events, WAIT)
        b.publish(KEYS.events, b"x")
        assert encodings.wait_for(1)
        assert encodings.items == [("application/msgpack",)]


# --- the shared zenoh flags ---


def config_of(options: ZenohOptions) -> dict[str, object]:
    config = zenoh_config(options)
    keys = ("mode", "listen/endpoints", "connect/endpoints", "scouting/multicast/enabled", "transport/link/tx/lease")
    return {k: json.loads(config.get_json(k)) for k in keys}


def test_default_is_a_loopback_peer_with_multicast_off_and_a_short_lease():
    assert config_of(ZenohOptions()) == {
        "mode": "peer",
        "listen/endpoints": ["tcp/127.0.0.1:0"],
        "connect/endpoints": [DEFAULT_ENDPOINT],
        "scouting/multicast/enabled": False,
        "transport/link/tx/lease": 2000,
    }


def test_endpoint_defaults_per_mode():
    hub = config_of(ZenohOptions(listen=("tcp/127.0.0.1:7500",)))
    assert hub["listen/endpoints"] == ["tcp/127.0.0.1:7500"] and hub["connect/endpoints"] == []
    spoke = config_of(ZenohOptions(connect=("tcp/127.0.0.1:7500",)))
    assert spoke["listen/endpoints"] == ["tcp/127.0.0.1:0"]
    assert spoke["connect/endpoints"] == ["tcp/127.0.0.1:7500"]
    router = config_of(ZenohOptions(mode="router"))
    assert router["mode"] == "router" and router["listen/endpoints"] == [DEFAULT_ENDPOINT]
    client = config_of(ZenohOptions(mode="client"))
    assert client["connect/endpoints"] == [DEFAULT_ENDPOINT]


def test_flags_parse_into_options():
    import argparse

    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    args = parser.parse_args(
        ["--mode", "client", "--connect", "tcp/10.0.0.1:7447", "--connect", "tcp/10.0.0.2:7447", "--fleet", "lab"]
    )
    options = zenoh_options_from_args(args)
    assert options == ZenohOptions("client", ("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"), (), None, "lab")
    assert options.keys.scan("r1") == "fleet/lab/robots/r1/scan"
    # a parent (fleetmap run) hands its children the same options
    assert zenoh_options_from_args(parser.parse_args(endpoints_argv(options))) == options


def test_a_config_file_decides_and_flags_override_it(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7600"]}, // robots\n}')
    from_file = config_of(ZenohOptions(config_file=str(path)))
    assert from_file["mode"] == "client" and from_file["connect/endpoints"] == ["tcp/127.0.0.1:7600"]
    overridden = config_of(ZenohOptions(mode="peer", connect=("tcp/127.0.0.1:7601",), config_file=str(path)))
    assert overridden["mode"] == "peer" and overridden["connect/endpoints"] == ["tcp/127.0.0.1:7601"]


def test_bad_zenoh_options_are_bad_input(tmp_path):
    with pytest.raises(BadInput, match=r"--connect foo: .*Endpoints must be of the form"):
        zenoh_config(ZenohOptions(connect=("foo",)))
    with pytest.raises(BadInput, match="no such zenoh config file"):
        zenoh_config(ZenohOptions(config_file=str(tmp_path / "missing.json5")))
    broken = tmp_path / "broken.json5"
    broken.write_text("{mode: ")
    with pytest.raises(BadInput, match="not a valid zenoh config"):
        zenoh_config(ZenohOptions(config_file=str(broken)))
    with pytest.raises(BadInput, match="--mode"):
        ZenohOptions(mode="hub")
    with pytest.raises(BadInput, match="--fleet"):
        ZenohOptions(fleet="Lab/1")


def test_a_listen_port_in_use_fails_to_open_with_bus_error():
    endpoint = free_loopback_endpoint()
    with ZenohBus.open(ZenohOptions(listen=(endpoint,))), pytest.raises(BusError, match="Address already in use"):
        ZenohBus.open(ZenohOptions(listen=(endpoint,)))


# --- across processes (slow) ---

CHILD = """
import sys
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.zenoh_config import ZenohOptions

keys = FleetKeys("t")
with ZenohBus.open(ZenohOptions(connect=(sys.argv[1],), fleet="t")) as bus:
    bus.declare_liveliness(keys.alive("child"))
    count = int(sys.argv[2])
    if count and not bus.wait_for_subscribers(keys.scan("child"), 5.0):
        sys.exit(3)
    for i in range(count):
        bus.publish(keys.scan("child"), i.to_bytes(4, "little") * 64)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin, or kills us
"""


def start_child(endpoint: str, count: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, endpoint, str(count)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


@pytest.fixture
def listener() -> Iterator[tuple[ZenohBus, str]]:
    endpoint = free_loopback_endpoint()
    with open_zenoh(ZenohOptions(listen=(endpoint,), fleet="t")) as bus:
        yield bus, endpoint


@pytest.mark.slow
def test_another_process_publishes_and_leaves_cleanly(listener):
    bus, endpoint = listener
    scans, joins, leaves = Inbox(), Inbox(), Inbox()
    bus.subscribe(KEYS.all_scans, scans)
    bus.subscribe_liveliness(KEYS.all_alive, joins, leaves)
    child = start_child(endpoint, 500)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "ready"
        assert joins.wait_for(1) and joins.items == [(KEYS.alive("child"),)]
        assert scans.wait_for(500)
        assert [p for _, p in scans.items] == [i.to_bytes(4, "little") * 64 for i in range(500)]
        assert child.stdin is not None
        child.stdin.close()
        assert child.wait(WAIT) == 0
        assert leaves.wait_for(1)
    finally:
        child.kill()
        child.wait()


@pytest.mark.slow
def test_a_killed_process_is_seen_leaving_within_two_seconds(listener):
    bus, endpoint = listener
    joins, leaves = Inbox(), Inbox()
    left_at: list[float] = []
    bus.subscribe_liveliness(KEYS.all_alive, joins, lambda key: (left_at.append(time.monotonic()), leaves(key)))
    child = start_child(endpoint, 0)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "ready"
        assert joins.wait_for(1)
        killed_at = time.monotonic()
        child.send_signal(signal.SIGKILL)
        assert leaves.wait_for(1, timeout=2.0), "the killed robot's token did not leave within 2 s"
        assert left_at[0] - killed_at < 2.0
    finally:
        child.kill()
        child.wait()


def test_zenoh_key_matching_of_the_in_memory_bus_follows_zenoh():
    bus = InMemoryBus()
    inbox = Inbox()
    bus.subscribe("fleet/t/**", inbox)
    bus.subscribe("fleet/t/robots/*/scan", inbox)
    bus.publish("fleet/t/robots/r1/scan", b"1")
    bus.publish("fleet/t/events", b"2")
    bus.publish("fleet/u/events", b"3")
    assert [p for _, p in inbox.items] == [b"1", b"1", b"2"]
    assert zenoh.KeyExpr("fleet/t/**").intersects("fleet/t/events")


@pytest.mark.slow
def test_clients_talk_through_a_fleetmap_router_that_stops_on_sigterm():
    endpoint = free_loopback_endpoint()
    router = subprocess.Popen(
        [sys.executable, "-m", "fleetmap", "router", "--listen", endpoint],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert router.stderr is not None
        # a service logs at INFO: its session's line comes before the router's own
        assert any("zenoh router" in router.stderr.readline() for _ in range(10))
        client = ZenohOptions(mode="client", connect=(endpoint,), fleet="t")
        with open_zenoh(client) as robot, open_zenoh(client) as merger:
            joins, maps = Inbox(), Inbox()
            merger.subscribe_liveliness(KEYS.all_alive, joins, lambda key: None)
            merger.subscribe(KEYS.all_localmaps, maps)
            robot.declare_liveliness(KEYS.alive("r1"))
            assert joins.wait_for(1)
            assert robot.wait_for_subscribers(KEYS.localmap("r1"), WAIT)
            robot.publish(KEYS.localmap("r1"), b"map")
            assert maps.wait_for(1) and maps.items == [(KEYS.localmap("r1"), b"map")]
        router.send_signal(signal.SIGTERM)
        stdout, _ = router.communicate(timeout=WAIT)
        assert router.returncode == 0 and "zenoh router stopped" in stdout
    finally:
        router.kill()
        router.wait()


@pytest.mark.slow  # waits on a real zenoh connection
def test_a_client_whose_router_never_answers_says_so_then_gives_up(caplog: pytest.LogCaptureFixture) -> None:
    endpoint = free_loopback_endpoint()  # nothing listens there
    with caplog.at_level(logging.WARNING), pytest.raises(BusError, match="Unable to connect"):
        ZenohBus.open(ZenohOptions(mode="client", connect=(endpoint,), connect_wait=1.0))
    waits = [r.getMessage() for r in caplog.records if "nothing answers" in r.getMessage()]
    assert waits and all(endpoint in w for w in waits)
    with pytest.raises(BadInput, match="--connect-wait"):
        ZenohOptions(connect_wait=-1.0)


def test_a_session_whose_barrier_never_answers_does_not_hold_up_the_closing_of_a_client_of_the_router():
    """A client's close waits for its router's barrier reply alone: that reply means nothing it
    published is left in its own queues. A session elsewhere on the fleet that holds a barrier
    queryable and never answers held up every service's stop by two flush timeouts (10 s). In-process
    sessions through a router; about 0.2 s."""
    endpoint = free_loopback_endpoint()
    with open_zenoh(ZenohOptions(mode="router", listen=(endpoint,), connect=(), fleet="t")) as router:
        client = ZenohOptions(mode="client", connect=(endpoint,), fleet="t")
        with open_zenoh(client) as mute, open_zenoh(client) as listener:
            held: list[zenoh.Query] = []  # (kept, never answered)
            asked = threading.Event()

            def hold(query: zenoh.Query) -> None:
                held.append(query)
                asked.set()

            mute.session.declare_queryable("fleetmap/barrier/mute", hold)
            inbox = Inbox()
            listener.subscribe(KEYS.events, inbox)
            leaving = open_zenoh(client)
            sync_declarations(mute, leaving)
            assert leaving.wait_for_subscribers(KEYS.events, WAIT)
            leaving.publish(KEYS.events, b"last words")
            started = time.monotonic()
            leaving.close()
            # held up, it waits two flush timeouts; answered by its router alone, a fraction of a
            # second (a busy machine stretches that, never to a whole flush timeout)
            assert time.monotonic() - started < FLUSH_TIMEOUT, "close waited for the session that never answers"
            assert inbox.wait_for(1), "what the closing client published was lost"
            # the query reaches the mute session on its own time: the close does not wait for it
            # (a loaded machine delivered it after the close had returned)
            assert asked.wait(WAIT), "the mute session was asked (the test would prove nothing otherwise)"
        assert router.stats.callback_errors == 0
