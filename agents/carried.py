"""Scans the motion model carried, placed again once the walls place a scan after them
(docs/decisions/090).

Where the walls neither place a scan nor say it was taken elsewhere (open ground, posts, a person
in front of the laser), the tracker *carries* it: places it where its motion model predicts
(:meth:`~fleetmap.agents.tracker.Tracker._carried`), each such step's uncertainty adding to the
next. When the walls place a scan again, the chain of carried steps has two known ends: the last
scan the walls placed before it (the *anchor*, ``A``) and the scan just fitted (``P_k``), which the
chain predicted at ``P^_k``. The chain's most likely poses spread that miss over its steps in
proportion to each one's uncertainty, as a fixed-lag smoother does over the stretch between two
measurements (Rauch-Tung-Striebel's, for a linear chain): the miss as a correction in the anchor's
frame, ``G = (A^-1 P_k) (A^-1 P^_k)^-1``, and each carried scan ``i`` moved by the share of it its
prediction's heading variance holds of the fitted scan's, ``w_i = var_i / var_k``:
``P_i <- A G^w_i A^-1 P_i`` (``G^w = exp(w log G)``, SE(2)'s geodesic,
:func:`fleetmap.agents.bursts.between` from the identity: a turn the wheels over-read
in place is taken back round the anchor, where it was turned). A turn in place is what the wheels
read worst and the walls least often check (a robot turning among posts): record 089's campus
scans 102-103, placed 11 degrees off by a turn the odometry read 9 degrees too far, come within a
degree or two.

Only what is not yet final moves. A scan's pose in the submap that placed it is what the merger
composes (the submap's placed-scan table, and the scan's message), and a submap published final
never changes. The agent holds a carried scan's message, and the final version of a finished
submap that placed one, while the run may still move it; a run holds a scan for as long as its
submap is one of the two active ones or the one finished just before them (the one that placed a
scan is often finished by that scan's own insertion), so no message waits longer than the robot
takes to fill about one submap (:meth:`CarriedRun.expire`); the run goes on from the scans still
open, its let-go scans keeping their poses. The walls the carried scans put in their submaps stay where
they were inserted, and so do submap frames and links: they are consistent with one another, and
a frame is only a frame. Scans the walls did not place while the robot moved blind (no segment)
are in the run too, for their poses in the tracking (``Agent.tracked``). A run ends unsmoothed
where the walls contradict a scan (towards a kidnap: the chain is broken), at a new epoch, and
where the scan that ends it was predicted without odometry (constant velocity measures no step).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from fleetmap.agents.bursts import between
from fleetmap.agents.submap import PlacedScan, Submap
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.motion import Prediction


@dataclass
class RunScan:
    """One scan of a carried run."""

    index: int
    pose: Transform2D
    """Its pose in the epoch's frame, as carried."""
    variance: float
    """Its prediction's heading variance (rad^2): what the carried steps before it left open."""
    submap: Submap | None
    """The submap that placed it (None: a scan with nothing to track, moved blind)."""


@dataclass(frozen=True)
class Smoothed:
    """A scan of a run, placed again: its pose in the epoch's frame and, where a submap placed
    it, its pose in that submap's frame."""

    pose: Transform2D
    in_submap: Transform2D | None


def spread_miss(
    anchor: Transform2D, poses: list[Transform2D], weights: list[float], predicted: Transform2D, fitted: Transform2D
) -> list[Transform2D]:
    """``poses`` (epoch frame) of a carried chain from ``anchor``, each moved by its share
    ``weights`` (0 to 1) of the miss between where the chain ``predicted`` its next scan and where
    that scan was ``fitted`` (the module docstring)."""
    back = anchor.inverse()
    g = back.compose(fitted).compose(back.compose(predicted).inverse())
    return [
        anchor.compose(between(Transform2D(), g, float(np.clip(w, 0.0, 1.0)))).compose(back.compose(p))
        for p, w in zip(poses, weights, strict=True)
    ]


@dataclass
class CarriedRun:
    """The run of scans carried since the last scan the walls placed (the module docstring)."""

    anchor: Transform2D | None = None
    """The epoch pose of the last scan the walls placed before the run (None: no run open)."""
    scans: list[RunScan] = field(default_factory=list)
    smoothed: dict[int, Smoothed] = field(default_factory=dict)
    """The scans the last run that ended placed again, by index (:meth:`take_smoothed`)."""

    def holds(self, index: int) -> bool:
        """Whether scan ``index`` may still be placed again (its message waits: ``Agent``)."""
        return self.anchor is not None and any(s.index == index for s in self.scans)

    def carry(
        self, index: int, pose: Transform2D, prediction: Prediction, submap: Submap, anchor: Transform2D | None
    ) -> None:
        """Scan ``index`` carried to ``pose`` (epoch frame) by ``prediction``, placed by ``submap``;
        ``anchor``: the last placed scan's pose where the walls placed it (a run starts there)."""
        if self.anchor is None:
            if anchor is None:
                return
            self.anchor = anchor
        self.scans.append(RunScan(index, pose, prediction.sigma_rotation**2, submap))

    def blind(self, index: int, pose: Transform2D, prediction: Prediction) -> None:
        """Scan ``index``, with nothing to track, moved blind to ``pose`` within a run."""
        if self.anchor is not None:
            self.scans.append(RunScan(index, pose, prediction.sigma_rotation**2, None))

    def close(self, fitted: Transform2D, predicted: Transform2D, prediction: Prediction) -> None:
        """The walls placed a scan at ``fitted`` (epoch frame) that the run's chain ``predicted``
        there by ``prediction``: the run's scans placed again, and their submaps' tables with them."""
        anchor, scans = self.anchor, self.scans
        self.drop()
        if anchor is None or not scans or "odometry" not in prediction.source:
            return
        variance = prediction.sigma_rotation**2
        weights = [s.variance / variance for s in scans]
        for s, pose in zip(
            scans, spread_miss(anchor, [s.pose for s in scans], weights, predicted, fitted), strict=True
        ):
            if s.submap is None:
                self.smoothed[s.index] = Smoothed(pose, None)
                continue
            in_submap = s.submap.origin.inverse().compose(pose)
            placed = s.submap.placed
            at = next(n for n in range(len(placed) - 1, -1, -1) if placed[n].index == s.index)
            placed[at] = PlacedScan(s.index, placed[at].stamp, in_submap)
            self.smoothed[s.index] = Smoothed(pose, in_submap)

    def places(self, submap: Submap) -> bool:
        """Whether the run holds a scan ``submap`` placed (its final version waits: ``Agent``)."""
        return any(s.submap is submap for s in self.scans)

    def expire(self, oldest: int) -> None:
        """Let go of the run's scans up to the last placed by a submap older than number ``oldest``:
        they keep their poses."""
        done = [n for n, s in enumerate(self.scans) if s.submap is not None and s.submap.number < oldest]
        if done:
            del self.scans[: done[-1] + 1]  # (the run goes on from its anchor: their steps are in its chain)

    def drop(self) -> None:
        """End the run where it stands (its scans keep their poses)."""
        self.anchor, self.scans = None, []

    def take_smoothed(self) -> dict[int, Smoothed]:
        """The scans placed again since the last call, by index."""
        out, self.smoothed = self.smoothed, {}
        return out
