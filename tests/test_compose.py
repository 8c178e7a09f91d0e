"""docker-compose.yml (the secured fleet, the default) and docker-compose.open.yml (one machine) run
fleetmap commands; there is no Docker engine here, so their commands are checked to be real commands
of this CLI with valid arguments, and the secured deployment's commands are run as written, on
loopback (the compose's host names and volumes replaced by an endpoint and folders)."""

from __future__ import annotations

import json
import subprocess
import threading
from pathlib import Path

import pytest

from fleetmap.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.open.yml"
SECURE = ROOT / "docker-compose.yml"


def _commands(path: Path = COMPOSE) -> dict[str, list[str]]:
    import yaml

    services = yaml.safe_load(path.read_text())["services"]
    return {name: s["command"] for name, s in services.items()}


@pytest.mark.parametrize("path", [COMPOSE, SECURE], ids=lambda p: p.name)
def test_compose_names_the_router_merger_recorder_and_three_agents(path: Path) -> None:
    commands = _commands(path)
    assert {c[1] for c in commands.values()} - {"secure"} == {"router", "merger", "record", "agent"}
    assert sum(c[1] == "agent" for c in commands.values()) == 3


@pytest.mark.parametrize("path", [COMPOSE, SECURE], ids=lambda p: p.name)
def test_every_compose_command_parses_with_the_cli(path: Path) -> None:
    parser = build_parser()
    for name, command in _commands(path).items():
        assert command[0] == "fleetmap"
        args = parser.parse_args(command[1:])
        assert callable(args.func), name


def test_the_secured_compose_gives_each_robot_and_service_its_own_config(tmp_path: Path) -> None:
    commands = _commands(SECURE)
    secure = [a.replace("/secure", str(tmp_path)) for a in commands["secure"][1:]]
    assert main(secure) == 0
    assert main(secure) == 0  # a restarted deployment keeps its credentials
    for name, command in commands.items():
        if name == "secure":
            continue
        config = Path(command[command.index("--zenoh-config") + 1].replace("/secure", str(tmp_path)))
        text = json.loads("".join(line for line in config.read_text().splitlines() if not line.startswith("//")))
        robot = command[command.index("--robot") + 1] if "--robot" in command else None
        if name == "router":
            assert text["listen"]["endpoints"] == ["tcp/0.0.0.0:7447"]
        else:
            assert text["connect"]["endpoints"] == ["tcp/router:7447"]
            assert text["transport"]["auth"]["usrpwd"]["user"] == (
                robot or {"record": "recorder"}.get(command[1], command[1])
            )


def _on_loopback(command: list[str], endpoint: str, folder: Path) -> list[str]:
    """A compose command as it runs here: the router's address and the volumes replaced."""
    out = []
    for arg in command[1:]:
        for there, here in (
            ("tcp/0.0.0.0:7447", endpoint),
            ("tcp/router:7447", endpoint),
            ("/secure", str(folder / "secure")),
            ("/data", str(folder / "data")),
        ):
            arg = arg.replace(there, here)
        out.append(arg)
    return out


@pytest.mark.slow
def test_the_default_compose_runs_a_secured_fleet_that_maps_and_says_nothing_of_an_open_one(tmp_path: Path) -> None:
    """docker-compose.yml's own commands, in its order (secure, router, merger, recorder, an agent):
    the robot is placed in the global map that a viewer logged in to the fleet sees; the open
    compose's router says the fleet is open, the secured one does not. About 10 s."""
    from fleetmap.shared.io.keys import FleetKeys
    from fleetmap.shared.io.zenoh_config import free_loopback_endpoint

    from tests.bus_helpers import Inbox
    from tests.live.test_fleet import WAIT, fleetmap_cmd, processes, start
    from tests.live.test_security import _open

    endpoint = free_loopback_endpoint()
    commands = {name: _on_loopback(c, endpoint, tmp_path) for name, c in _commands(SECURE).items()}
    (tmp_path / "data").mkdir()
    assert main(commands.pop("secure")) == 0
    keys = FleetKeys("default")
    with processes() as procs:
        router = start(procs, *commands.pop("router"), log=tmp_path / "router.log")
        viewer = _open(tmp_path / "secure" / "viewer.json5", wait=WAIT)
        with viewer:
            services, poses = Inbox(), Inbox()
            viewer.subscribe_liveliness(keys.all_services, services, lambda k: None)
            viewer.subscribe(keys.pose("r1"), poses)
            start(procs, *commands.pop("merger"), log=tmp_path / "merger.log")
            start(procs, *commands.pop("recorder"), log=tmp_path / "recorder.log")
            assert services.wait_for(2, WAIT), services.items
            agent = commands.pop("agent1")
            agent[agent.index("--speed") + 1] = "8"
            start(procs, *agent, log=tmp_path / "agent.log")
            assert poses.wait_for(1, WAIT), "r1 was not placed"
        router.terminate()
        router.wait(WAIT)
    assert "OPEN fleet" not in (tmp_path / "router.log").read_text()
    assert "OPEN fleet" not in (tmp_path / "merger.log").read_text()
    # the open compose's router says so within its first lines (killed after WAIT if it does not)
    open_router = _on_loopback(_commands(COMPOSE)["router"], free_loopback_endpoint(), tmp_path)
    child = subprocess.Popen(fleetmap_cmd(*open_router), stderr=subprocess.PIPE, text=True)
    timer = threading.Timer(WAIT, child.kill)
    timer.start()
    said: list[str] = []
    try:
        while child.stderr is not None and len(said) < 5 and not any("OPEN fleet" in line for line in said):
            said.append(child.stderr.readline())
    finally:
        timer.cancel()
        child.terminate()
        child.wait(WAIT)
    assert any("OPEN fleet" in line for line in said), said
