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

Such a relation is the ground truth's error, not the map's; ``relations.py`` counts it apart from
the wrong ones. No threshold is added: the bounds are the wrong relation's own.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Transform2D, wrap_angle
from fleetmap.shared.core.tracking import ReferenceMap, ScanSamples, register
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
        self._samples: dict[int, ScanSamples] = {}
        self.params = TrackingParams()

    def samples(self, index: int) -> ScanSamples:
        if index not in self._samples:
            self._samples[index] = raw_samples(self.scans[index])
        return self._samples[index]

    def sides_with_map(
        self, i: int, j: int, truth: Transform2D, estimate: Transform2D, wrong_m: float, wrong_deg: float
    ) -> bool:
        """Whether scans ``i`` and ``j``'s raw returns put ``j`` in ``i``'s frame at the map's
        ``estimate`` rather than at the corrected relation ``truth`` (the module's docstring)."""
        reference = ReferenceMap(0.02)
        reference.insert(self.samples(i))
        try:
            fit = register(self.samples(j), reference, truth, truth, LOOSE, self.params)
        except np.linalg.LinAlgError:
            return False
        if not fit.converged:
            return False
        moved = fit.pose.as_array() - truth.as_array()
        moved[2] = wrap_angle(moved[2])
        return (
            beyond(truth.inverse().compose(fit.pose), wrong_m, wrong_deg)
            and not beyond(estimate.inverse().compose(fit.pose), wrong_m, wrong_deg)
            and float(moved @ fit.scan_information @ moved) > SIGNIFICANT
        )
