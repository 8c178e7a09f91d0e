"""docker-compose.yml runs fleetmap commands; there is no Docker engine here, so its commands are
checked to be real commands of this CLI with valid arguments (their behaviour is tested in tests/live)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fleetmap.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
SECURE = ROOT / "docker-compose.secure.yml"


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
