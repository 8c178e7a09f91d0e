"""The typed config: stages, tags, the basic example, overrides from files and recordings,
retired parameters, unknown ones refused."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from fleetmap.shared.config import (
    SECTIONS,
    FleetmapConfig,
    IntegrationParams,
    parameters,
    tuned,
)
from fleetmap.shared.config_files import apply_overrides, load_config
from fleetmap.shared.errors import BadInput

from fleetmap.cli import build_parser
from fleetmap.config_args import field_sentences

BASIC = Path(__file__).resolve().parents[2] / "src" / "fleetmap" / "examples" / "basic.toml"


def test_a_retired_parameter_in_an_old_config_is_ignored_and_an_unknown_one_refused() -> None:
    # a recording made before a parameter was retired still replays with its own config
    old = {"merge": {"carried_max_ambiguity": 0.25, "histogram_bins": 36, "bridge_min_value": 10.0, "join_support": 3}}
    old["tracking"] = {"registration": "point_to_curve"}
    config = apply_overrides(FleetmapConfig(), old, "the recording's config")
    assert config.merge.join_support == 3
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


def test_a_config_written_by_a_run_loads_back_to_the_same_config(tmp_path: Path) -> None:
    config = tuned(FleetmapConfig(), kappa=0.03, max_speed=1.5, valid_min_map_value=9.0, pivot_refine=False)
    assert config.integration.motion.max_speed == 1.5
    assert config.integration.validity.valid_min_map_value == 9.0
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
    old.write_text("[integration]\nvalid_min_map_value = 10.0\nmax_speed = 2.0\n", encoding="utf-8")
    config = load_config(old)
    assert config.integration.validity.valid_min_map_value == 10.0
    assert config.integration.motion.max_speed == 2.0


def test_help_shows_the_basic_parameters_and_help_all_every_one(capsys: pytest.CaptureFixture[str]) -> None:
    def help_of(flag: str) -> str:
        with pytest.raises(SystemExit) as done:
            build_parser("map").parse_args(["map", flag])
        assert done.value.code == 0
        return capsys.readouterr().out

    short, full = help_of("--help"), help_of("--help-all")
    assert "--max-range" in short and "--max-speed" in short
    assert "--point-distance-tolerance" not in short and "--valid-min-map-value" not in short
    assert "--point-distance-tolerance" in full and "[integration.validity]" in full
    assert "[paper] POINTDISTANCETOLERANCE" in full
    assert len(short.splitlines()) < len(full.splitlines()) / 3
