"""The command line, run as a user runs it: exit codes, one-line errors, JSON exactly as the contracts."""

from __future__ import annotations

import argparse
import io
import json
import math
import re
import subprocess
import sys
import tomllib
from collections.abc import Callable
from fnmatch import fnmatch
from pathlib import Path

import msgpack
import numpy as np
import pytest
from fleetmap.scenarios.laser import LaserParams, simulate_scan
from fleetmap.shared.config_files import load_config
from fleetmap.shared.io.messages import FleetEvent
from fleetmap.shared.io.recording import RecordingWriter
from mcap.writer import CompressionType

from fleetmap import config_args
from fleetmap.cli import COMMANDS, build_parser, main
from tests.helpers import ROOM

EXAMPLES = Path(__file__).resolve().parents[1] / "src" / "fleetmap" / "examples"


def fleetmap(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetmap", *args], capture_output=True, text=True, input=stdin, timeout=120
    )


def write_map(path: Path, segments: list[list[float]], **extra: object) -> str:
    path.write_text(json.dumps({"segments": segments, "ordered": True, **extra}))
    return str(path)


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_integrate_json_prints_the_contract_fields_and_recovers_the_example() -> None:
    r = fleetmap("integrate", str(EXAMPLES / "scan_a.json"), str(EXAMPLES / "scan_b.json"), "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == {"x", "y", "theta", "value", "valid", "seconds"}
    # The example scans were simulated from (4.5, 4.5, 0.4) and (5.8, 5.2, 1.3).
    assert math.hypot(out["x"] - 1.46997, out["y"] - 0.13850) < 0.02
    assert abs(out["theta"] - 0.9) < math.radians(0.5)
    assert out["valid"] is True and out["value"] > 3 and 0 < out["seconds"] < 5


@pytest.mark.parametrize("how", ["--aligner", "--config"])
def test_integrate_with_the_ransac_aligner_recovers_the_example(
    how: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "fleet.toml"
    cfg.write_text('[integration]\naligner = "ransac"\n')
    choice = ["--aligner", "ransac"] if how == "--aligner" else ["--config", str(cfg)]
    code = main(["integrate", str(EXAMPLES / "scan_a.json"), str(EXAMPLES / "scan_b.json"), *choice, "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    r = json.loads(out)
    assert math.hypot(r["x"] - 1.46997, r["y"] - 0.13850) < 0.02
    assert abs(r["theta"] - 0.9) < math.radians(0.5) and r["valid"] is True


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_integrate_batch_answers_every_line_in_order(tmp_path: Path) -> None:
    a = json.loads((EXAMPLES / "scan_a.json").read_text())
    b = json.loads((EXAMPLES / "scan_b.json").read_text())
    lines = [{"id": "ab", "a": a, "b": b}, {"id": "ba", "a": b, "b": a}, {"id": "aa", "a": a, "b": a}]
    batch = tmp_path / "pairs.jsonl"
    batch.write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    r = fleetmap("integrate", "--batch", str(batch), "--json")
    assert r.returncode == 0, r.stderr
    rows = [json.loads(x) for x in r.stdout.splitlines()]
    assert [x["id"] for x in rows] == ["ab", "ba", "aa"]
    assert all(set(x) == {"id", "x", "y", "theta", "value", "valid", "seconds"} for x in rows)
    # B on A and A on B are inverse transforms; A on itself is the identity.
    ab, ba, aa = rows
    c, s = math.cos(ab["theta"]), math.sin(ab["theta"])
    assert abs(ba["theta"] + ab["theta"]) < 0.01
    assert math.hypot(ba["x"] + c * ab["x"] + s * ab["y"], ba["y"] - s * ab["x"] + c * ab["y"]) < 0.03
    assert math.hypot(aa["x"], aa["y"]) < 1e-6 and abs(aa["theta"]) < 1e-6


@pytest.mark.parametrize(
    "content, needle",
    [
        ("{not json", "malformed JSON"),
        ('{"segments": [[0, 0, NaN, 1]]}', "NaN or infinite"),
        ('{"segments": [[0, 0, 1e999, 1]]}', "NaN or infinite"),
        (json.dumps({"segments": [[1, 1, 1, 1]]}), "zero length"),
        (json.dumps({"segments": []}), "empty"),
        (json.dumps({"segments": [[0, 0, 1]]}), "segment 0 must be"),
        (json.dumps([1, 2]), "must be a JSON object"),
    ],
)
def test_bad_map_files_exit_2_with_one_line_naming_the_file(
    tmp_path: Path, content: str, needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # In process (the command line's main, as the console script runs it): the process exit codes
    # themselves are tested below and in the other commands' tests.
    from fleetmap.cli import main

    bad = tmp_path / "bad.json"
    bad.write_text(content)
    code = main(["integrate", str(EXAMPLES / "scan_a.json"), str(bad), "--json"])
    out, err = capsys.readouterr()
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and needle in lines[0], err
    assert out == ""


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_a_missing_file_exits_2_naming_it(tmp_path: Path) -> None:
    r = fleetmap("integrate", str(tmp_path / "nope.json"), str(EXAMPLES / "scan_a.json"))
    assert r.returncode == 2 and "nope.json: no such file" in r.stderr


@pytest.mark.slow  # one of the fast suite's slowest (1.5-2.7 s): CI runs it with the slow ones
def test_a_bad_batch_line_exits_2_naming_line_and_id(tmp_path: Path) -> None:
    a = json.loads((EXAMPLES / "scan_a.json").read_text())
    batch = tmp_path / "pairs.jsonl"
    batch.write_text(
        json.dumps({"id": "ok", "a": a, "b": a}) + "\n" + json.dumps({"id": "x7", "a": a, "b": {"segments": []}}) + "\n"
    )
    r = fleetmap("integrate", "--batch", str(batch), "--json")
    assert r.returncode == 2 and "pairs.jsonl:2 (id x7) map b" in r.stderr and "empty" in r.stderr


@pytest.mark.slow  # starts processes: run in CI, deselected by -m "not slow"
def test_parameter_overrides_and_config_files_are_checked(tmp_path: Path) -> None:
    a, b = str(EXAMPLES / "scan_a.json"), str(EXAMPLES / "scan_b.json")
    r = fleetmap("integrate", a, b, "--heuristic", "histogram", "--point-distance-tolerance", "0.01", "--json")
    assert r.returncode == 0, r.stderr
    cfg = tmp_path / "fleet.toml"
    cfg.write_text("[integration]\npoint_distance_tolerence = 0.01\n")
    r = fleetmap("integrate", a, b, "--config", str(cfg))
    assert r.returncode == 2 and "point_distance_tolerence" in r.stderr and "unknown parameter" in r.stderr
    r = fleetmap("integrate", a, b, "--heuristic", "psychic")
    assert r.returncode == 2 and "psychic" in r.stderr


def test_extract_writes_one_line_per_scan_in_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    scans = [simulate_scan(ROOM, (4.0 + 0.3 * k, 4.5, 0.2 * k), LaserParams(), rng, stamp=100.0 + k) for k in range(3)]
    src = tmp_path / "scans.jsonl"
    src.write_text("\n".join(json.dumps(s.to_json_dict()) for s in scans) + "\n")
    out = tmp_path / "segments.jsonl"
    r = fleetmap("extract", str(src), "--format", "ranges-jsonl", "--out", str(out))
    assert r.returncode == 0, r.stderr
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert [x["stamp"] for x in rows] == [100.0, 101.0, 102.0]
    assert all(x["ordered"] is True and len(x["segments"]) >= 4 for x in rows)


@pytest.mark.slow  # one of the fast suite's slowest (about 1 s): CI runs it with the slow ones
def test_extract_reads_carmen_and_rejects_garbage(tmp_path: Path) -> None:
    log = tmp_path / "run.clf"
    ranges = " ".join(["2.0"] * 181)
    log.write_text(f"FLASER 181 {ranges} 0 0 0 0 0 0 5.0 host 5.0\n")
    out = tmp_path / "o.jsonl"
    assert fleetmap("extract", str(log), "--format", "carmen", "--out", str(out)).returncode == 0
    assert json.loads(out.read_text())["stamp"] == 5.0
    junk = tmp_path / "junk.clf"
    junk.write_text("hello\n")
    r = fleetmap("extract", str(junk), "--format", "carmen", "--out", str(out))
    assert r.returncode == 2 and "junk.clf" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow  # starts processes: run in CI, deselected by -m "not slow"
def test_every_command_is_listed_and_a_misspelt_one_is_refused_naming_them() -> None:
    listed = build_parser().format_help()
    misspelt = fleetmap("integrat", "a.json")
    assert misspelt.returncode == 2
    for name in COMMANDS:
        assert name in listed, f"{name} missing from --help"
        assert f"'{name}'" in misspelt.stderr, f"{name} missing from the choices"
    # A command given after -v still parses as that command (the global options take no value).
    with pytest.raises(SystemExit) as done:
        main(["-v", "integrate", "--help"])
    assert done.value.code == 0


@pytest.mark.slow  # runs fleetmap processes
@pytest.mark.parametrize(
    ("command", "flag", "says"),
    [
        ("merger", "--state", "does not exist (--state)"),
        ("record", "--out", "does not exist (--out)"),
    ],
)
def test_a_service_told_to_write_into_a_missing_folder_exits_2_before_it_starts(
    tmp_path: Path, command: str, flag: str, says: str
) -> None:
    # checked at start (under restart: unless-stopped, a service that dies at its first write
    # crash-loops), before any zenoh session opens
    target = tmp_path / "nowhere" / "file"
    r = fleetmap(command, flag, str(target), "--listen", "tcp/127.0.0.1:1")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and str(target) in lines[0] and says in lines[0], r.stderr


def _byte_flipped_recording() -> bytes:
    """A small recording with bytes flipped where the mcap library decodes text (a channel's
    topic): it raised UnicodeDecodeError, an exit 1 with a traceback's last line."""
    stream = io.BytesIO()
    writer = RecordingWriter(stream, compression=CompressionType.NONE)
    writer.write_raw("fleet/default/events", FleetEvent("recorder_start", None, 1.0).to_msgpack(), 1, 1)
    writer.finish()
    data = bytearray(stream.getvalue())
    at = data.index(b"fleet/default/events")
    data[at : at + 4] = b"\xff\xfe\xfd\xfc"
    return bytes(data)


@pytest.mark.slow  # runs fleetmap processes
def test_input_faults_of_every_command_exit_2_with_one_plain_line(tmp_path: Path) -> None:
    # no exception names, no Rust error structures, no numpy warnings: one line naming the fault
    (tmp_path / "a-file").write_text("")
    huge = tmp_path / "huge.json"
    huge.write_text(json.dumps({"segments": [[0, 0, 1e308, 0], [0, 1, 2, 3]], "ordered": False}))
    scan = str(EXAMPLES / "scan_a.json")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(bytes(range(256)))
    flipped = tmp_path / "flipped.mcap"
    flipped.write_bytes(_byte_flipped_recording())
    shape = tmp_path / "merger.state"  # msgpack, of the state's version, holding a list where its robots go
    shape.write_bytes(msgpack.packb({"v": 2, "submaps": [], "edges": [], "robots": [1], "seq": 0, "stamp": 0}))
    cases = [
        (["merge", scan, scan.replace("_a", "_b"), "--plot", str(tmp_path / "nowhere" / "g.png")], "does not exist"),
        (["run", "--out", str(tmp_path / "a-file" / "run")], "cannot be made a folder (--out)"),
        (["router", "--listen", "bogus"], "--listen bogus: Endpoints must be of the form"),
        (["router", "--listen", "tcp/127.0.0.1:99999"], "port 99999 is not a port number"),
        (["integrate", str(huge), scan], "segment 0 lies beyond 1e+06 m of the origin"),
        (["integrate", scan, scan, "--config", str(binary)], f"{binary}: not a text file"),
        (["replay", str(flipped), "--out", str(tmp_path / "r1")], f"{flipped}: corrupt MCAP file"),
        (["recover", str(flipped), str(tmp_path / "fixed.mcap")], f"{flipped}: corrupt MCAP file"),
        (["replay", str(flipped), "--out", str(tmp_path / "r2"), "--from", "nan"], "--from: must be a number"),
        (["merger", "--state", str(shape), "--listen", "tcp/127.0.0.1:0"], f"{shape}: cannot load the merger state"),
    ]
    for args, says in cases:
        r = fleetmap(*args)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and says in lines[0], (args, r.stderr)
        assert "Error" not in lines[0] and "Warning" not in lines[0] and "Message {" not in lines[0], lines[0]


@pytest.mark.parametrize("command", COMMANDS)
def test_help_reads_usage_first_and_says_what_each_flag_is(command: str) -> None:
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    text = sub.format_help()
    usage = text.split("\n\n")[0]
    assert usage.startswith(f"usage: fleetmap {command}") and usage.endswith("[options]") and len(usage) < 200, usage
    for action in sub._actions:
        if action.option_strings and not isinstance(action, argparse._HelpAction):
            assert action.help and not action.help.startswith("default"), (command, action.option_strings)
    if command == "run":
        from fleetmap.scenarios.loader import list_scenarios

        flat = " ".join(text.split()).replace("- ", "-")  # argparse wraps lines at a name's hyphen
        assert all(name in flat for name in list_scenarios())


@pytest.mark.slow  # runs fleetmap processes
def test_absurd_but_finite_ranges_map_without_numpy_warnings(tmp_path: Path) -> None:
    # readings of 1e308 m (beyond float32: no return) among real ones
    scan = {"stamp": 1.0, "angle_min": -1.5, "angle_increment": 0.01, "range_max": 1e308}
    scans = tmp_path / "huge.jsonl"
    scans.write_text(json.dumps({**scan, "ranges": [1e308] * 100 + [2.0] * 200}) + "\n")
    r = fleetmap("map", str(scans), "--out", str(tmp_path / "out"), "--no-progress")
    assert r.returncode == 0 and "Warning" not in r.stderr, r.stderr


def test_verbosity_flags_are_taken_anywhere_on_the_line(tmp_path: Path) -> None:
    import logging

    from fleetmap.cli import _verbosity

    assert _verbosity(["merger", "-v", "--fleet", "x", "-vv"]) == (["merger", "--fleet", "x"], 3)
    assert _verbosity(["-q", "record", "--out", "f", "--", "-v"]) == (["record", "--out", "f", "--", "-v"], -1)
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        root.handlers.clear()  # basicConfig configures only a root logger without handlers
        out = tmp_path / "map.json"
        out.write_text('{"segments": [[0, 0, 1, 0]], "ordered": false}')
        assert main(["merge", str(out), "--json", "-qq"]) == 0
        assert logging.getLogger().level == logging.CRITICAL
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


@pytest.mark.slow
def test_a_service_writes_its_threads_stacks_on_sigusr1_and_goes_on(tmp_path: Path) -> None:
    import signal
    import socket
    import threading
    import time

    from fleetmap.shared.io.zenoh_config import free_loopback_endpoint

    def listening(host: str, port: int) -> bool:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            return False

    def wait_for(predicate: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return False
            threading.Event().wait(0.1)
        return True

    endpoint = free_loopback_endpoint()
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    err = tmp_path / "router.err"
    with err.open("wb") as stderr:
        router = subprocess.Popen([sys.executable, "-m", "fleetmap", "router", "--listen", endpoint], stderr=stderr)
    try:
        assert wait_for(lambda: listening(host, int(port)) or router.poll() is not None, 30.0)
        assert router.poll() is None, err.read_text()
        router.send_signal(signal.SIGUSR1)
        assert wait_for(lambda: "most recent call first" in err.read_text(), 5.0), err.read_text()
        assert router.poll() is None, "SIGUSR1 stopped the service"
    finally:
        router.terminate()
        router.wait(20)


def _help(command: str) -> str:
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return " ".join(sub.format_help().split()).replace("- ", "-")  # argparse wraps lines at a hyphen


def test_the_basic_config_the_help_names_is_there_and_installs_with_the_package() -> None:
    found = re.search(r"(\S+basic\.toml)", _help("map"))
    assert found, "the --config help names no basic config"
    named = Path(found.group(1))
    assert named.is_file() and load_config(named).extraction.max_range > 0
    # pip copies a package's files that pyproject.toml declares as its package data, and no others
    package = Path(config_args.__file__).resolve().parent
    declared = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert any(fnmatch(named.relative_to(package).as_posix(), g) for g in declared["package-data"]["fleetmap"])


@pytest.mark.parametrize(
    ("command", "args"),
    [("map", ["log.clf", "--out", "o"]), ("extract", ["log.clf", "--format", "carmen", "--out", "o"])],
)
def test_a_logs_no_return_reading_is_named_apart_from_max_range_and_its_old_name_still_works(
    command: str, args: list[str]
) -> None:
    parser = build_parser(command)
    for flag in ("--no-return-reading", "--range-max"):
        assert parser.parse_args([command, *args, flag, "50"]).no_return_reading == 50.0
    assert math.isinf(parser.parse_args([command, *args]).no_return_reading)
    shown = _help(command)
    assert "--no-return-reading" in shown and "--range-max" not in shown


def test_the_example_config_every_help_names_is_installed_and_loads(capsys: pytest.CaptureFixture[str]) -> None:
    # CI installs the package (not editable): the path the help names is the installed copy's
    with pytest.raises(SystemExit):
        main(["map", "--help"])
    # the help wraps at hyphens (a path's site-packages, a worktree's name): join them again
    named = re.search(r"(\S+basic\.toml)", re.sub(r"-\s+", "-", " ".join(capsys.readouterr().out.split())))
    assert named is not None
    path = Path(named.group(1))
    assert path.is_file(), f"the help names {path}, which is not installed"
    assert Path(config_args.__file__).parent in path.parents
    assert load_config(path).extraction.max_range == tomllib.loads(path.read_text())["extraction"]["max_range"]
