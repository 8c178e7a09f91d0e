"""The scan pair's returns as evidence of the step between them (docs/decisions/083 and 088).

Where the walls cannot place a scan (posts, hedges, open ground) the raw returns of the scan and
the one before it still measure the step between them
(:func:`~fleetmap.shared.core.pointstep.point_step`): a turn in place the wheels over-read, a fit
along a row of posts that slid a post along. :class:`~fleetmap.agents.tracker.Tracker` is a
:class:`PairReturns`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from fleetmap.agents.fitcheck import Fit
from fleetmap.agents.fitting import ScanIn
from fleetmap.agents.prediction import Predictor, borne_out
from fleetmap.agents.submap import SubmapChain
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.extraction import scan_points
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.motion import Prediction
from fleetmap.shared.core.pointstep import point_step
from fleetmap.shared.core.rangescan import RangeScan


class PairReturns:
    """The steps the scan pair's returns measure (the module docstring)."""

    config: FleetmapConfig
    chain: SubmapChain
    motion: Predictor
    exact: bool
    _pose: Transform2D | None
    _held: list[Any]
    _scan: tuple[int, RangeScan] | None
    _scan_before: tuple[int, RangeScan] | None

    def _borne_out(self, taken: ScanIn, fit: Fit, prediction: Prediction) -> Fit:
        """``fit``, or refused where it lies beyond the odometry's gate and the scan's returns
        against the scan before's do not bear it out (:func:`~fleetmap.agents.prediction.borne_out`;
        docs/decisions/088): the odometry then carries the scan. Only a reading that is the scan's
        own is asked (on a clock not trusted, the reading is interpolated at a stamp that may not
        be the scan's), and only of the scan after the one before it."""
        if not fit.good or self._held or prediction.source != "odometry" or not self.exact or self._pose is None:
            return fit
        returns = self._pair_returns(taken.seq)
        if returns is None:
            return fit
        placed = self.chain.active[0].origin.compose(fit.registration.pose)
        if borne_out(prediction, self._pose, placed, returns, self.motion.step_variance):
            return fit
        return replace(fit, good=False, why="a fit beyond the odometry's gate that the scan's returns do not bear out")

    def _by_points(self, seq: int, prediction: Prediction) -> Prediction:
        """``prediction`` of the step to scan ``seq``, or the step the returns of that scan and the
        one before measure over it (:func:`~fleetmap.shared.core.pointstep.point_step`; as sure as
        their distribution says, plus the drift the prediction carries), where both have returns
        and the odometry predicted it (constant velocity measures nothing: its window, metres
        wide on a sparse log, holds every look-alike step along a corridor). The step's own
        uncertainty (:attr:`~fleetmap.agents.prediction.Predictor.step_variance`) is the prior, and
        the measured one's is what the next step's drift adds (docs/decisions/083)."""
        returns = self._pair_returns(seq) if "odometry" in prediction.source else None
        if returns is None:
            return prediction
        reference, scan, angle_increment = returns
        variance_t, variance_r = self.motion.step_variance
        measured = point_step(
            reference, scan, prediction.increment, math.sqrt(variance_t), math.sqrt(variance_r), angle_increment
        )
        if measured is None:
            return prediction
        covariance = measured.covariance
        step_t, step_r = max(covariance[0, 0], covariance[1, 1]), covariance[2, 2]
        drift_t, drift_r = self.motion.drift
        self.motion.step_variance = (step_t, step_r)
        return replace(
            prediction,
            increment=measured.increment,
            sigma_translation=math.sqrt(step_t + drift_t),
            sigma_rotation=math.sqrt(step_r + drift_r),
        )

    def _pair_returns(self, seq: int) -> tuple[Array, Array, float] | None:
        """The returns of scan ``seq`` and of the scan just before it (each in its own laser frame)
        and the latter's beam spacing; None where the scan before it is not the last one seen."""
        before, now = self._scan_before, self._scan
        if before is None or now is None or before[0] != seq - 1:
            return None
        reach = self.config.extraction.max_range
        return scan_points(before[1], reach), scan_points(now[1], reach), before[1].angle_increment
