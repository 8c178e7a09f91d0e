"""Whether a corrected log's own raw scans side with a map against one of its relations.

The corrected logs' poses are GMapping's output (the data README: "good to a few centimetres"), and
their relations are every two scans within 2 m by those poses. Where GMapping itself placed a scan
wrong, a map that placed it right is scored wrong. csail-corrected has such scans: 42, 364 and
397-399 lie 7-12 degrees off the walls of their neighbours at their own corrected poses (scan 398
against the walls of scans 388-396 and 400-405: 30 % of its returns within 5 cm at its corrected
pose, 93 % at 12 degrees from it).

A wrong relation (more than 1 m or 10 degrees from the map's) is checked on the raw returns of its
two scans alone, no map: the second scan is registered on the first's returns (point-to-line ICP,
the tracker's ``register``, as ``relation_frame.py`` does), started at the corrected relation and
pulled towards nothing. The raw scans *side with the map* when all three hold:

- the registration ends beyond the wrong bound of the corrected relation, and within it of the map's;
- the move from the corrected relation is significant at the fit's own information (chi-square,
  3 degrees of freedom, 99.9 %): along a corridor, where the walls fix nothing, it is not;
- ``register`` ends no worse than it started (its own rule): the raw returns fit the answer at least
  as well as the corrected relation.

Where the two scans share too little wall for the pair alone to say (csail-corrected's scans 15
and 398: 1.3 m apart, facing away from each other), each scan's corrected pose is checked on its
neighbours in the log instead. A *step* (scan k to k + 1) is contradicted when the pair check above
holds for it against its corrected step (the raw fit ends beyond the wrong bound of it,
significantly). A scan lies in a *run* between the contradicted steps nearest it on either side
(GMapping turned csail-corrected's scans 397-399 11 degrees together, and back). The scan is
*re-placed* where both the scan before its run and the scan after it put it: registered on each
one's raw returns from its corrected pose, each fit must contradict that pose as above, and the two
must agree with each other (the difference of the two poses within chi-square's 99.9 % bound of
their summed covariances, Mangelson et al.'s pairwise consistency); the re-placed pose is their
information-weighted mean. A relation with a re-placed scan is taken between the re-placed poses;
the raw scans side with the map when that is beyond the wrong bound of the corrected relation and
within it of the map's. A scan far inside a long run shares no wall with the run's two neighbours
and is not re-placed; nor is csail-corrected's 399 (its fit on scan 396's returns slides 0.96 m
away on 15 % of its walls) or 364 (its two fits disagree).

Such a relation is the ground truth's error, not the map's; ``relations.py`` counts it apart from
the wrong ones. No threshold is added: the bounds are the wrong relation's own.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.tracking import ReferenceMap, Registration, ScanSamples, register
from fleetmap.shared.io.logs import read_carmen
from relation_frame import raw_samples
from scipy.stats import chi2

SIGNIFICANT = float(chi2.ppf(0.999, 3))
LOOSE = np.diag([1 / 100.0**2, 1 / 100.0**2, 1 / math.pi**2])
"""A prior that pulls towards nothing: it only keeps the normal equations solvable where the walls
leave a direction free."""


def beyond(t: Transform2D, wrong_m: float, wrong_deg: float) -> bool:
    """Whether the transform ``t`` is farther than the bound (m, degrees) from the identity."""
    return math.hypot(t.x, t.y) > wrong_m or math.degrees(abs(t.theta)) > wrong_deg


class RawTruth:
    """A corrected log's raw scans, to check its relations against (by scan index, as
    ``relations.corrected_relations`` numbers them)."""

    def __init__(self, path: Path) -> None:
        self.scans = [s for s in read_carmen(path) if s.odometry is not None]
        self.poses = [Transform2D(*s.odometry) for s in self.scans]
        self._samples: dict[int, ScanSamples] = {}
        self._steps: dict[tuple[int, float, float], Transform2D | None] = {}
        self.params = TrackingParams()

    def samples(self, index: int) -> ScanSamples:
        if index not in self._samples:
            self._samples[index] = raw_samples(self.scans[index])
        return self._samples[index]

    def _raw_fit(self, i: int, j: int, truth: Transform2D, wrong_m: float, wrong_deg: float) -> Registration | None:
        """Scan ``j`` registered on scan ``i``'s raw returns from the corrected relation ``truth``:
        the registration where it ends beyond the wrong bound of ``truth``, significantly (the
        module's docstring), else None."""
        reference = ReferenceMap(0.02)
        reference.insert(self.samples(i))
        try:
            fit = register(self.samples(j), reference, truth, truth, LOOSE, self.params)
        except np.linalg.LinAlgError:
            return None
        if not fit.converged:
            return None
        moved = fit.pose.as_array() - truth.as_array()
        moved[2] = wrap_angle(moved[2])
        if beyond(truth.inverse().compose(fit.pose), wrong_m, wrong_deg) and (
            float(moved @ fit.scan_information @ moved) > SIGNIFICANT
        ):
            return fit
        return None

    def step(self, k: int, wrong_m: float, wrong_deg: float) -> Transform2D | None:
        """Scan ``k + 1`` in scan ``k``'s frame by their raw returns where that contradicts the
        corrected step, else None."""
        key = (k, wrong_m, wrong_deg)
        if key not in self._steps:
            truth = self.poses[k].inverse().compose(self.poses[k + 1])
            fit = self._raw_fit(k, k + 1, truth, wrong_m, wrong_deg)
            self._steps[key] = None if fit is None else fit.pose
        return self._steps[key]

    def _placed_on(self, k: int, index: int, wrong_m: float, wrong_deg: float) -> tuple[Transform2D, Array] | None:
        """Scan ``index``'s pose and covariance (in the log's frame) registered on scan ``k``'s raw
        returns, where that contradicts its corrected pose (:meth:`_raw_fit`), else None."""
        truth = self.poses[k].inverse().compose(self.poses[index])
        fit = self._raw_fit(k, index, truth, wrong_m, wrong_deg)
        if fit is None:
            return None
        c, s = math.cos(self.poses[k].theta), math.sin(self.poses[k].theta)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return self.poses[k].compose(fit.pose), turn @ np.linalg.inv(fit.information) @ turn.T

    def replaced(self, index: int, wrong_m: float, wrong_deg: float) -> Transform2D | None:
        """Scan ``index``'s pose by the raw returns of the scans on either side of its run, where
        both contradict its corrected pose and agree with each other (the module's docstring),
        else None."""
        first, last = index, index
        while first > 0 and self.step(first - 1, wrong_m, wrong_deg) is None:
            first -= 1
        while last < len(self.poses) - 1 and self.step(last, wrong_m, wrong_deg) is None:
            last += 1
        if first == 0 or last == len(self.poses) - 1:
            return None
        before = self._placed_on(first - 1, index, wrong_m, wrong_deg)
        after = self._placed_on(last + 1, index, wrong_m, wrong_deg)
        if before is None or after is None:
            return None
        difference = before[0].as_array() - after[0].as_array()
        difference[2] = wrap_angle(difference[2])
        if float(difference @ np.linalg.solve(before[1] + after[1], difference)) > SIGNIFICANT:
            return None
        weights = np.linalg.inv(before[1]) + np.linalg.inv(after[1])
        mean = after[0].as_array() + np.linalg.solve(weights, np.linalg.inv(before[1]) @ difference)
        return Transform2D.from_array(mean)

    def sides_with_map(
        self, i: int, j: int, truth: Transform2D, estimate: Transform2D, wrong_m: float, wrong_deg: float
    ) -> bool:
        """Whether scans ``i`` and ``j``'s raw returns put ``j`` in ``i``'s frame at the map's
        ``estimate`` rather than at the corrected relation ``truth``: by the pair's own returns, or
        by the runs they are re-placed with (the module's docstring)."""
        fit = self._raw_fit(i, j, truth, wrong_m, wrong_deg)
        if fit is not None and not beyond(estimate.inverse().compose(fit.pose), wrong_m, wrong_deg):
            return True
        a, b = self.replaced(i, wrong_m, wrong_deg), self.replaced(j, wrong_m, wrong_deg)
        if a is None and b is None:
            return False
        between = (a or self.poses[i]).inverse().compose(b or self.poses[j])
        return beyond(truth.inverse().compose(between), wrong_m, wrong_deg) and not beyond(
            estimate.inverse().compose(between), wrong_m, wrong_deg
        )
