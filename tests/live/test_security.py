"""A fleet that lets in only its own robots: ``fleetmap secure``'s configs on a real router.

The router, merger and recorder are the real programs, each logged in with its own credentials;
the test's sessions play a legitimate robot, a rogue (authenticated as r2) and a viewer.
"""

from __future__ import annotations

import json
import signal
import stat
from contextlib import ExitStack
from pathlib import Path

import msgpack
import pytest
from fleetmap.shared.io.bus import BusError
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import FleetEvent, GlobalMap, decode
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions, free_loopback_endpoint

from fleetmap.cli import main
from tests.bus_helpers import Inbox
from tests.helpers import true_local_map
from tests.live.test_fleet import WAIT, processes, run_department, start

KEYS = FleetKeys("t")
SERVICES = ("merger", "recorder")


def _secure(folder: Path, endpoint: str) -> int:
    return main(["secure", "--fleet", "t", "--robots", "r1,r2", "--out", str(folder), "--listen", endpoint])


def _open(config: Path, wait: float = 0.0) -> ZenohBus:
    return ZenohBus.open(ZenohOptions(config_file=str(config), fleet="t", connect_wait=wait))


def _without_comments(path: Path) -> dict:  # type: ignore[type-arg]
    return json.loads("".join(line for line in path.read_text().splitlines() if not line.startswith("//")))


def test_secure_writes_owner_only_configs_and_prints_no_secret(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "secure"
    command = ["secure", "--fleet", "t", "--robots", "r1,r2", "--out", str(folder)]
    assert main(command) == 0
    printed = capsys.readouterr()
    passwords = [line.split(":", 1)[1] for line in (folder / "users.txt").read_text().splitlines()]
    assert len(passwords) == 5 and len(set(passwords)) == 5 and min(len(p) for p in passwords) >= 40
    assert not any(p in printed.out + printed.err for p in passwords)
    # every command printed names the fleet: a robot run as printed without it talks to nobody
    commands = [line for line in printed.out.splitlines() if "fleetmap agent" in line or "fleetmap merger" in line]
    assert len(commands) == 2 and all("--fleet t " in line for line in commands), printed.out
    for path in folder.iterdir():
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    r1 = _without_comments(folder / "r1.json5")
    assert r1["mode"] == "client" and r1["scouting"]["gossip"]["enabled"] is False
    router = _without_comments(folder / "router.json5")
    assert router["access_control"]["default_permission"] == "deny"
    # a second run would change every password under running robots: refused unless asked
    assert main(command) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["secure", "--fleet", "t", "--robots", "r1,merger", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "merger" in err and len(err.strip().splitlines()) == 1


def test_a_router_listening_everywhere_is_reached_on_loopback_at_its_own_port(tmp_path: Path) -> None:
    command = ["secure", "--fleet", "t", "--robots", "r1", "--out", str(tmp_path), "--listen", "tcp/0.0.0.0:9001"]
    assert main(command) == 0
    assert _without_comments(tmp_path / "r1.json5")["connect"]["endpoints"] == ["tcp/127.0.0.1:9001"]
    assert _without_comments(tmp_path / "router.json5")["listen"]["endpoints"] == ["tcp/0.0.0.0:9001"]


@pytest.mark.slow
def test_only_the_fleets_own_robots_get_in_and_none_speaks_for_another(tmp_path: Path) -> None:
    endpoint = free_loopback_endpoint()
    folder = tmp_path / "secure"
    assert _secure(folder, endpoint) == 0
    recording = tmp_path / "session.mcap"
    with processes() as procs, ExitStack() as stack:
        start(procs, "router", "--zenoh-config", str(folder / "router.json5"), log=tmp_path / "router.log")
        viewer = stack.enter_context(_open(folder / "viewer.json5", wait=WAIT))
        services, seen, alive = Inbox(), Inbox(), Inbox()
        viewer.subscribe_liveliness(KEYS.all_services, services, lambda k: None)
        viewer.subscribe(KEYS.everything, seen)
        viewer.subscribe_liveliness(KEYS.all_alive, alive, lambda k: None)
        role = {
            name: ["--zenoh-config", str(folder / f"{name}.json5"), "--fleet", "t"] for name in ("merger", "recorder")
        }
        start(procs, "record", "--out", str(recording), *role["recorder"], log=tmp_path / "recorder.log")
        merger = start(procs, "merger", *role["merger"], log=tmp_path / "merger.log")
        assert services.wait_for(2, WAIT), services.items

        # without credentials, or with a wrong password: refused
        plain = _without_comments(folder / "r1.json5")
        del plain["transport"]["auth"]
        (tmp_path / "anonymous.json5").write_text(json.dumps(plain))
        wrong = _without_comments(folder / "r1.json5")
        wrong["transport"]["auth"]["usrpwd"]["password"] += "x"
        (tmp_path / "wrong.json5").write_text(json.dumps(wrong))
        for config in ("anonymous.json5", "wrong.json5"):
            with pytest.raises(BusError):
                _open(tmp_path / config)

        # r2, logged in as itself, speaks for r1 and for the merger: nobody hears it
        r1_map, _ = true_local_map("department", "r1", 0, 6)
        with _open(folder / "r2.json5") as rogue:
            wire = msgpack.unpackb(r1_map.to_msgpack())
            rogue.publish(KEYS.localmap("r1"), msgpack.packb({**wire, "version": 2**62}))
            rogue.publish(KEYS.scan("r1"), b"forged scan")
            rogue.publish(KEYS.pose("r2"), b"forged pose")  # its own key, but the merger's to say
            rogue.publish(f"{KEYS.prefix}/robots/r2/k0", b"made-up key")  # under its own prefix, not a key it has
            rogue.publish(KEYS.globalmap, GlobalMap(10**9, 9e9, ()).to_msgpack())
            rogue.publish(KEYS.events, FleetEvent("republish_request", None, 1.0).to_msgpack())
            token = rogue.declare_liveliness(KEYS.alive("r1"))
            rogue.declare_liveliness(KEYS.alive("r2"))  # its own: allowed, and declared after the forged one
            assert alive.wait_for(1, WAIT)
            assert alive.items == [(KEYS.alive("r2"),)]
            rogue.flush()
            # the legitimate r1 then maps: its map is merged, and only what it said is heard
            with _open(folder / "r1.json5") as r1:
                r1.declare_liveliness(KEYS.alive("r1"))
                assert r1.wait_for_subscribers(KEYS.localmap("r1"), WAIT)
                r1.publish(KEYS.localmap("r1"), r1_map.to_msgpack())
                assert seen.wait_until(lambda got: any(k == KEYS.globalmap for k, _ in got), WAIT)
                # the robot's pose is put just after the global map
                assert seen.wait_until(lambda got: any(k == KEYS.pose("r1") for k, _ in got), WAIT)
                assert alive.wait_for(2, WAIT)
                # a robot may ask the merger's state: a restarted agent begins after its epochs there
                state = [GlobalMap.from_msgpack(p) for p in r1.query(KEYS.state, timeout=WAIT)]
                assert len(state) == 1 and state[0].component_of("r1/0/0") is not None
                token.close()
            merged = [decode(p) for k, p in seen.items if k == KEYS.globalmap]
            assert all(isinstance(m, GlobalMap) and m.stamp < 9e9 for m in merged)
            assert merged[-1].component_of("r1/0/0") is not None
        assert [p for k, p in seen.items if k == KEYS.localmap("r1")] == [r1_map.to_msgpack()]
        assert KEYS.pose("r1") in {k for k, _ in seen.items}  # the merger puts every robot's global pose
        assert KEYS.scan("r1") not in {k for k, _ in seen.items}
        assert not any(p in (b"forged pose", b"made-up key") for _, p in seen.items)
        events = [decode(p) for k, p in seen.items if k == KEYS.events]
        assert not any(isinstance(e, FleetEvent) and e.stamp == 1.0 for e in events)
        assert alive.items == [(KEYS.alive("r2"),), (KEYS.alive("r1"),)]

        merger.send_signal(signal.SIGTERM)
        assert merger.wait(WAIT) == 0
        recorder = procs[1]
        recorder.send_signal(signal.SIGTERM)
        assert recorder.wait(WAIT) == 0
    with RecordingReader(recording) as reader:
        messages = [(m.topic, m.payload) for m in reader.messages()]
    assert not any(p in (b"forged scan", b"forged pose", b"made-up key") for _, p in messages)
    localmaps = [decode(p) for t, p in messages if t == KEYS.localmap("r1")]
    assert [m.version for m in localmaps] == [r1_map.version]
    assert all(decode(p).stamp < 9e9 for t, p in messages if t == KEYS.globalmap)


@pytest.mark.slow
def test_a_secured_tls_fleet_maps_the_default_scenario_as_well_as_an_open_one(tmp_path: Path) -> None:
    out = tmp_path / "run"
    report = run_department(out, "--secure", "--tls")
    assert report["messages_recorded"] == report["messages_seen"] > 100
    router = _without_comments(out / "secure" / "router.json5")
    assert router["transport"]["link"]["tls"]["enable_mtls"] is True
