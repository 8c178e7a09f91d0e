"""The ground truth of a scenario: every scan's true pose and the wall parts the scans see.

This is what scores a run (:mod:`fleetmap.scenarios.metrics`) and what ``fleetmap simulate`` writes
to ``truth.json``; none of it is ever sent to the algorithms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fleetmap.scenarios.fleet import Event, Kidnap, MergerRestart, PlannedScan, Scenario, plan
from fleetmap.scenarios.metrics import visible_walls
from fleetmap.shared.core.geometry import Array, Transform2D


@dataclass(frozen=True, eq=False)
class GroundTruth:
    scenario: Scenario
    scans: tuple[PlannedScan, ...]
    """Every scan of every robot, by robot (in the scenario's order), then index."""
    visible: Array
    """``(k, 4)`` wall parts hit by the scans (world frame), see :func:`~fleetmap.scenarios.metrics.visible_walls`."""

    def pose(self, robot: str, index: int) -> Transform2D:
        """True laser pose of scan ``index`` of ``robot``."""
        for s in self.scans:
            if s.robot == robot and s.index == index:
                return s.pose
        raise KeyError(f"no scan {index} of robot {robot!r}")

    def to_json_dict(self) -> dict[str, Any]:
        sc = self.scenario
        return {
            "scenario": sc.name,
            "world": {"name": sc.world.name, "walls": sc.world.walls.round(6).tolist()},
            "scans": [
                {"robot": s.robot, "index": s.index, "stamp": s.stamp, "leg": s.leg, "pose": s.pose.to_dict()}
                for s in self.scans
            ],
            "events": [event_to_dict(e) for e in sc.events],
            "visible_walls": self.visible.round(6).tolist(),
        }


def event_to_dict(e: Event) -> dict[str, Any]:
    out: dict[str, Any] = {"t": e.t, "type": e.kind}
    if isinstance(e, MergerRestart):
        out["down_for"] = e.down_for
    else:
        out["robot"] = e.robot
    if isinstance(e, Kidnap):
        out["pose"] = e.pose.to_dict()
        out["path"] = [list(p) for p in e.path]
    return out


def ground_truth(scenario: Scenario) -> GroundTruth:
    scans = tuple(s for r in scenario.robots for s in plan(scenario, r.id))
    return GroundTruth(scenario, scans, visible_walls(scenario.world.walls, (s.pose for s in scans), scenario.laser))
