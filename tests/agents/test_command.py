"""``fleetmap agent`` refuses bad input before it goes on the bus: exit 2, one line naming it."""

from __future__ import annotations

import pytest

from fleetmap.cli import main


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--robot", "r9", "--scenario", "department"], "robot 'r9': not in scenario 'department'"),
        (["--robot", "R1", "--scenario", "department"], "--robot: 'R1' is not a valid name"),
        (["--robot", "r1", "--carmen", "missing.log"], "missing.log: no such file"),
        (["--robot", "r1", "--ros2-bag", "missing.mcap"], "missing.mcap: no such file"),
        (["--robot", "r1", "--scenario", "department", "--start", "3"], "apply to --carmen only"),
        (["--robot", "r1", "--scenario", "department", "--speed", "-1"], "--speed: must be 0"),
        (["--robot", "r1", "--scenario", "department", "--kidnap-after", "0"], "kidnap_after: must be a positive"),
    ],
)
def test_bad_input_exits_2_with_one_line_naming_it(tmp_path, monkeypatch, capsys, args, says):
    monkeypatch.chdir(tmp_path)
    assert main(["agent", *args, "--connect", "tcp/127.0.0.1:9", "--wait-for-listener", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fleetmap agent: error: ") and says in err[0]


def test_odometry_on_for_a_source_without_odometry_exits_2(tmp_path, monkeypatch, capsys):
    from tests.agents.test_sources import write_bag

    bag = tmp_path / "laser-only.mcap"
    write_bag(bag, [(5.0, [1.0, 2.0, 3.0])])
    args = ["agent", "--robot", "r1", "--ros2-bag", str(bag), "--odometry", "on", "--connect", "tcp/127.0.0.1:9"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no odometry" in err[0] and str(bag) in err[0]
