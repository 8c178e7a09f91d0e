"""The typed config: stages, tags, the basic example, overrides from files and recordings,
retired parameters, unknown ones refused."""

from __future__ import annotations

import importlib
import logging
import re
import tomllib
from dataclasses import fields
from pathlib import Path

import pytest
from fleetmap.shared.config import (
    SECTIONS,
    FleetmapConfig,
    IntegrationParams,
    parameters,
    tuned,
)
from fleetmap.shared.config_files import RETIRED, apply_overrides, load_config
from fleetmap.shared.errors import BadInput

from fleetmap.cli import build_parser
from fleetmap.config_args import config_from_args, field_sentences, preset

BASIC = Path(__file__).resolve().parents[2] / "src" / "fleetmap" / "examples" / "basic.toml"


def test_a_retired_parameter_still_loads_said_at_info_at_its_value_with_a_warning_at_another(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # (milliseconds) a recording made before a parameter became a constant still replays with its config
    old = {
        "merge": {"carried_max_ambiguity": 0.25, "far_budget": 12, "join_support": 3, "max_robots": 9},
        "integration": {"valid_min_map_value": 8.0, "ransac": {"ransac_iterations": 2000}},
        "tracking": {"registration": "point_to_curve"},  # a feature dropped (record 012)
    }
    with caplog.at_level(logging.INFO, logger="fleetmap.shared.config_files"):
        config = apply_overrides(FleetmapConfig(), old, "fleet.toml")
    assert config == tuned(FleetmapConfig(), max_robots=9)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [
        "fleet.toml: [merge] join_support = 3 is no longer a parameter: it is fixed at 2 "
        "(fleetmap.merger.joins.JOIN_SUPPORT); this run uses 2",
        "fleet.toml: [tracking] registration = 'point_to_curve' is no longer a parameter: it is fixed at "
        "'point_to_line' (fleetmap.shared.core.tracking.RESIDUAL); this run uses 'point_to_line'",
    ]
    said = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.INFO)
    for name in ("[merge] far_budget", "[integration] valid_min_map_value", "[integration.ransac] ransac_iterations"):
        assert name in said
    with pytest.raises(BadInput, match=r"\[merge\] no_such_thing: unknown parameter"):
        apply_overrides(FleetmapConfig(), {"merge": {"no_such_thing": 1}}, "fleet.toml")
    with pytest.raises(BadInput, match=r"unknown section \[validity\]"):
        apply_overrides(FleetmapConfig(), {"validity": {"valid_min_value": 1.0}}, "fleet.toml")


def test_every_parameter_is_tagged_paper_or_fleetmap_with_a_one_line_doc() -> None:
    names = [f.name for _, f in parameters()]
    assert len(names) == len(set(names)), "a parameter name is in two sections"
    for path, f in parameters():
        assert f.metadata["origin"] in ("paper", "fleetmap"), f"{path}.{f.name}"
        sentence = field_sentences(SECTIONS[path]).get(f.name, "")
        assert 10 < len(sentence) <= 160, f"{path}.{f.name}: {sentence!r}"
    paper = {f.name for _, f in parameters() if f.metadata["origin"] == "paper"}
    assert {"tau", "kappa", "point_distance_tolerance", "fusion_tolerance", "segment_length_refuse"} <= paper
    assert "max_speed" not in paper


def test_the_basic_example_holds_exactly_the_basic_parameters_at_their_defaults() -> None:
    data = tomllib.loads(BASIC.read_text(encoding="utf-8"))
    given: dict[str, object] = {}

    def walk(path: str, table: dict[str, object]) -> None:
        for key, value in table.items():
            if isinstance(value, dict):
                walk(f"{path}.{key}" if path else key, value)
            else:
                given[f"{path}.{key}"] = value

    walk("", data)
    defaults = FleetmapConfig().flat()
    basic = {f"{path}.{f.name}" for path, f in parameters() if f.metadata["basic"]}
    assert set(given) == basic
    assert all(given[k] == defaults[k] for k in basic)
    assert load_config(BASIC) == FleetmapConfig()


def test_every_retired_parameter_is_fixed_at_the_value_of_the_constant_that_replaced_it() -> None:
    # (a few seconds, importing the modules) a config at the old default loads quietly only if the
    # constant kept that value
    for table, entries in RETIRED.items():
        assert table not in SECTIONS or not set(entries) & {f.name for f in fields(SECTIONS[table])}, table
        for name, retired in entries.items():
            if retired.value is None:
                continue  # a feature removed
            module, constant = ("fleetmap." + retired.constant).rsplit(".", 1)
            assert getattr(importlib.import_module(module), constant) == retired.value, (table, name)


def test_at_most_40_public_parameters_and_help_all_lists_them_all(capsys: pytest.CaptureFixture[str]) -> None:
    # (about a second) issue 51: a config a person can read
    assert len(parameters()) <= 40
    with pytest.raises(SystemExit):
        build_parser("map").parse_args(["map", "--help-all"])
    groups = re.split(r"^(\S.*):$", capsys.readouterr().out, flags=re.M)
    listed = [
        option
        for title, text in zip(groups[1::2], groups[2::2], strict=True)
        if " parameters" in title
        for option in re.findall(r"^  --([a-z-]+) ", text, re.M)
    ]
    assert sorted(listed) == sorted(f.name.replace("_", "-") for _, f in parameters())


def test_the_presets_differ_where_live_and_offline_differ_and_a_users_file_goes_on_top(tmp_path: Path) -> None:
    # (milliseconds)
    live, off = preset("live"), preset("offline")
    assert live == FleetmapConfig() and off.merge.step_seconds == 5.0 and off.merge.max_integration_work == 0
    mine = tmp_path / "mine.toml"
    mine.write_text("[merge]\nmax_integration_work = 1000\n", encoding="utf-8")
    args = build_parser("map").parse_args(["map", "in.log", "--out", "o", "--config", str(mine), "--max-robots", "9"])
    config = config_from_args(args)
    assert (config.merge.max_integration_work, config.merge.step_seconds, config.merge.max_robots) == (1000, 5.0, 9)


def test_a_config_written_by_a_run_loads_back_to_the_same_config(tmp_path: Path) -> None:
    config = tuned(FleetmapConfig(), kappa=0.03, max_speed=1.5, map_free_space_clearance=0.2, pivot_refine=False)
    assert config.integration.motion.max_speed == 1.5
    assert config.integration.validity.map_free_space_clearance == 0.2
    file = tmp_path / "config.toml"
    file.write_text(config.to_toml(), encoding="utf-8")
    assert load_config(file) == config
    with pytest.raises(BadInput, match="no such parameter: max_sped"):
        tuned(IntegrationParams(), max_sped=1.0)


def test_a_parameter_in_its_old_table_is_read_in_its_stage(tmp_path: Path) -> None:
    # configs and recordings written before the validity and motion tables still load
    old = tmp_path / "old.toml"
    old.write_text("[integration]\nkappa = 0.03\n", encoding="utf-8")
    with pytest.raises(BadInput, match=r"\[integration\] kappa: unknown parameter"):
        load_config(old)  # an extraction parameter was never one of integration's
    old.write_text("[integration]\nmap_free_space_clearance = 0.2\nmax_speed = 2.0\n", encoding="utf-8")
    config = load_config(old)
    assert config.integration.validity.map_free_space_clearance == 0.2
    assert config.integration.motion.max_speed == 2.0


def test_help_shows_the_basic_parameters_and_help_all_every_one(capsys: pytest.CaptureFixture[str]) -> None:
    def help_of(flag: str) -> str:
        with pytest.raises(SystemExit) as done:
            build_parser("map").parse_args(["map", flag])
        assert done.value.code == 0
        return capsys.readouterr().out

    short, full = help_of("--help"), help_of("--help-all")
    assert "--max-range" in short and "--max-speed" in short
    assert "--point-distance-tolerance" not in short and "--map-free-space-clearance" not in short
    assert "--point-distance-tolerance" in full and "[integration.validity]" in full
    assert "[paper] POINTDISTANCETOLERANCE" in full
    for _, f in parameters():
        option = re.compile(rf"^  --{f.name.replace('_', '-')} ", re.M)
        assert bool(option.search(short)) == f.metadata["basic"] and option.search(full), f.name
