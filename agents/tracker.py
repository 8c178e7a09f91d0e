"""A robot's front end: its scans tracked into small, overlapping submaps (``docs/design.md``).

For each scan (:meth:`Tracker.add`):

1. **Predict** its pose from the previous one: the odometry's increment when the robot has
   odometry, else constant velocity (:mod:`fleetmap.shared.core.motion`), with that model's
   uncertainty (:mod:`fleetmap.agents.prediction`, which also judges the odometry's sign).
2. **Register** it on the matching submap by robust point-to-line ICP, the prediction as prior
   (:func:`fleetmap.shared.core.tracking.register`).
   A prediction that measures nothing and is wider than registration's reach (constant
   velocity a second or more between scans) has its window searched too (:meth:`Tracker._searched`,
   :func:`fleetmap.agents.fitcheck.window_fit`; docs/decisions/017-a-prior-that-measures-nothing-is-searched.md),
   its minima weighed by the prediction (docs/decisions/023-the-window-weighed-by-its-prior.md).
   Before that, such a scan is integrated pose-free on the last placed scan, as the pivot method
   places each scan (paper IV-C), and registered from there: that step, where its fit is good and
   typical, is the scan's (:meth:`Tracker._stepped`, :mod:`fleetmap.agents.pose_free`;
   docs/decisions/045-the-step-a-sparse-log-measures-itself.md).
3. **Check the fit** (:mod:`fleetmap.agents.fitcheck`): enough of the scan's walls on the
   submap's (``MIN_MATCHED_SHARE``, ``MIN_MATCHED_LENGTH``) and the scan's beams through little
   of the submap's walls (``MAX_SEE_THROUGH``: a laser does not see through walls). The clock
   bounds no registration (docs/decisions/009-clocks-evidence-over-stamps.md).
4. A failed fit is tried again from starts turned across the prediction's heading uncertainty
   (:meth:`Tracker._turned_fits`; where only those fit, the best where the robot can have driven,
   :meth:`Tracker._reachable_fit`), then **re-acquired** with the paper's pose-free integration of
   the scan on the submap (Algorithms 1-4), within the reach of the robot (``max_speed``,
   :meth:`~fleetmap.agents.prediction.Predictor.reachable`), then registered and checked again.
   Where the odometry measured the step, the fit from where the robot stood must lie within the
   odometry's 99 % gate (:func:`_explained`): the wheels measure standing still too.
5. A scan that fits is placed; it is **inserted** into the active submaps when the robot has
   moved ``INSERT_DISTANCE`` or turned ``INSERT_ROTATION`` since the last inserted one (or
   ``INSERT_INTERVAL`` has passed) (:mod:`fleetmap.agents.submap`). The motion between placed
   scans also judges the stamps (:mod:`fleetmap.agents.clock_evidence`).
6. A scan that neither fits nor re-acquires is weighed as evidence (a kidnap is a conclusion,
   not a count of poor fits; docs/decisions/009-clocks-evidence-over-stamps.md;
   :func:`fleetmap.agents.fitcheck.contradicts`). Where the walls say nothing against its
   prediction (open space, a few metres of wall, new walls) the robot is **carried** by its
   motion model: the scan is placed at the prediction, and the prediction's uncertainty grows
   until the walls place a scan again. Where they contradict the prediction (beams through the
   submap's walls, walls in its seen free space) the scan is left unplaced; after
   ``kidnap_after`` such scans with no placed one between, each contradicted from every start
   tried or fitting only beyond the motion model's 99 % gate, the robot has lost its place: a new
   **epoch** begins at the first of them, whose place nobody knows until the merger finds it, and
   the others are tracked into it.

**Submaps** (Cartographer's scheme, :mod:`fleetmap.agents.submap`): two are active at a time, and
every inserted scan goes into both; a scan is registered on, and placed by, the older one.
Consecutive submaps overlap by half, each chained to the previous one by its *link*, and a
finished submap never changes. What a submap publishes is its walls less those its own scans saw
through more than they saw (people, doors, carts); registration keeps every wall.

The tracker is pure: scans and odometry in, poses and submaps out; no clock, no I/O.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from fleetmap.agents.clock_evidence import check_motion, check_order
from fleetmap.agents.fitcheck import (
    KIDNAP_REASON,
    TYPICAL_SCORE_SHARE,
    Fit,
    best_fit,
    judge,
    same_start,
    turned_fits,
    typical_floor,
    window_fit,
)
from fleetmap.agents.pose_free import LOOSE_ROTATION, LOOSE_TRANSLATION, loose, reacquired, stepped
from fleetmap.agents.prediction import OTHER_SIGN, Predictor, explains, within_gate
from fleetmap.agents.submap import PlacedScan, Submap, SubmapChain
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.motion import Prediction
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.tracking import (
    MAX_CORRESPONDENCE,
    SAMPLE_SPACING,
    Registration,
    ScanSamples,
    register,
    sample_segments,
)

__all__ = ["KIDNAP_REASON", "PlacedScan", "Submap", "TrackStep", "Tracker"]

log = logging.getLogger(__name__)

RECENT_FITS = 20
"""The robot's recent fits whose median a typical fit is measured against (``TYPICAL_SCORE_SHARE``):
a few seconds of scans, so a new room's walls soon set the norm."""


@dataclass(frozen=True)
class TrackStep:
    """What one scan did to the tracker."""

    status: str
    """"first" (an epoch's first scan), "tracked", "reacquired" (by pose-free integration),
    "unplaced" (the fit failed, and the walls contradict the prediction: held towards a kidnap),
    "carried" (the fit failed, but the walls say nothing against the prediction: placed there by
    the motion model), or "empty" (no segment: nothing to track)."""
    epoch: int
    """The epoch the scan is in."""
    submap: int | None
    """The submap that placed it (None: not placed)."""
    pose: Transform2D | None
    """Its laser pose in that submap's frame."""
    new_epoch: bool = False
    """This scan started an epoch after a lost one (a kidnap); the epoch's first scan is
    ``first_scan`` and its placed scans are in its submaps."""
    first_scan: int | None = None
    registration: Registration | None = None


@dataclass(frozen=True)
class _ScanIn:
    """A scan as the tracker takes it (:meth:`Tracker.add`), with its number in the robot's sequence
    of scans and its samples."""

    seq: int
    index: int
    stamp: float
    scan: RangeScan
    segments: Array
    samples: ScanSamples
    odometry: Transform2D | None


@dataclass(frozen=True)
class _Held:
    """A scan that did not fit, kept until the robot finds its place again or starts an epoch."""

    taken: _ScanIn
    counts: bool
    """It counts towards a kidnap: the walls dispute every start tried, or it fits beyond the
    motion model's gate (:meth:`Tracker._track`)."""


class Tracker:
    """One robot's tracking: :meth:`add` each scan in order."""

    def __init__(self, config: FleetmapConfig | None = None, odometry: bool = True) -> None:
        self.config = config or FleetmapConfig()
        self.params = self.config.tracking
        self.epoch = -1
        """The current epoch (-1 before the first scan with segments)."""
        self.first_epoch = 0
        """The number of the first epoch (a robot restarted under its id goes on after its earlier run's)."""
        self.chain = SubmapChain(self.config)
        """The epoch's submaps (:mod:`fleetmap.agents.submap`)."""
        self.motion = Predictor(self.config, odometry)
        """The motion models (:mod:`fleetmap.agents.prediction`)."""
        self.clock = self.motion.clock
        """The time between scans as the evidence supports it (the stamps, or the scans' sequence)."""
        self._pose: Transform2D | None = None
        """The robot's pose in the epoch's frame after the last scan (predicted if unplaced)."""
        self._stamp: float | None = None
        self._seq = 0
        """The last scan's number in the robot's sequence of scans (from 1)."""
        self._good: tuple[float, Transform2D, int] | None = None
        """Stamp, epoch-frame pose and sequence number of the last placed scan."""
        self._previous: tuple[Array, Transform2D] | None = None
        """The segments and epoch-frame pose of the last placed scan (:meth:`_stepped`)."""
        self._step: Prediction | None = None  # the scan pair's step, where the walls said nothing against it
        self._held: list[_Held] = []
        self.exact = True
        """Whether the next scan's reading is where it was taken (:mod:`fleetmap.agents.bursts`)."""
        self._anchor: tuple[Transform2D, Transform2D] | None = None
        """The epoch pose and reading of the last placed scan whose reading was exact."""
        self._spread = False
        """Whether the last scan's reading was spread within a burst."""
        self._scores: deque[float] = deque(maxlen=RECENT_FITS)
        """The scores of the robot's recent good fits (:meth:`_fit`)."""

    # -- queries -----------------------------------------------------------------------------
    @property
    def matching(self) -> Submap | None:
        return self.chain.active[0] if self.chain.active else None

    @property
    def pose(self) -> Transform2D | None:
        """The robot's pose in the matching submap's frame after the last scan; None if lost."""
        if self._pose is None or self._held or not self.chain.active:
            return None
        return self.chain.active[0].origin.inverse().compose(self._pose)

    @property
    def epoch_pose(self) -> Transform2D | None:
        """The robot's pose in its epoch's frame after the last scan; None if that scan was not placed."""
        if self._pose is None or self._held:
            return None
        return self._pose

    def take_finished(self) -> list[Submap]:
        return self.chain.take_finished()

    def submaps(self) -> Iterator[Submap]:
        """The active submaps, oldest first."""
        return iter(self.chain.active)

    # -- the step ----------------------------------------------------------------------------
    def add(
        self, index: int, stamp: float, scan: RangeScan, segments: Array, odometry: Transform2D | None = None
    ) -> list[TrackStep]:
        """Track one scan; the steps it caused (more than one when it starts an epoch: then the
        scans held since the robot lost its place are tracked into it too, in order)."""
        previous = self.clock.previous
        self.clock.tick(stamp)
        check_order(self.clock, previous, index, stamp)
        return self._track(self.clock.scans, index, stamp, scan, segments, odometry)

    # -- internals ---------------------------------------------------------------------------
    def _track(
        self, seq: int, index: int, stamp: float, scan: RangeScan, segments: Array, odometry: Transform2D | None
    ) -> list[TrackStep]:
        samples = sample_segments(segments, SAMPLE_SPACING)
        if len(samples) == 0:
            self._advance_blind(seq, stamp, odometry)
            return [TrackStep("empty", max(self.epoch, self.first_epoch), None, None)]
        taken = _ScanIn(seq, index, stamp, scan, segments, samples, odometry)
        if self.epoch < 0:
            return [self._start_epoch(taken, new=False)]
        spread, self._spread = self._spread, not self.exact
        if spread and self.exact and odometry is not None and self._anchor is not None and self._pose is not None:
            # a reading where the scan was taken, after readings spread within a burst: the
            # increment from the last such scan, as placed, not from the spread one before it
            # (a turn in place is not even: a spread heading can be 50 degrees off)
            at, reading = self._anchor
            self.motion.odometry = reading.compose(at.inverse()).compose(self._pose)
        self.motion.exact = self.exact
        predictions = self.motion.predictions(seq, stamp, odometry, self._stamp, self._seq)
        fit = self._fit(taken, predictions)
        odometry_predicts = "odometry" in predictions[0].source
        if (
            fit.good
            and self._held
            and odometry_predicts
            and not within_gate(
                self.chain.active[0].origin.compose(fit.registration.pose),
                self._pose_in_epoch(predictions[0]),
                predictions[0],
            )
        ):
            # after the walls contradicted the prediction, a fit the odometry cannot explain is the
            # scan fitting elsewhere: more contrary evidence, not the robot found again (constant
            # velocity measures nothing: it neither carries the robot nor gates a fit)
            fit = replace(
                fit, good=False, why="a fit beyond the motion model's 99 % gate", contradicted=True, everywhere=True
            )
        if fit.good:
            self._held.clear()
            status = "tracked" if fit.why == "" else fit.why
            before, anchor = self._pose, self._anchor
            step = self._place(taken, fit, status)
            self.motion.judge_placed(before, self._pose, anchor, spread, odometry)
            return [step]
        if not fit.contradicted and odometry_predicts:
            return [self._carried(taken, fit, predictions[0])]
        if self._step is not None:  # measured by the scan pair, as the odometry would have
            self.motion.step_variance = (LOOSE_TRANSLATION**2, LOOSE_ROTATION**2)
            return [self._carried(taken, fit, self._step)]
        self._pose = self._pose_in_epoch(predictions[0])
        self._stamp, self._seq = stamp, seq
        self.motion.odometry = odometry  # a scan without odometry breaks its chain (:meth:`_place`)
        self.motion.carry()
        counts = fit.everywhere or not fit.contradicted  # (not carried: no odometry)
        self._held.append(_Held(taken, counts))
        if sum(h.counts for h in self._held) < self.params.kidnap_after:
            log.debug("scan %d did not fit (%s)", index, fit.why)
            return [TrackStep("unplaced", self.epoch, None, None, registration=fit.registration)]
        return self._lost()

    def _carried(self, taken: _ScanIn, fit: Fit, prediction: Prediction) -> TrackStep:
        """No evidence either way (open space, a few metres of wall, a person in front of the
        laser): the walls neither place the scan nor say it was taken elsewhere. The robot is where
        its odometry takes it (a fit the walls refused may have slid). Constant velocity does not
        carry it: it measures nothing, and over a second between scans (a sparse log) it is a guess
        1.5 m wide; such a scan is held as a contradicted one is."""
        log.debug("scan %d carried by its motion model (%s)", taken.index, fit.why)
        predicted = self.chain.active[0].origin.inverse().compose(self._pose_in_epoch(prediction))
        # placed as the prediction, as sure as its motion model (the walls fixed nothing)
        prior = replace(
            fit.registration,
            pose=predicted,
            information=prediction.information(),
            scan_information=np.zeros((3, 3)),
        )
        carried = replace(fit, registration=prior)
        self._held.clear()  # a kidnap is scans contradicted in a row
        drift = self.motion.drift
        step = self._place(taken, carried, "carried")
        self.motion.drift = drift
        self.motion.carry()  # the walls did not check this step: its uncertainty adds to the next ones'
        self.motion.track_drift = self.motion.drift
        return step

    def _pose_in_epoch(self, prediction: Prediction) -> Transform2D:
        base = self._pose if self._pose is not None else Transform2D()
        return base.compose(prediction.increment)

    def _advance_blind(self, seq: int, stamp: float, odometry: Transform2D | None) -> None:
        """A scan with nothing to track: the pose moves by odometry (or velocity) alone."""
        if self._pose is not None and self._stamp is not None:
            self._pose = self._pose_in_epoch(self.motion.predictions(seq, stamp, odometry, self._stamp, self._seq)[0])
            self._stamp, self._seq = stamp, seq
            self.motion.odometry = odometry
            self.motion.carry()
            if not self._held:
                self.motion.track_drift = self.motion.drift

    def _fit(self, taken: _ScanIn, predictions: list[Prediction]) -> Fit:
        """The scan's fit on the matching submap.

        The first prediction's fit is taken when it is good and typical: its score at least
        ``TYPICAL_SCORE_SHARE`` of the median of the robot's recent fits (a fit that suddenly
        supports a third of what the last ones did has likely slid into a wrong minimum). Otherwise
        the other predictions and the robot standing still are tried too, and the pose-free
        integration (:meth:`_reacquire`) if none is typical; a later fit replaces an earlier good one
        only if it scores over ``1 / TYPICAL_SCORE_SHARE`` times as much (along a corridor the fits
        score alike, and the first prediction's stands: :func:`~fleetmap.agents.fitcheck.best_fit`),
        unless the walls refused it: the models left, as unsure as each other, weigh by score.
        The odometry's other sign, in doubt, is always tried, and weighed by score alone
        (:func:`_either_sign`). Failing all, the first fit, not good."""
        measured = self._stepped(taken, predictions[0])
        if measured is not None:
            self._scores.append(measured.registration.score)
            return measured
        submap = self.chain.active[0]
        share = TYPICAL_SCORE_SHARE
        floor = typical_floor(self._scores)
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
        if best is None or best.registration.score < floor:
            # only a typical fit from a turned start: an atypical one is no better than the
            # prediction's own, which the pose-free integration below may still replace
            turned = self._turned_fits(taken, predictions[0], floor, tried)
            fits += turned
            if turned and turned[-1].good and turned[-1].registration.score >= floor:
                best = turned[-1]
            elif best is None:
                best = self._reachable_fit(taken, turned)
        if best is None or best.registration.score < floor:
            # a scan re-acquired by pose-free integration must fit as well as the robot's scans
            # usually do: one that explains a fraction of what they did matched a look-alike (a
            # carried robot's view of one corridor on another)
            again = self._reacquire(taken, submap, predictions[0])
            if (
                again is not None
                and again.registration.score >= floor
                and (best is None or again.registration.score * share >= best.registration.score)
            ):
                best = again
        if best is not None:
            best = self._searched(taken, predictions[0], best)
            self._scores.append(best.registration.score)
            return best
        return replace(fits[0], everywhere=all(f.disputed for f in fits))

    def _searched(self, taken: _ScanIn, prediction: Prediction, best: Fit) -> Fit:
        """``best``, or a better fit from the prediction's window (:func:`window_fit`) where the
        prediction is constant velocity and its two sigma, no farther than the robot drives in one
        scan step, is wider than registration's reach. The odometry's prediction is never searched,
        however wide: its prior is evidence along a corridor that the walls' support is not (a
        burst's spread readings, searched, placed aces-corrected's robot up to 6 m backwards)."""
        radius = self._radius(taken, prediction)
        if not best.good or radius <= MAX_CORRESPONDENCE or "odometry" in prediction.source:
            return best
        submap = self.chain.active[0]
        mean = submap.origin.inverse().compose(self._pose_in_epoch(prediction))
        return window_fit(
            best,
            submap,
            taken.samples,
            mean,
            radius,
            prediction,
            lambda start: self._registered(taken, submap, start, mean, prediction),
        )

    def _radius(self, taken: _ScanIn, prediction: Prediction) -> float:
        """How far from the prediction the scan may be: two sigma, within the robot's reach."""
        last = (self._stamp if self._stamp is not None else taken.stamp, self._pose or Transform2D(), self._seq)
        return min(2.0 * prediction.sigma_translation, self.motion.reach(last, taken.seq, taken.stamp))

    def _stepped(self, taken: _ScanIn, prediction: Prediction) -> Fit | None:
        """Where the motion model measures nothing (no odometry; constant velocity wider than
        registration's reach), the step measured by the scan's pose-free integration on the last
        placed scan (:func:`~fleetmap.agents.pose_free.stepped`), registered from there on the
        submap: its fit when good and typical, else None (the motion models are tried then)."""
        self._step = None
        if (
            self._previous is None
            or "odometry" in prediction.source
            or self._radius(taken, prediction) <= MAX_CORRESPONDENCE
        ):
            return None
        reach = self.motion.reach(self._good, taken.seq, taken.stamp)
        step = stepped(self._previous[0], taken.segments, reach, self.config.integration)
        if step is None:
            return None
        placed = self._previous[1].compose(step)
        increment = (self._pose or Transform2D()).inverse().compose(placed)
        measured = Prediction(increment, LOOSE_TRANSLATION, LOOSE_ROTATION, "integration")
        start = self.chain.active[0].origin.inverse().compose(placed)
        fit = self._registered(taken, self.chain.active[0], start, start, measured)
        if fit.good and fit.registration.score >= typical_floor(self._scores):
            return fit
        self._step = None if fit.contradicted else measured  # (the walls say nothing against it)
        return None

    def _turned_fits(self, taken: _ScanIn, prediction: Prediction, floor: float, tried: list[Transform2D]) -> list[Fit]:
        """Fits from starts turned across the prediction's heading uncertainty (:func:`turned_fits`)."""
        submap = self.chain.active[0]
        mean = submap.origin.inverse().compose(self._pose_in_epoch(prediction))
        registered = partial(self._registered, taken, submap, mean=mean, prediction=prediction)
        return turned_fits(mean, prediction.sigma_rotation, floor, tried, registered)

    def _reachable_fit(self, taken: _ScanIn, fits: list[Fit]) -> Fit | None:
        """No start of the motion models placed the scan: the best good fit from a turned start
        (:func:`best_fit`) where the robot can have driven, as a re-acquired one must be, however
        little of the scan the submap holds yet (a turn into new space: acapulco-corrected without
        odometry, scan 77, a fit at half the robot's typical score, 0.04 m from the truth). One
        that slid beyond that lies where no start searched (scan 161: 5.7 m along a corridor)."""
        origin, last, seq, stamp = self.chain.active[0].origin, self._good, taken.seq, taken.stamp
        reachable = [f for f in fits if self.motion.reachable(last, origin.compose(f.registration.pose), seq, stamp)]
        best = best_fit(reachable, False)
        if best is not None:
            log.debug("scan %d fits from a turned start alone (score %.2f)", taken.index, best.registration.score)
        return best

    def _registered(
        self, taken: _ScanIn, submap: Submap, start: Transform2D, mean: Transform2D, prediction: Prediction
    ) -> Fit:
        """The scan registered on ``submap`` from ``start``, pulled towards the prediction's
        ``mean`` with its information, and checked (:meth:`_judge`)."""
        reg = register(taken.samples, submap.reference, start, mean, prediction.information(), self.params)
        why, (contradicted, disputed) = self._judge(reg, taken, submap)
        return Fit(reg, why == "", why, contradicted, disputed)

    def _judge(self, reg: Registration, taken: _ScanIn, submap: Submap) -> tuple[str, tuple[bool, bool]]:
        """The fit check (:func:`~fleetmap.agents.fitcheck.judge`), its beam test excusing the
        uncertainty of the track the robot is carried on."""
        max_range = self.config.extraction.max_range
        return judge(reg, taken.scan, taken.segments, submap, max_range, self.motion.track_drift)

    def _reacquire(self, taken: _ScanIn, submap: Submap, prediction: Prediction) -> Fit | None:
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
        why, _ = self._judge(reg, taken, submap)
        placed = submap.origin.compose(reg.pose)
        if why != "" or not self.motion.reachable(self._good, placed, taken.seq, taken.stamp):
            return None
        measured = prediction.source == "odometry" and self.exact  # not a mistimed or spread reading
        if measured and not within_gate(placed, self._pose_in_epoch(prediction), prediction):
            return None
        return Fit(reg, True, "reacquired")

    def _place(self, taken: _ScanIn, fit: Fit, status: str) -> TrackStep:
        """Place the scan by its fit on the matching submap; insert it when due."""
        seq, index, stamp, odometry = taken.seq, taken.index, taken.stamp, taken.odometry
        submap = self.chain.active[0]
        reg = fit.registration
        pose = submap.origin.compose(reg.pose)
        if self._good is not None:
            seconds = stamp - self._good[0]
            check_motion(self.clock, index, seconds, self._good[1], pose, reg.scan_information, submap.origin.theta)
            self.motion.moved(self._good, pose, seq, stamp)
        self._pose, self._stamp, self._seq, self._good = pose, stamp, seq, (stamp, pose, seq)
        self._previous = (taken.segments, pose)
        self.motion.drift = self.motion.track_drift = (0.0, 0.0)
        # a scan without odometry breaks its chain: the next increment is measured from the next
        # reading, never across a stretch that no reading saw (a corrected log's scans with no
        # wheel reading between them, :func:`~fleetmap.shared.io.logs.read_carmen_odometry`)
        self.motion.odometry = odometry
        self._anchor = (pose, odometry) if self.exact and odometry is not None else self._anchor
        submap.placed.append(PlacedScan(index, stamp, reg.pose))
        if self.chain.due(stamp, pose):
            self.chain.insert(self.epoch, index, stamp, taken.scan, taken.segments, taken.samples, pose, reg)
        return TrackStep(status, self.epoch, submap.number, reg.pose, registration=reg)

    def _start_epoch(self, taken: _ScanIn, new: bool) -> TrackStep:
        """Begin an epoch whose frame is this scan's pose."""
        seq, index, stamp = taken.seq, taken.index, taken.stamp
        self.epoch = max(self.epoch + 1, self.first_epoch)
        self._pose, self._stamp, self._seq, self._good = Transform2D(), stamp, seq, (stamp, Transform2D(), seq)
        self._previous = (taken.segments, Transform2D())
        self.motion.restart(taken.odometry)
        self._anchor = (Transform2D(), taken.odometry) if self.exact and taken.odometry is not None else None
        self._held = []
        self._scores.clear()
        self.chain.restart(self.epoch, index, stamp, taken.scan, taken.segments, taken.samples)
        return TrackStep("first", self.epoch, 0, Transform2D(), new_epoch=new, first_scan=index)

    def _lost(self) -> list[TrackStep]:
        """``kidnap_after`` scans the walls contradict, with none placed between: a new epoch from the first of them."""
        held, self._held = self._held, []
        first = held[0].taken
        log.info("epoch %d from scan %d (%s)", self.epoch + 1, first.index, KIDNAP_REASON.format(n=len(held)))
        steps = [self._start_epoch(first, new=True)]
        for h in held[1:]:
            t = h.taken
            steps += self._track(t.seq, t.index, t.stamp, t.scan, t.segments, t.odometry)
        return steps


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
