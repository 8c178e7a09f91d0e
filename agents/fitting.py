"""Where a scan fits on the matching submap: every start the motion models, the scan pair and
the walls suggest, registered and checked, and the one taken (step 2 of
:mod:`fleetmap.agents.tracker`'s walk-through; :meth:`FitSearch._fit`).

:class:`FitSearch` is the tracker's search for a fit, apart from what the tracker then does with
it (place the scan, carry the robot, hold the scan towards a kidnap): it reads the tracker's state
(the last placed scan, the robot's recent scores, the motion models, the active submap) and
changes nothing but the step the scan pair measured (``_step``) and the recent scores.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

from fleetmap.agents.fitcheck import (
    TYPICAL_SCORE_SHARE,
    Fit,
    beam_margin,
    best_fit,
    judge,
    same_start,
    swept_fit,
    turned_fits,
    typical_floor,
    window_fit,
)
from fleetmap.agents.pose_free import LOOSE_ROTATION, LOOSE_TRANSLATION, ambiguous, loose, paired, reacquired
from fleetmap.agents.prediction import OTHER_SIGN, Predictor, explains, within_gate
from fleetmap.agents.submap import Submap, SubmapChain
from fleetmap.shared.config import FleetmapConfig, TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.motion import Prediction
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.tracking import (
    MAX_CORRESPONDENCE,
    REACH_ROTATION,
    Registration,
    ScanSamples,
    beam_evidence,
    register,
)

__all__ = ["FitSearch", "ScanIn"]

log = logging.getLogger("fleetmap.agents.tracker")  # (its messages are the tracker's)


@dataclass(frozen=True)
class ScanIn:
    """A scan as the tracker takes it (:meth:`Tracker.add`), with its number in the robot's sequence
    of scans and its samples."""

    seq: int
    index: int
    stamp: float
    scan: RangeScan
    segments: Array
    samples: ScanSamples
    odometry: Transform2D | None


class FitSearch:
    """The search for a scan's fit (the module docstring); :class:`~fleetmap.agents.tracker.Tracker`
    is one."""

    config: FleetmapConfig
    params: TrackingParams
    chain: SubmapChain
    motion: Predictor
    exact: bool
    by_pace: bool
    _pose: Transform2D | None
    _stamp: float | None
    _seq: int
    _good: tuple[float, Transform2D, int] | None
    _previous: tuple[Array, tuple[float, Transform2D, int]] | None
    _step: Prediction | None
    _paired: Transform2D | None
    """Where the scan pair's integration, ambiguous, put the scan (the submap's frame): a start
    for the window's search (:meth:`_searched`)."""
    _scores: deque[float]

    def _pose_in_epoch(self, prediction: Prediction) -> Transform2D:
        base = self._pose if self._pose is not None else Transform2D()
        return base.compose(prediction.increment)

    def _fit(self, taken: ScanIn, predictions: list[Prediction]) -> Fit:
        """The scan's fit on the matching submap.

        The first prediction's fit is taken when it is good and typical: its score at least
        ``TYPICAL_SCORE_SHARE`` of the median of the robot's recent fits (a fit that suddenly
        supports a third of what the last ones did has likely slid into a wrong minimum). Otherwise
        the other predictions and the robot standing still are tried too, and the pose-free
        integration (:meth:`_reacquired`) if none is typical; a later fit replaces an earlier good one
        only if it scores over ``1 / TYPICAL_SCORE_SHARE`` times as much (along a corridor the fits
        score alike, and the first prediction's stands: :func:`~fleetmap.agents.fitcheck.best_fit`),
        unless the walls refused it: the models left, as unsure as each other, weigh by score.
        The odometry's other sign, in doubt, is always tried, and weighed by score alone
        (:func:`_either_sign`). The scan pair's fit (:meth:`_stepped`), good but not typical, is
        the first of them, and a turned start's typical fit replaces it only so too
        (:func:`_replaces`); a burst's reading that constant velocity agrees with needs no scan
        pair (:meth:`_agreed`). Failing all, the first fit, not good."""
        submap = self.chain.active[0]
        share = TYPICAL_SCORE_SHARE
        floor = typical_floor(self._scores)
        if (agreed := self._agreed(taken, predictions, floor)) is not None:
            return agreed
        measured = self._stepped(taken, predictions[0])
        if measured is not None and measured.registration.score >= floor:
            self._scores.append(measured.registration.score)
            return measured
        tried: list[Transform2D] = []
        fits: list[Fit] = []
        priors: list[Prediction] = []  # each fit's motion model
        last = self._good[1] if self._good is not None else self._pose or Transform2D()
        standing = self.motion.standing
        apart = _apart(predictions)
        signed: Fit | None = None  # the fit from the odometry's other sign, in doubt
        for n, prediction in enumerate([*predictions, standing]):
            typical = fits and fits[0].good and fits[0].registration.score >= floor
            if n and typical and not (apart and n == 1) and prediction.source != OTHER_SIGN:
                continue  # (the odometry's other sign, in doubt, is registered: the walls weigh it)
            # the robot standing still where it was last placed; the models from its last pose
            base = last.compose(prediction.increment) if prediction is standing else self._pose_in_epoch(prediction)
            predicted = submap.origin.inverse().compose(base)
            if any(same_start(predicted, other) for other in tried):
                continue
            tried.append(predicted)
            fit = self._registered(taken, submap, predicted, predicted, prediction)
            if prediction is standing and self.exact:  # (the wheels measure standing still too)
                fit = _explained(fit, predictions[0], submap.origin, self._pose or Transform2D())
            if prediction.source == OTHER_SIGN:
                signed = fit
                continue
            fits.append(fit)
            priors.append(prediction)
        best = _either_sign(best_fit(fits, apart, priors), signed)
        if measured is not None and (best is None or best.registration.score * share < measured.registration.score):
            best = measured  # (registration started from the pair's step: a later fit must outscore it)
        if best is None or best.registration.score < floor:
            # only a typical fit from a turned start: an atypical one is no better than the
            # prediction's own, which the pose-free integration below may still replace
            turned = self._turned_fits(taken, predictions[0], floor, tried)
            fits += turned
            if (
                turned
                and turned[-1].good
                and turned[-1].registration.score >= floor
                and _replaces(turned[-1], best, measured)
            ):
                best = turned[-1]
            elif best is None:
                best = self._swept(taken, predictions[0], self._reachable_fit(taken, turned))
        if best is None or best.registration.score < floor:
            best = self._reacquired(taken, submap, predictions[0], best, floor)
        if best is not None:
            best = self._searched(taken, predictions[0], best)
            self._scores.append(best.registration.score)
            return best
        return replace(fits[0], everywhere=all(f.disputed for f in fits))

    def _reacquired(
        self, taken: ScanIn, submap: Submap, prediction: Prediction, best: Fit | None, floor: float
    ) -> Fit | None:
        """``best`` (no start's fit typical), or the scan re-acquired by pose-free integration
        (:meth:`_reacquire`). Where no start placed the scan, the re-acquired fit must fit as well
        as the robot's scans usually do: one that explains a fraction of what they did matched a
        look-alike (a carried robot's view of one corridor on another). Where a start's fit is no
        typical one either, the re-acquired one is weighed as any later start's: scoring over
        ``1 / TYPICAL_SCORE_SHARE`` times as much, it replaces it (edmonton-corrected without
        odometry, scan 94: constant velocity's fit scored 1.86, 0.5 m off, the re-acquired one
        4.49, 0.1 m off, the robot's floor 5.03; kept, the weak fit was searched about and slid
        1.4 m along the corridor). Where the stamps, still trusted, give the scan less time than
        its sequence (:meth:`_stamps_shrink`), it is also re-acquired within the sequence's reach
        (:meth:`_by_sequence`), and that fit is taken only if typical."""
        again = self._reacquire(taken, submap, prediction)
        if (again is None or again.registration.score < floor) and self._stamps_shrink(taken):
            untimed = self._by_sequence(partial(self._reacquire, taken, submap, prediction))
            if untimed is None or untimed.registration.score < floor:
                untimed = self._by_sequence(partial(self._sequence_fit, taken))
            again = untimed if untimed is not None and untimed.registration.score >= floor else again
        if again is None:
            return best
        if best is None:
            return again if again.registration.score >= floor else None
        return again if again.registration.score * TYPICAL_SCORE_SHARE >= best.registration.score else best

    def _stamps_shrink(self, taken: ScanIn) -> bool:
        """Whether the stamps, still trusted, give the scan less time since the last placed scan
        than the scans' sequence does at the log's mean period (a logger that stamps a burst at
        receipt shrinks a second to milliseconds, and the robot's reach with it)."""
        clock, good = self.motion.clock, self._good
        if good is None or not clock.times(taken.seq - good[2], taken.seq):
            return False
        return taken.stamp - good[0] < (taken.seq - good[2]) * clock.period

    def _by_sequence(self, search: Callable[[], Fit | None]) -> Fit | None:
        """``search`` with the robot's reach timed by the scans' sequence, not by the stamps: the
        clock shapes where registration starts and the search's bounds, but a scan that fits
        typically only in the time its sequence takes is evidence against the stamps (said when
        it is placed: :func:`~fleetmap.agents.clock_evidence.check_motion`), not a reason to
        place it where it fits poorly (freiburg-101-corrected in bursts without odometry, scan 4:
        a metre and 27 degrees from scan 3, stamped a millisecond after it; the one fit within a
        millisecond's reach scored 0.79 a metre off, the true pose's 6.08; docs/decisions/068)."""
        clock = self.motion.clock
        clock.trusted = False
        try:
            return search()
        finally:
            clock.trusted = True

    def _sequence_fit(self, taken: ScanIn) -> Fit | None:
        """Constant velocity timed by the scans' sequence (:meth:`Predictor.velocity_by_sequence`),
        registered from its prediction and, where good, searched about it (:meth:`_searched`), as a
        true clock's constant velocity is; None where not good. Where the pair's integration and the
        re-acquisition are not valid, this is the search a clock that shrank the interval kept the
        scan from (aces-corrected in bursts without odometry, scan 4: a metre from scan 3, stamped
        0.6 ms after it; constant velocity over 0.6 ms, 5 cm wide, held it where scan 3 was, at a
        score of 2.51; timed by the sequence, constant velocity and its window place it as the true
        clock does, at 14.9; docs/decisions/075)."""
        prediction = self.motion.velocity_by_sequence(taken.seq, self._seq)
        _submap, mean, registered = self._window(taken, prediction)
        fit = registered(mean)
        return self._searched(taken, prediction, fit) if fit.good else None

    def _agreed(self, taken: ScanIn, predictions: list[Prediction], floor: float) -> Fit | None:
        """Where a burst's reading (spread between the bursts' readings, or given to the scan by
        the robot's pace) and constant velocity, measured by two placed scans, put the scan within
        registration's reach of each other (:func:`~fleetmap.agents.fitcheck.same_start`), the
        first prediction's fit, if good and typical: two motion models agree, one from the wheels
        and one from the scans placed before, and the scan pair (:meth:`_stepped`), which says
        where registration starts when the reading may be a step off, is not integrated. None
        otherwise. Integrating the pair at every such scan cost aces in bursts 15 ms a scan,
        against 3 on its true clock, for the same share of steps within 0.10 m and 2 degrees
        (docs/decisions/066)."""
        if not ("odometry" in predictions[0].source and self.by_pace and self.motion.velocity_known):
            return None
        reading = next((p for p in predictions if p.source == "odometry"), None)
        velocity = next((p for p in predictions if p.source == "velocity"), None)
        if reading is None or velocity is None:
            return None
        submap = self.chain.active[0]
        a, b, start = (
            submap.origin.inverse().compose(self._pose_in_epoch(p)) for p in (reading, velocity, predictions[0])
        )
        if not same_start(a, b):
            return None
        fit = self._registered(taken, submap, start, start, predictions[0])
        if not (fit.good and fit.registration.score >= floor):
            return None
        self._step = None  # (no pair measured this step)
        self._scores.append(fit.registration.score)
        return fit

    def _searched(self, taken: ScanIn, prediction: Prediction, best: Fit) -> Fit:
        """``best``, or a better fit from the prediction's window (:func:`window_fit`) where the
        prediction is constant velocity and its two sigma, no farther than the robot drives in one
        scan step, is wider than registration's reach. The odometry's prediction is never searched,
        however wide: its prior is evidence along a corridor that the walls' support is not (a
        burst's spread readings, searched, placed aces-corrected's robot up to 6 m backwards).
        Where the scan pair's integration was valid but for a rival nearly as good (ambiguous), its
        best transformation within the window is registered first (:attr:`_paired`;
        docs/decisions/069)."""
        radius = self._radius(taken, prediction)
        if not best.good or radius <= MAX_CORRESPONDENCE or "odometry" in prediction.source:
            return best
        submap, mean, registered = self._window(taken, prediction)
        against = partial(self._against, taken, submap)
        seed = self._paired
        seeds = [seed] if seed is not None and math.hypot(seed.x - mean.x, seed.y - mean.y) <= radius else []
        return window_fit(
            against(best), submap, taken.samples, mean, radius, prediction, _then(registered, against), seeds
        )

    def _swept(self, taken: ScanIn, prediction: Prediction, best: Fit | None) -> Fit | None:
        """A fit from a turned start alone (:meth:`_reachable_fit`), or a better one from the
        prediction's window searched at every heading it allows (:func:`swept_fit`), where the
        prediction is constant velocity unsure of the heading beyond registration's reach and its
        window wider than registration's reach, and no scan pair measured the step (its gate holds
        a weak fit, as the odometry's does). A turned start searches only the predicted position:
        a turn that also carried the robot a metre aside lies beyond it (orebro-corrected, scan
        216; docs/decisions/062). Where no turned start fitted either (``best`` None), the window
        is searched all the same, a fit found there kept only where the robot can have driven: a
        scan is held as fitting nowhere only once nowhere near its prediction was searched
        (acapulco-corrected, a scan in ten dropped, five people, no odometry: scan 300 turned
        60 degrees one way where constant velocity turned it 36 the other, its true pose's fit
        typical, 2.6 m from the predicted position; docs/decisions/071)."""
        radius = self._radius(taken, prediction)
        if (
            radius <= MAX_CORRESPONDENCE
            or prediction.sigma_rotation <= REACH_ROTATION
            or "odometry" in prediction.source
            or self._step is not None
        ):
            return best
        submap, mean, registered = self._window(taken, prediction)
        against = partial(self._against, taken, submap)
        found = swept_fit(
            None if best is None else against(best),
            submap,
            taken.samples,
            mean,
            radius,
            prediction,
            _then(registered, against),
        )
        if best is None and found is not None:
            placed = submap.origin.compose(found.registration.pose)
            if not self.motion.reachable(self._good, placed, taken.seq, taken.stamp):
                return None
        return found

    def _radius(self, taken: ScanIn, prediction: Prediction) -> float:
        """How far from the prediction the scan may be: two sigma, within the robot's reach."""
        last = (self._stamp if self._stamp is not None else taken.stamp, self._pose or Transform2D(), self._seq)
        return min(2.0 * prediction.sigma_translation, self.motion.reach(last, taken.seq, taken.stamp))

    def _stepped(self, taken: ScanIn, prediction: Prediction) -> Fit | None:
        """Where the motion model measures nothing (no odometry; constant velocity wider than
        registration's reach), the step measured by the scan's pose-free integration on the last
        scan the walls placed (not a carried one: :func:`~fleetmap.agents.pose_free.stepped`;
        record 045), within the robot's reach since that scan, registered from there on the
        submap: its fit when good, else None (the motion models are tried then). A typical fit is
        taken at once; one that is not (a turn, little of the scan on the submap yet) is the first
        of the fits (:meth:`_fit`), replaced only by one scoring ``1 / TYPICAL_SCORE_SHARE`` times
        as much: the pair's step is where registration starts, as the first prediction's start is
        elsewhere (freiburg-101-corrected, scans 60 and 93, with odometry in bursts and without
        it: the pair's fits 0.01-0.03 m off the true step, the motion models' that replaced them
        0.2-0.4 m and 5-7 degrees off; docs/decisions/060).

        A reading spread within a burst (not :attr:`exact`) is a guess that the robot kept its pace
        between the burst's two readings: registered from it, a scan slides to a look-alike of the
        walls (freiburg-101-corrected in bursts: scan 150, its reading 0.8 m short, settled 1.8 m
        on, where a corridor's walls repeat). The scan pair's step is then where registration
        starts, the reading still its prior (record 052): along a corridor whose pair slides, the
        reading holds the robot as it did. So for a burst's own reading given to a scan by the
        robot's pace (:attr:`by_pace`; record 054)."""
        self._step = self._paired = None
        spread = "odometry" in prediction.source and self.by_pace
        if self._previous is None or (
            not spread and ("odometry" in prediction.source or self._radius(taken, prediction) <= MAX_CORRESPONDENCE)
        ):
            return None
        segments, last = self._previous
        found = paired(
            segments, taken.segments, self.motion.reach(last, taken.seq, taken.stamp), self.config.integration
        )
        submap = self.chain.active[0]
        if found is None or not found.valid:
            if found is not None and ambiguous(segments, taken.segments, found, self.config.integration):
                self._paired = submap.origin.inverse().compose(last[1].compose(found.transform))
            return None
        placed = last[1].compose(found.transform)
        increment = (self._pose or Transform2D()).inverse().compose(placed)
        measured = Prediction(increment, LOOSE_TRANSLATION, LOOSE_ROTATION, "integration")
        start = submap.origin.inverse().compose(placed)
        if spread:
            mean = submap.origin.inverse().compose(self._pose_in_epoch(prediction))
            fit = self._registered(taken, submap, start, mean, prediction)
        else:
            fit = self._registered(taken, submap, start, start, measured)
        if fit.good and fit.registration.score >= typical_floor(self._scores):
            return fit
        self._step = None if fit.contradicted else measured  # (the walls say nothing against it)
        return fit if fit.good else None

    def _turned_fits(self, taken: ScanIn, prediction: Prediction, floor: float, tried: list[Transform2D]) -> list[Fit]:
        """Fits from starts turned across the prediction's heading uncertainty (:func:`turned_fits`)."""
        _submap, mean, registered = self._window(taken, prediction)
        return turned_fits(mean, prediction.sigma_rotation, floor, tried, registered)

    def _window(
        self, taken: ScanIn, prediction: Prediction
    ) -> tuple[Submap, Transform2D, Callable[[Transform2D], Fit]]:
        """What a search about the prediction needs: the matching submap, the prediction's mean in
        its frame, and the scan registered on it from a start, pulled towards that mean."""
        submap = self.chain.active[0]
        mean = submap.origin.inverse().compose(self._pose_in_epoch(prediction))
        return submap, mean, partial(self._registered, taken, submap, mean=mean, prediction=prediction)

    def _reachable_fit(self, taken: ScanIn, fits: list[Fit]) -> Fit | None:
        """No start of the motion models placed the scan: the best good fit from a turned start
        (:func:`best_fit`) where the robot can have driven, as a re-acquired one must be, however
        little of the scan the submap holds yet (a turn into new space: acapulco-corrected without
        odometry, scan 77, a fit at half the robot's typical score, 0.04 m from the truth). One
        that slid beyond that lies where no start searched (scan 161: 5.7 m along a corridor).
        Where the scan pair measured the step (``_step``: the walls said nothing against it), a fit
        this weak must lie within that step's 99 % gate, as one must within the odometry's: the
        pair's integration is evidence, a turned start that a few metres of wall support is not
        (orebro-corrected, scan 59: the pair measured the 30-degree turn within 0.1 m and a degree;
        2.7 m of wall took a start 92 degrees from it, and the map after it ran turned by as much)."""
        origin, last, seq, stamp = self.chain.active[0].origin, self._good, taken.seq, taken.stamp
        reachable = [f for f in fits if self.motion.reachable(last, origin.compose(f.registration.pose), seq, stamp)]
        step = self._step
        if step is not None:
            predicted = self._pose_in_epoch(step)
            reachable = [f for f in reachable if within_gate(origin.compose(f.registration.pose), predicted, step)]
        best = best_fit(reachable, False)
        if best is not None:
            log.debug("scan %d fits from a turned start alone (score %.2f)", taken.index, best.registration.score)
        return best

    def _registered(
        self, taken: ScanIn, submap: Submap, start: Transform2D, mean: Transform2D, prediction: Prediction
    ) -> Fit:
        """The scan registered on ``submap`` from ``start``, pulled towards the prediction's
        ``mean`` with its information, and checked (:meth:`_judge`)."""
        reg = register(taken.samples, submap.reference, start, mean, prediction.information(), self.params)
        return self._judge(reg, taken, submap)

    def _judge(self, reg: Registration, taken: ScanIn, submap: Submap) -> Fit:
        """The fit check (:func:`~fleetmap.agents.fitcheck.judge`), its beam test excusing the
        uncertainty of the track the robot is carried on."""
        max_range = self.config.extraction.max_range
        return judge(reg, taken.scan, taken.segments, submap, max_range, self.motion.track_drift)

    def _against(self, taken: ScanIn, submap: Submap, fit: Fit) -> Fit:
        """A good fit with the submap's wall its beams pass through and return from
        (:attr:`~fleetmap.agents.fitcheck.Fit.beams`), for a window search to weigh it
        (:func:`~fleetmap.agents.fitcheck.weighed`); the beam test's margin excuses the uncertainty
        of the track the robot is carried on, as the fit check's does."""
        if not fit.good or fit.beams is not None:
            return fit
        margin = beam_margin(self.motion.track_drift)
        beams = beam_evidence(
            submap.reference, taken.scan, fit.registration.pose, self.config.extraction.max_range, margin
        )
        return replace(fit, beams=beams)

    def _reacquire(self, taken: ScanIn, submap: Submap, prediction: Prediction) -> Fit | None:
        """The paper's pose-free integration of the scan on the submap, within the robot's reach of
        its last placed scan (any heading), then registered and checked: a fit where the robot can
        have driven, or None. Where the odometry measured the step (the scan's own reading, on a
        clock trusted or not read at its stamps), that is also within its 99 % gate (a log without
        a clock bounds no reach: infinite-corridor-corrected's scan 151 was re-acquired 15.6 m and
        88 degrees from its odometry, and the rest of the map turned with it)."""
        reach = self.motion.reach(self._good, taken.seq, taken.stamp)
        last = submap.origin.inverse().compose(self._good[1] if self._good is not None else self._pose or Transform2D())
        max_range = self.config.extraction.max_range
        start = reacquired(submap.segment_map(), taken.segments, last, reach, max_range, self.config.integration)
        if start is None:
            return None
        reg = register(taken.samples, submap.reference, start, start, loose(), self.params)
        fit = self._judge(reg, taken, submap)
        placed = submap.origin.compose(reg.pose)
        if not fit.good or not self.motion.reachable(self._good, placed, taken.seq, taken.stamp):
            return None
        measured = prediction.source == "odometry" and self.exact  # not a mistimed or spread reading
        if measured and not within_gate(placed, self._pose_in_epoch(prediction), prediction):
            return None
        return replace(fit, why="reacquired")


def _replaces(fit: Fit, best: Fit | None, measured: Fit | None) -> bool:
    """Whether a typical ``fit`` replaces ``best``: over the scan pair's fit ``measured`` only by
    outscoring it ``1 / TYPICAL_SCORE_SHARE`` times, as any later start must (orebro-corrected,
    scan 36: the pair's fit 4.29, right; a start turned round 5.33, the robot's floor 5.00)."""
    return (
        best is None or best is not measured or fit.registration.score * TYPICAL_SCORE_SHARE >= best.registration.score
    )


def _then(registered: Callable[[Transform2D], Fit], then: Callable[[Fit], Fit]) -> Callable[[Transform2D], Fit]:
    """``registered``, each fit it gives passed on through ``then``."""
    return lambda start: then(registered(start))


def _apart(predictions: list[Prediction]) -> bool:
    """Whether the first two motion models disagree on the heading by more than the first one's
    uncertainty: one of them is wrong (a real robot's odometry can be off by 10-25 degrees on one
    fast turn), and a registration started ten degrees off may settle in a wrong minimum. The walls
    fix the heading everywhere, so both are registered and the better fit by score is taken."""
    return (
        len(predictions) > 1
        and abs(float(wrap_angle(predictions[1].increment.theta - predictions[0].increment.theta)))
        > predictions[0].sigma_rotation
    )


def _either_sign(best: Fit | None, other: Fit | None) -> Fit | None:
    """The better of the best fit and the fit from the odometry's other sign, by score: two motion
    models in doubt, weighed by the walls alike (:data:`~fleetmap.agents.prediction.SIGN_DOUBT`).
    Two fits within registration's reach of each other are one minimum, found first by the best
    (:func:`~fleetmap.agents.fitcheck.same_start`; aces with jittered stamps: 4 of 10 such pairs
    scored a hair apart, and taking the other moved the log's short relations within 0.10 m, 2
    degrees from 96.5 to 96.1 %, record 043)."""
    if other is None or not other.good:
        return best
    if best is None:
        return other
    if other.registration.score > best.registration.score and not same_start(
        other.registration.pose, best.registration.pose
    ):
        return other
    return best


def _explained(fit: Fit, prediction: Prediction, origin: Transform2D, last: Transform2D) -> Fit:
    """The fit from where the robot stood, on a submap whose frame is ``origin``, refused and
    counted as a dispute of the prediction where the odometry measured the step from the robot's
    ``last`` pose and does not explain it (:func:`~fleetmap.agents.prediction.explains`)."""
    if not fit.good or prediction.source != "odometry":
        return fit
    if explains(prediction, last, origin.compose(fit.registration.pose)):
        return fit
    return replace(fit, good=False, why="a fit beyond the odometry's 99 % gate", disputed=True)
