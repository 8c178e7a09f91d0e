"""What the merger counts (:class:`MergerStats`): messages taken, dropped and refused, pairs integrated."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any


@dataclass
class MergerStats:
    received: Counter[str] = field(default_factory=Counter)
    """Messages received, per schema."""
    malformed: int = 0
    malformed_reasons: Counter[str] = field(default_factory=Counter)
    """Malformed messages per 'schema field' (what was wrong)."""
    ignored: int = 0
    """Well-formed messages not meant for the merger on the key they came on."""
    foreign: int = 0
    """Messages naming another robot than the robot of their key (a robot speaking for another),
    dropped whatever the router allowed."""
    refused: Counter[str] = field(default_factory=Counter)
    """Messages and pairs refused by a limit (``MAX_SUBMAP_SEGMENTS``, ``max_robots``,
    ``MAX_QUEUED_PAIRS``), per limit."""
    stale: int = 0
    """Submap versions older than (or as old as) the version already held."""
    steps: int = 0
    integrations: int = 0
    """Pairs of submaps integrated (pose-free or near a prediction)."""
    near: int = 0
    """... of which registered near where the graph predicts them ..."""
    idle: int = 0
    """... and pose-free tries for robots apart from the global map, taken when nothing else was due."""
    join_pairs: int = 0
    """Near registrations queued between the groups of submaps a join put in one frame ..."""
    retried: int = 0
    """... and those of them integrated again pose-free, their registration not valid where the
    chains' drift may have carried them beyond its reach (docs/decisions/028)."""
    far_scored: int = 0
    """Pairs of submaps scored for the far search's order (:mod:`fleetmap.merger.farrank`)."""
    exhausted: int = 0
    """Integrations stopped at ``merge.max_integration_work`` (not valid; logged)."""
    failed: int = 0
    """Integrations and far scores that failed where they ran (a worker that died more often than it
    is retried, a Ray task's error): logged and dropped, the merger goes on."""
    poses_dropped: int = 0
    """Scans the pose thread had no room for (it keeps ``POSE_QUEUE`` waiting)."""
    key_scans: int = 0
    """Scans kept to register on the submaps they revisit (:mod:`fleetmap.merger.scangraph`)."""
    scan_registrations: int = 0
    """Key scans registered on other submaps by the last :meth:`~fleetmap.merger.engine.Merger.scan_poses` ..."""
    scan_constraints: int = 0
    """... and the fits kept as edges."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "received": dict(self.received),
            "malformed": self.malformed,
            "malformed_reasons": dict(self.malformed_reasons),
            "ignored": self.ignored,
            "foreign": self.foreign,
            "refused": dict(self.refused),
            "stale": self.stale,
            "steps": self.steps,
            "integrations": self.integrations,
            "near": self.near,
            "idle": self.idle,
            "join_pairs": self.join_pairs,
            "retried": self.retried,
            "far_scored": self.far_scored,
            "exhausted": self.exhausted,
            "failed": self.failed,
            "poses_dropped": self.poses_dropped,
            "key_scans": self.key_scans,
            "scan_registrations": self.scan_registrations,
            "scan_constraints": self.scan_constraints,
        }
