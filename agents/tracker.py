"""A robot's front end: its scans tracked into small, overlapping submaps (``docs/design.md``).

For each scan (:meth:`Tracker.add`):

1. **Predict** its pose from the previous one: the odometry's increment when the robot has
   odometry, else constant velocity (:mod:`fleetmap.shared.core.motion`), with that model's
   uncertainty (:mod:`fleetmap.agents.prediction`, which also judges the odometry's sign).
2. **Register** it on the matching submap by robust point-to-line ICP, the prediction as prior
   (:func:`fleetmap.shared.core.tracking.register`; the search for a fit, steps 2-4, is
   :mod:`fleetmap.agents.fitting`).
   A prediction that measures nothing and is wider than registration's reach (constant
   velocity a second or more between scans) has its window searched too (:meth:`Tracker._searched`,
   :func:`fleetmap.agents.fitcheck.window_fit`; docs/decisions/017-a-prior-that-measures-nothing-is-searched.md),
   its minima weighed by the prediction (docs/decisions/023-the-window-weighed-by-its-prior.md).
   Before that, such a scan is integrated pose-free on the last scan the walls placed, as the pivot method
   places each scan (paper IV-C), and registered from there: that step, where its fit is good and
   typical, is the scan's, and where good but not typical, the first of the fits the motion
   models must outscore (:meth:`Tracker._stepped`, :mod:`fleetmap.agents.pose_free`;
   docs/decisions/045-the-step-a-sparse-log-measures-itself.md, docs/decisions/060), turned
   starts too. A pair valid but for a rival nearly as good seeds the window search with its best
   (docs/decisions/069). So is a
   scan whose odometry was spread within a burst (a guess of the robot's pace), registered from the pair's step with the
   spread reading as its prior (docs/decisions/052-a-spread-reading-is-a-prior-not-a-start.md),
   and one that got its burst's own reading by a guess of which scan it was read for
   (docs/decisions/054-a-bursts-own-reading-is-as-sure-as-its-owner.md).
3. **Check the fit** (:mod:`fleetmap.agents.fitcheck`): enough of the scan's walls on the
   submap's (``MIN_MATCHED_SHARE``, ``MIN_MATCHED_LENGTH``) and the scan's beams through little
   of the submap's walls (``MAX_SEE_THROUGH``: a laser does not see through walls). The clock
   bounds no registration (docs/decisions/009-clocks-evidence-over-stamps.md). A fit beyond the
   odometry's 99 % gate stands only where the scan's returns bear it out against the wheels'
   step (:meth:`Tracker._borne_out`; docs/decisions/088): a row of posts fits a post along.
4. A failed fit is tried again from starts turned across the prediction's heading uncertainty
   (:meth:`Tracker._turned_fits`; where only those fit, the best where the robot can have driven,
   :meth:`Tracker._reachable_fit`), then **re-acquired** with the paper's pose-free integration of
   the scan on the submap (Algorithms 1-4), within the reach of the robot (``max_speed``,
   :meth:`~fleetmap.agents.prediction.Predictor.reachable`; timed by the scans' sequence too where
   stamps still trusted give less time: docs/decisions/068), then registered and checked again.
   Where the odometry measured the step, the fit from where the robot stood must lie within the
   odometry's 99 % gate (:func:`fleetmap.agents.fitting._explained`): the wheels measure standing still too.
5. A scan that fits is placed; it is **inserted** into the active submaps when the robot has
   moved ``INSERT_DISTANCE`` or turned ``INSERT_ROTATION`` since the last inserted one (or
   ``INSERT_INTERVAL`` has passed) (:mod:`fleetmap.agents.submap`). The motion between placed
   scans also judges the stamps (:mod:`fleetmap.agents.clock_evidence`).
6. A scan that neither fits nor re-acquires is weighed as evidence (a kidnap is a conclusion,
   not a count of poor fits; docs/decisions/009-clocks-evidence-over-stamps.md;
   :func:`fleetmap.agents.fitcheck.contradicts`). Where the walls say nothing against its
   prediction (open space, a few metres of wall, new walls) the robot is **carried** by its
   motion model: the scan is placed at the prediction, and the prediction's uncertainty grows
   until the walls place a scan again, whose fit then places the carried scans again, the miss
   spread over their steps (:mod:`fleetmap.agents.carried`; docs/decisions/090); where the
   odometry predicted the step, the scan's returns measure it against the scan before's
   (:mod:`fleetmap.agents.returns`, :mod:`fleetmap.shared.core.pointstep`; docs/decisions/083):
   posts and hedges measure a turn in place that the walls cannot and the wheels over-read.
   Where the walls contradict the prediction (beams through the submap's walls, walls in its seen
   free space) the scan is left unplaced; after
   ``kidnap_after`` such scans with no placed one between, each contradicted from every start
   tried or fitting only beyond the motion model's 99 % gate, the robot has lost its place: a new
   **epoch** begins at the first of them, whose place nobody knows until the merger finds it, and
   the others are tracked into it. A scan with less wall than any fit must match
   (``MIN_MATCHED_LENGTH``: a few posts in open ground) is no such evidence: the robot moves on by
   its motion model, as over an empty scan (docs/decisions/061). A kidnap concluded on stamps the
   motion has not yet refuted is a conclusion about the clock too: the first held scan is tracked
   again with its time by the scans' sequence, and where it is placed then, the stamps were wrong,
   not the robot's place (:meth:`Tracker._untimed`).

**Submaps** (Cartographer's scheme, :mod:`fleetmap.agents.submap`): two are active at a time, and
every inserted scan goes into both; a scan is registered on, and placed by, the older one.
Consecutive submaps overlap by half, each chained to the previous one by its *link*, and a
finished submap never changes. What a submap publishes is its walls less those its own scans saw
through more than they saw (people, doors, carts); registration keeps every wall.

The tracker is pure: scans and odometry in, poses and submaps out; no clock, no I/O.
"""

from __future__ import annotations

import copy
import logging
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
from fleetmap.agents.carried import CarriedRun
from fleetmap.agents.clock_evidence import check_motion, check_order, say_distrusted
from fleetmap.agents.fitcheck import KIDNAP_REASON, MIN_MATCHED_LENGTH, Fit
from fleetmap.agents.fitting import FitSearch, ScanIn
from fleetmap.agents.pose_free import LOOSE_ROTATION, LOOSE_TRANSLATION
from fleetmap.agents.prediction import Predictor, within_gate
from fleetmap.agents.returns import PairReturns
from fleetmap.agents.submap import PlacedScan, Submap, SubmapChain, rotated
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.motion import Prediction
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.tracking import SAMPLE_SPACING, Registration, sample_segments

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
class _Held:
    """A scan that did not fit, kept until the robot finds its place again or starts an epoch."""

    taken: ScanIn
    counts: bool
    """It counts towards a kidnap: the walls dispute every start tried, or it fits beyond the
    motion model's gate (:meth:`Tracker._track`)."""


@dataclass(frozen=True)
class _Before:
    """What the tracker was before a scan: its pose, the last scan's stamp and number, its motion
    models and whether the last reading was spread (:meth:`Tracker._untimed`)."""

    pose: Transform2D | None
    stamp: float | None
    seq: int
    motion: Predictor
    spread: bool


class Tracker(FitSearch, PairReturns):
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
        self._previous: tuple[Array, tuple[float, Transform2D, int]] | None = None
        """The segments, and the stamp, epoch-frame pose and sequence number, of the last scan the
        walls placed (:meth:`_stepped`; not a carried one)."""
        self._step: Prediction | None = None
        """The step the scan pair measured, where the walls said nothing against it (:meth:`_stepped`)."""
        self._paired: Transform2D | None = None
        self._held: list[_Held] = []
        self._unheld: _Before | None = None
        """The tracker as it was before the first held scan (:meth:`_untimed`)."""
        self.exact = True
        """Whether the next scan's reading is where it was taken (:mod:`fleetmap.agents.bursts`)."""
        self.by_pace = False
        """Whether that reading is the robot's pace's guess: spread within a burst, or the burst's
        own given to the scan by the pace (which of its scans it was read for,
        :meth:`~fleetmap.agents.bursts.BurstOdometry._owner`; record 054)."""
        self._anchor: tuple[Transform2D, Transform2D] | None = None
        """The epoch pose and reading of the last placed scan whose reading was exact."""
        self._spread = False
        """Whether the last scan's reading was spread within a burst."""
        self._scores: deque[float] = deque(maxlen=RECENT_FITS)
        """The scores of the robot's recent good fits (:meth:`_fit`)."""
        self._scan: tuple[int, RangeScan] | None = None
        """The sequence number and scan of the last scan tracked (:meth:`_by_points`) ..."""
        self._scan_before: tuple[int, RangeScan] | None = None
        """... and of the scan before it."""
        self.run = CarriedRun()
        """The scans carried since the last scan the walls placed (:mod:`fleetmap.agents.carried`)."""

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
        steps = self._track(self.clock.scans, index, stamp, scan, segments, odometry)
        self.run.expire(self.chain.active[0].number - 1 if self.chain.active else 0)
        return steps

    # -- internals ---------------------------------------------------------------------------
    def _track(
        self, seq: int, index: int, stamp: float, scan: RangeScan, segments: Array, odometry: Transform2D | None
    ) -> list[TrackStep]:
        self._scan_before, self._scan = self._scan, (seq, scan)
        samples = sample_segments(segments, SAMPLE_SPACING)
        if len(samples) == 0:
            self._advance_blind(index, seq, stamp, odometry)
            return [TrackStep("empty", max(self.epoch, self.first_epoch), None, None)]
        taken = ScanIn(seq, index, stamp, scan, segments, samples, odometry)
        if self.epoch < 0:
            return [self._start_epoch(taken, new=False)]
        if not self._held and self.clock.trusted:  # (only a trusted clock's kidnap is tried again)
            self._unheld = _Before(self._pose, self._stamp, self._seq, copy.copy(self.motion), self._spread)
        spread, self._spread = self._spread, not self.exact
        if spread and self.exact and odometry is not None and self._anchor is not None and self._pose is not None:
            # a reading where the scan was taken, after readings spread within a burst: the
            # increment from the last such scan, as placed, not from the spread one before it
            # (a turn in place is not even: a spread heading can be 50 degrees off)
            at, reading = self._anchor
            self.motion.odometry = reading.compose(at.inverse()).compose(self._pose)
        self.motion.exact = self.exact
        self.motion.by_pace = self.by_pace
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
        fit = self._without_reading(taken, fit, predictions)
        fit = self._borne_out(taken, fit, predictions[0])
        if fit.good:
            self._held.clear()
            status = "tracked" if fit.why == "" else fit.why
            before, anchor = self._pose, self._anchor
            expected = self._pose_in_epoch(predictions[0])  # (where the carried chain, if any, put it)
            fitted = self.chain.active[0].origin.compose(fit.registration.pose)
            step = self._place(taken, fit, status)
            self.run.close(fitted, expected, predictions[0])
            self.motion.judge_placed(before, self._pose, anchor, spread, odometry)
            return [step]
        if not fit.contradicted and odometry_predicts:
            return [self._carried(taken, fit, predictions[0])]
        if self._step is not None:  # measured by the scan pair, as the odometry would have
            self.motion.step_variance = (LOOSE_TRANSLATION**2, LOOSE_ROTATION**2)
            return [self._carried(taken, fit, self._step)]
        if taken.samples.length < MIN_MATCHED_LENGTH:
            # less wall than any fit must match: no start could have placed it, so its not fitting
            # is no evidence of a kidnap (docs/decisions/061)
            self._advance_blind(index, seq, stamp, odometry)
            return [TrackStep("unplaced", self.epoch, None, None, registration=fit.registration)]
        self._pose = self._pose_in_epoch(predictions[0])
        self._stamp, self._seq = stamp, seq
        self.motion.odometry = odometry  # a scan without odometry breaks its chain (:meth:`_place`)
        self.motion.carry()
        counts = fit.everywhere or not fit.contradicted  # (not carried: no odometry)
        self._held.append(_Held(taken, counts))
        self.run.drop()  # (the walls broke the carried chain)
        if sum(h.counts for h in self._held) < self.params.kidnap_after:
            log.debug("scan %d did not fit (%s)", index, fit.why)
            return [TrackStep("unplaced", self.epoch, None, None, registration=fit.registration)]
        return self._lost()

    def _carried(self, taken: ScanIn, fit: Fit, prediction: Prediction) -> TrackStep:
        """No evidence either way (open space, a few metres of wall, a person in front of the
        laser): the walls neither place the scan nor say it was taken elsewhere. The robot is where
        its odometry takes it (a fit the walls refused may have slid). Constant velocity does not
        carry it: it measures nothing, and over a second between scans (a sparse log) it is a guess
        1.5 m wide; such a scan is held as a contradicted one is."""
        log.debug("scan %d carried by its motion model (%s)", taken.index, fit.why)
        prediction = self._by_points(taken.seq, prediction)
        submap, at = self.chain.active[0], self._pose_in_epoch(prediction)
        predicted = submap.origin.inverse().compose(at)
        good, walled = self._good, self._previous
        anchor = good[1] if good is not None and walled is not None and walled[1][2] == good[2] else None
        self.run.carry(taken.index, at, prediction, submap, anchor)
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

    def _advance_blind(self, index: int, seq: int, stamp: float, odometry: Transform2D | None) -> None:
        """A scan with nothing to track: the pose moves by odometry (or velocity) alone, or by the
        step its returns measure (:meth:`_by_points`)."""
        if self._pose is not None and self._stamp is not None:
            predicted = self.motion.predictions(seq, stamp, odometry, self._stamp, self._seq)[0]
            predicted = self._by_points(seq, predicted)
            self._pose = self._pose_in_epoch(predicted)
            self.run.blind(index, self._pose, predicted)
            self._stamp, self._seq = stamp, seq
            self.motion.odometry = odometry
            self.motion.carry()
            if not self._held:
                self.motion.track_drift = self.motion.drift

    def _place(self, taken: ScanIn, fit: Fit, status: str) -> TrackStep:
        """Place the scan by its fit on the matching submap; insert it when due."""
        seq, index, stamp, odometry = taken.seq, taken.index, taken.stamp, taken.odometry
        submap = self.chain.active[0]
        reg = fit.registration
        pose = submap.origin.compose(reg.pose)
        own = self._own_reading(pose, odometry)
        if self.exact and odometry is not None and not own:
            self._spread = True  # the next scan is measured from the last reading that was its own
        if self._good is not None:
            seconds = stamp - self._good[0]
            check_motion(
                self.clock,
                index,
                seconds,
                self._good[1],
                pose,
                reg.scan_information,
                submap.origin.theta,
                seq - self._good[2],
                seq,
            )
            self.motion.moved(self._good, pose, seq, stamp, reg.information)
        self._pose, self._stamp, self._seq, self._good = pose, stamp, seq, (stamp, pose, seq)
        if status != "carried":  # (a carried scan's pose is the motion model's guess, its view poor)
            self._previous = (taken.segments, (stamp, pose, seq))
        self.motion.drift = self.motion.track_drift = (0.0, 0.0)
        # a scan without odometry breaks its chain: the next increment is measured from the next
        # reading, never across a stretch that no reading saw (a corrected log's scans with no
        # wheel reading between them, :func:`~fleetmap.shared.io.logs.read_carmen_odometry`)
        self.motion.odometry = odometry
        self._anchor = (pose, odometry) if own and odometry is not None else self._anchor
        submap.placed.append(PlacedScan(index, stamp, reg.pose))
        if fit.spread is not None:
            self.chain.widen(rotated(fit.spread, submap.origin.theta))
        if self.chain.due(stamp, pose):
            self.chain.insert(self.epoch, index, stamp, taken.scan, taken.segments, taken.samples, pose, reg)
        return TrackStep(status, self.epoch, submap.number, reg.pose, registration=reg)

    def _without_reading(self, taken: ScanIn, fit: Fit, predictions: list[Prediction]) -> Fit:
        """``fit``, or the scan registered again without its reading where that reading was the
        burst's own, given to the scan by the robot's pace, and the walls placed the scan nearer
        the scan before than where the reading says (:meth:`_own_reading`): the reading was the
        scan before's (or after's), a step off, and registration started from it and was pulled
        towards it by its prior. The other motion models (constant velocity, the robot standing
        still, the scan pair's step where constant velocity measures nothing) place the scan then,
        where one of them fits (docs/decisions/058)."""
        odometry = taken.odometry
        if not (fit.good and self.by_pace and self.exact and odometry is not None):
            return fit
        if self._own_reading(self.chain.active[0].origin.compose(fit.registration.pose), odometry):
            return fit
        others = [p for p in predictions if "odometry" not in p.source]
        if not others:
            return fit
        scores, step = copy.copy(self._scores), self._step
        self._scores.pop()  # (the first fit's, which this one replaces)
        again = self._fit(taken, others)
        if again.good:
            return again
        self._scores, self._step = scores, step
        return fit

    def _own_reading(self, pose: Transform2D, odometry: Transform2D | None) -> bool:
        """Whether the scan about to be placed at ``pose`` (epoch frame) carries a reading known to
        be its own, to measure the next readings from (:attr:`_anchor`). A reading spread within a
        burst is not. A burst's own reading that the robot's pace gave to this scan
        (:attr:`by_pace`) is, unless the walls placed the scan before it nearer where the reading
        says (under the odometry's covariance): a driver that repeated a stamp read it for the scan
        before, and given to the wrong scan it is a step off; measured from, it put the next scan
        a step off too, at a clock whose readings were otherwise right (docs/decisions/057). Then
        the next scan is measured from the last reading that was its scan's own, as after spread
        ones."""
        if not self.exact or odometry is None:
            return False
        if not self.by_pace:
            return True
        step, before = self.motion.odometry_step, self._pose
        if step is None or before is None:
            return True
        step = self.motion.believed(step)
        said = before.compose(step.increment)
        return step.distance2(said, pose) <= step.distance2(said, before)

    def _start_epoch(self, taken: ScanIn, new: bool) -> TrackStep:
        """Begin an epoch whose frame is this scan's pose."""
        seq, index, stamp = taken.seq, taken.index, taken.stamp
        self.epoch = max(self.epoch + 1, self.first_epoch)
        self._pose, self._stamp, self._seq, self._good = Transform2D(), stamp, seq, (stamp, Transform2D(), seq)
        self._previous = (taken.segments, (stamp, Transform2D(), seq))
        self._scan = (seq, taken.scan)  # (held scans tracked into the epoch measure from it)
        self.motion.restart(taken.odometry)
        self._anchor = (Transform2D(), taken.odometry) if self.exact and taken.odometry is not None else None
        self._held = []
        self.run.drop()
        self._scores.clear()
        self.chain.restart(self.epoch, index, stamp, taken.scan, taken.segments, taken.samples)
        return TrackStep("first", self.epoch, 0, Transform2D(), new_epoch=new, first_scan=index)

    def _lost(self) -> list[TrackStep]:
        """``kidnap_after`` scans the walls contradict, with none placed between: a new epoch from the first of them."""
        held, self._held = self._held, []
        if self.clock.trusted and (steps := self._untimed(held)):
            return steps
        first = held[0].taken
        log.info("epoch %d from scan %d (%s)", self.epoch + 1, first.index, KIDNAP_REASON.format(n=len(held)))
        steps = [self._start_epoch(first, new=True)]
        for h in held[1:]:
            t = h.taken
            steps += self._track(t.seq, t.index, t.stamp, t.scan, t.segments, t.odometry)
        return steps

    def _untimed(self, held: list[_Held]) -> list[TrackStep]:
        """A kidnap concluded on the stamps' word is a conclusion about the clock too: the first
        held scan is tracked again from where the robot was before it, its time by the scans'
        sequence at the log's mean period (a logger that stamps bursts at receipt shrinks a second
        to milliseconds, and with it the robot's reach). Placed, the stamps were wrong, not the
        robot's place: said once, and the held scans tracked on. Else nothing changes ([])."""
        before = self._unheld
        if before is None:
            return []
        kept = _Before(self._pose, self._stamp, self._seq, self.motion, self._spread)
        self._pose, self._stamp, self._seq, self._spread = before.pose, before.stamp, before.seq, before.spread
        self.motion, self.clock.trusted = copy.copy(before.motion), False
        first = held[0].taken
        steps = self._track(first.seq, first.index, first.stamp, first.scan, first.segments, first.odometry)
        if steps[0].status == "unplaced":
            self._pose, self._stamp, self._seq, self.motion, self._spread = (
                kept.pose,
                kept.stamp,
                kept.seq,
                kept.motion,
                kept.spread,
            )
            self.clock.trusted, self._held = True, []
            return []
        self.clock.distrust()
        say_distrusted(
            self.clock, f"scans {first.index}-{held[-1].taken.index} fit only in the time their sequence takes"
        )
        for h in held[1:]:
            t = h.taken
            steps += self._track(t.seq, t.index, t.stamp, t.scan, t.segments, t.odometry)
        return steps
