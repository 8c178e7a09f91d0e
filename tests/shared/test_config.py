"""The typed config: overrides from files and recordings, retired parameters, unknown ones refused."""

from __future__ import annotations

import pytest
from fleetmap.shared.config import FleetmapConfig, apply_overrides
from fleetmap.shared.errors import BadInput


def test_a_retired_parameter_in_an_old_config_is_ignored_and_an_unknown_one_refused() -> None:
    # a recording made before a parameter was retired still replays with its own config
    old = {"merge": {"carried_max_ambiguity": 0.25, "join_support": 3}}
    config = apply_overrides(FleetmapConfig(), old, "the recording's config")
    assert config.merge.join_support == 3
    with pytest.raises(BadInput, match=r"\[merge\] no_such_thing: unknown parameter"):
        apply_overrides(FleetmapConfig(), {"merge": {"no_such_thing": 1}}, "fleet.toml")
