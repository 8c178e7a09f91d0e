"""Two alignments of the same two groups of submaps, both borne out, in a building that repeats
itself: the one whose walls stand where the other group's lasers saw through loses."""

from __future__ import annotations

import pytest
from fleetmap.shared.config import FleetmapConfig

from tests.helpers import benchmark_tool


@pytest.mark.slow  # four agents and the merger on a scenario, without a bus (about 20 s)
def test_a_robot_kidnapped_into_an_aliased_lane_joins_where_no_wall_says_otherwise() -> None:
    # warehouse-events: r1 is kidnapped into the north lane, which the crashed r4 and r2 have
    # mapped. r4's aisle and r1's second epoch lie on r2's turn down the aisle four rack pitches
    # (14 m) west as well as where they are: five valid integrations bear out the wrong alignment,
    # two the right one, and each one's pairs bear it out. The wrong one puts the forklift's bay
    # where r2 saw a rack's end (40 m of solid wall in seen free space over the pairs); the right
    # one puts none. The fleet must be one map, r1 and r4 in it where they are, none merged wrongly.
    offline = benchmark_tool("offline")
    _, report, _ = offline.run("warehouse-events", FleetmapConfig(), 0.5)
    assert report["maps_merged_wrongly"] == [], report["maps_merged_wrongly"]
    for robot in ("r1", "r4"):
        r = report["robots"][robot]
        assert r["placed"], f"{robot} was left out of the fleet's map"
        assert r["error_m"] <= 0.1 and r["error_deg"] <= 2.0, r
    (kidnap,) = report["kidnaps"]
    assert kidnap["relocalized"] and not kidnap["false_relocalization"], kidnap
