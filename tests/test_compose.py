"""docker-compose.yml runs fleetmap commands; there is no Docker engine here, so its commands are
checked to be real commands of this CLI with valid arguments (their behaviour is tested in tests/live)."""

from __future__ import annotations

from pathlib import Path

from fleetmap.cli import build_parser

COMPOSE = Path(__file__).resolve().parents[1] / "docker-compose.yml"


def _commands() -> dict[str, list[str]]:
    import yaml

    services = yaml.safe_load(COMPOSE.read_text())["services"]
    return {name: s["command"] for name, s in services.items()}


def test_compose_names_the_router_merger_recorder_and_three_agents() -> None:
    commands = _commands()
    assert {c[1] for c in commands.values()} == {"router", "merger", "record", "agent"}
    assert sum(c[1] == "agent" for c in commands.values()) == 3


def test_every_compose_command_parses_with_the_cli() -> None:
    parser = build_parser()
    for name, command in _commands().items():
        assert command[0] == "fleetmap"
        args = parser.parse_args(command[1:])
        assert callable(args.func), name
