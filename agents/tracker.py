"""A robot's front end: its scans tracked into small, overlapping submaps (``docs/design.md``).

For each scan (:meth:`Tracker.add`):

1. **Predict** its pose from the previous one: the odometry's increment when the robot has
   odometry, else constant velocity (:mod:`fleetmap.shared.core.motion`), with that model's
   uncertainty.
2. **Register** it on the matching submap by robust point-to-line ICP, the prediction as prior
   (:func:`fleetmap.shared.core.tracking.register`).
3. **Check the fit**: enough of the scan's walls on the submap's (``min_matched_share``,
   ``min_matched_length``), the scan's beams through little of the submap's walls
   (``max_see_through``: a laser does not see through walls), and a pose the robot can have
   driven to since its last good scan (``max_speed``).
4. A failed fit is **re-acquired** with the paper's pose-free integration of the scan on the
   submap (Algorithms 1-4), within the reach of the robot, then registered and checked again.
5. A scan that fits is placed; it is **inserted** into the active submaps when the robot has
   moved ``insert_distance`` or turned ``insert_rotation`` since the last inserted one (or
   ``insert_interval`` has passed).
6. A scan that neither fits nor re-acquires is weighed as evidence (a kidnap is a conclusion,
   not a count of poor fits; docs/decisions/009-clocks-evidence-over-stamps.md). Where the walls
   say nothing against its prediction (open space, a few metres of wall, new walls) the robot is
   **carried** by its motion model: the scan is placed at the prediction, and the prediction's
   uncertainty grows until the walls place a scan again. Where they contradict the prediction
   (beams through the submap's walls, walls in its seen free space) the scan is left unplaced;
   after ``kidnap_after`` such scans with no placed one between, each contradicted from every
   start tried or fitting only beyond the motion model's 99 % gate, the robot has lost its place:
   a new **epoch** begins at the first of them, whose place nobody knows until the merger finds
   it, and the others are tracked into it.

**Submaps** (Cartographer's scheme): two are active at a time, and every inserted scan goes into
both. A scan is registered on, and placed by, the older one, which holds more. A submap is
finished when it covers ``submap_length`` metres of the robot's path or ``submap_scans`` inserted
scans; the next one starts halfway through, at an inserted scan, whose pose is the new submap's
frame. So consecutive submaps overlap by half, and each is chained to the previous one by the
*link*: its frame in the previous submap's frame, with the uncertainty of the registration that
placed it. A finished submap never changes.

**What a submap publishes** is its walls less those its own scans saw through more than they saw
(:func:`fleetmap.shared.core.tracking.wall_evidence`, the see-through test of the fit's check on
each inserted scan's beams): a person walking past, a door swinging, a cart pushed by. Another
robot there minutes later sees through them too, and left in, they refute the right match of the
two robots' submaps (docs/decisions/002-pose-graph.md). Registration keeps every wall.

The tracker is pure: scans and odometry in, poses and submaps out; no clock, no I/O.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np
from fleetmap.shared.config import FleetmapConfig, TrackingParams
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.integration import Window, integrate
from fleetmap.shared.core.mapgrid import scan_viewpoint
from fleetmap.shared.core.motion import (
    CHI2_1DOF_99,
    CHI2_3DOF_99,
    Prediction,
    ScanClock,
    from_odometry,
    from_velocity,
    fused,
    odometry_increment,
    velocity_between,
)
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.tracking import (
    REACH_ROTATION,
    ReferenceMap,
    Registration,
    ScanSamples,
    beam_evidence,
    drift_covariance,
    register,
    sample_segments,
    see_through,
    wall_evidence,
)
from fleetmap.shared.core.walls import WallMap

log = logging.getLogger(__name__)


KIDNAP_REASON = (
    "{n} scans that the submap's walls contradict fit neither the submap nor, by pose-free "
    "integration, anywhere near it"
)
"""The reason of an epoch started by lost tracking (EpochLink.reason and the event's detail)."""


@dataclass(frozen=True)
class PlacedScan:
    """A scan as a submap places it."""

    index: int
    stamp: float
    pose: Transform2D
    """The laser's pose in the submap's frame."""


@dataclass
class Submap:
    """One submap of an epoch (see the module docstring): what the agent publishes of it and the
    reference the tracker registers on."""

    epoch: int
    number: int
    frame_scan: int
    """The index of the scan whose pose is its frame (its first inserted scan)."""
    origin: Transform2D
    """Its frame (the pose of its first scan) in the epoch's frame."""
    link_transform: Transform2D | None
    """Its frame in the previous submap's frame (None for an epoch's first submap)."""
    link_covariance: Array | None
    reference: ReferenceMap
    walls: WallMap
    params: TrackingParams
    """The tracking's see-through test, which judges the walls (:meth:`segment_map`)."""
    max_range: float
    """How far the robot's extraction reads a beam (m)."""
    viewpoints_in: list[Array] = field(default_factory=list)
    """The inserted scans' viewpoints ``[x, y, theta, bearing_min, bearing_max]``."""
    scans_in: list[tuple[RangeScan, Transform2D]] = field(default_factory=list)
    """The inserted scans and their poses (what they saw of its walls: :meth:`segment_map`)."""
    placed: list[PlacedScan] = field(default_factory=list)
    """The scans this submap placed (registered on it while it was the matching submap)."""
    path_length: float = 0.0
    inserted: int = 0
    finished: bool = False
    _last_insert: Transform2D | None = None
    _built: tuple[int, SegmentMap] | None = None

    def insert(self, scan: RangeScan, samples: ScanSamples, segments: Array, pose: Transform2D) -> None:
        """Add a scan taken at ``pose`` (this submap's frame): its beams (which judge the walls),
        and its samples and segments in its own frame."""
        self.reference.insert(samples.moved(pose))
        self.scans_in.append((scan, pose))
        self.walls.add(pose.apply(segments))
        viewpoint = scan_viewpoint(segments)
        if len(viewpoint):
            viewpoint[0, 0:3] = pose.x, pose.y, pose.theta
            self.viewpoints_in.append(viewpoint[0])
        if self._last_insert is not None:
            self.path_length += math.hypot(pose.x - self._last_insert.x, pose.y - self._last_insert.y)
        self._last_insert = pose
        self.inserted += 1

    def segment_map(self) -> SegmentMap:
        """Its walls, one segment per stretch of wall (:class:`fleetmap.shared.core.walls.WallMap`),
        less those its own scans saw through more than they saw (:func:`wall_evidence`): people,
        doors and carts that moved while the robot looked. Another robot's laser, there minutes
        later, sees through them as well; left in, they would refute the right match of the two
        robots' submaps (docs/decisions/002-pose-graph.md)."""
        if self._built is None or self._built[0] != self.inserted:
            walls = self.walls.segments
            seen, through = wall_evidence(walls, self.scans_in, self.params, self.max_range)
            walls = walls[through <= seen]
            self._built = (self.inserted, SegmentMap(walls, ordered=False, oriented=True))
        if self.finished:
            self.scans_in = []  # a finished submap never changes: its walls are judged for good
        return self._built[1]

    def viewpoints(self) -> Array:
        return np.array(self.viewpoints_in) if self.viewpoints_in else np.zeros((0, 5))


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


@dataclass
class _Held:
    """A scan that did not fit, kept until the robot finds its place again or starts an epoch."""

    seq: int
    index: int
    stamp: float
    scan: RangeScan
    segments: Array
    samples: ScanSamples
    odometry: Transform2D | None
    counts: bool
    """It counts towards a kidnap: the walls dispute every start tried, or it fits beyond the
    motion model's gate (:meth:`Tracker._track`)."""


@dataclass(frozen=True)
class _Fit:
    registration: Registration
    good: bool
    why: str
    contradicted: bool = False
    """The scan and the submap disagree on space both saw at this fit's pose (:meth:`_judge`): the
    walls say the scan was not taken there. A fit refused only for the little wall it matched says
    nothing of where the scan was taken."""
    disputed: bool = False
    """The scan and the submap disagree at this pose on at least as much wall as it takes to place a
    scan, whatever they agree on."""
    everywhere: bool = False
    """(A refused scan's first fit) the walls dispute every start tried, not only this one."""


class Tracker:
    """One robot's tracking: :meth:`add` each scan in order."""

    def __init__(self, config: FleetmapConfig | None = None, odometry: bool = True) -> None:
        self.config = config or FleetmapConfig()
        self.params = self.config.tracking
        self.use_odometry = odometry
        self.epoch = -1
        """The current epoch (-1 before the first scan with segments)."""
        self.first_epoch = 0
        """The number of the first epoch (a robot restarted under its id goes on after its earlier run's)."""
        self.active: list[Submap] = []
        """The active submaps, oldest (the matching one) first."""
        self.finished: list[Submap] = []
        """Submaps finished since :meth:`take_finished` was last called, in order."""
        self._submaps = 0
        self._pose: Transform2D | None = None
        """The robot's pose in the epoch's frame after the last scan (predicted if unplaced)."""
        self._stamp: float | None = None
        self._seq = 0
        """The last scan's number in the robot's sequence of scans (from 1)."""
        self._odometry: Transform2D | None = None
        self._good: tuple[float, Transform2D, int] | None = None
        """Stamp, epoch-frame pose and sequence number of the last placed scan."""
        self._velocity = np.zeros(3)
        """Per second of :attr:`clock` time, in the laser's frame."""
        self._velocity_known = False
        """Whether two placed scans of the epoch gave the velocity."""
        self.clock = ScanClock(self.config.integration.motion.max_speed)
        """The time between scans as the evidence supports it (the stamps, or the scans' sequence)."""
        self._held: list[_Held] = []
        self._drift = (0.0, 0.0)
        """The motion model's variances (m^2, rad^2) added up over the steps since the last scan the
        walls placed: the prediction's uncertainty grows with every step they did not check
        (:meth:`_predictions`)."""
        self._step_variance = (0.0, 0.0)
        """The last prediction's own variances, before :attr:`_drift`."""
        self._standing = Prediction(Transform2D(), 0.0, 0.0, "still")
        """The last scan's start from where the robot was last placed (:meth:`_predictions`)."""
        self._track_drift = (0.0, 0.0)
        """:attr:`_drift` as of the last carried scan: the uncertainty of the track the robot is on,
        which the beam test excuses (:meth:`_contradicts`). The scans held since add nothing: they
        are what is being tested, from that track."""
        self._scores: deque[float] = deque(maxlen=self.params.recent_fits)
        """The scores of the robot's recent good fits (:meth:`_fit`)."""
        self._inserted_at: tuple[float, Transform2D] | None = None
        self._odometry_step: Prediction | None = None
        """The last scan's odometry prediction as the wheels gave it (:meth:`_judge_odometry_sign`)."""
        self.reversed_odometry = 0.0
        """The belief that the odometry's translation has lost its sign (:meth:`_judge_odometry_sign`)."""
        self.bad_odometry = 0
        """Odometry readings ignored (not finite, or a jump the robot cannot have driven)."""

    # -- queries -----------------------------------------------------------------------------
    @property
    def matching(self) -> Submap | None:
        return self.active[0] if self.active else None

    @property
    def pose(self) -> Transform2D | None:
        """The robot's pose in the matching submap's frame after the last scan; None if lost."""
        if self._pose is None or self._held or not self.active:
            return None
        return self.active[0].origin.inverse().compose(self._pose)

    @property
    def epoch_pose(self) -> Transform2D | None:
        """The robot's pose in its epoch's frame after the last scan; None if that scan was not placed."""
        if self._pose is None or self._held:
            return None
        return self._pose

    def take_finished(self) -> list[Submap]:
        out, self.finished = self.finished, []
        return out

    # -- the step ----------------------------------------------------------------------------
    def add(
        self, index: int, stamp: float, scan: RangeScan, segments: Array, odometry: Transform2D | None = None
    ) -> list[TrackStep]:
        """Track one scan; the steps it caused (more than one when it starts an epoch: then the
        scans held since the robot lost its place are tracked into it too, in order)."""
        previous = self.clock.previous
        self.clock.tick(stamp)
        if previous is not None and self.clock.distrusted_at == self.clock.scans:
            said = "repeats" if stamp == previous else f"is {previous - stamp:.4f} s before"
            self._say_clock(f"scan {index}'s stamp {said} the previous scan's")
        return self._track(self.clock.scans, index, stamp, scan, segments, odometry)

    # -- internals ---------------------------------------------------------------------------
    def _track(
        self, seq: int, index: int, stamp: float, scan: RangeScan, segments: Array, odometry: Transform2D | None
    ) -> list[TrackStep]:
        samples = sample_segments(segments, self.params.sample_spacing)
        if len(samples) == 0:
            self._advance_blind(seq, stamp, odometry)
            return [TrackStep("empty", max(self.epoch, self.first_epoch), None, None)]
        if self.epoch < 0:
            return [self._start_epoch(seq, index, stamp, scan, segments, samples, odometry, new=False)]
        predictions = self._predictions(seq, stamp, odometry)
        fit = self._fit(scan, samples, segments, predictions, seq, stamp)
        odometry_predicts = "odometry" in predictions[0].source
        if (
            fit.good
            and self._held
            and odometry_predicts
            and not self._within_gate(fit.registration.pose, predictions[0])
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
            before = self._pose
            step = self._place(seq, index, stamp, scan, segments, samples, odometry, fit, status)
            if before is not None and self._pose is not None:
                self._judge_odometry_sign(before.inverse().compose(self._pose))
            return [step]
        if not fit.contradicted and odometry_predicts:
            # No evidence either way (open space, a few metres of wall, a person in front of the
            # laser): the walls neither place the scan nor say it was taken elsewhere. The robot
            # is where its odometry takes it (a fit the walls refused may have slid). Constant
            # velocity does not carry it: it measures nothing, and over a second between scans
            # (a sparse log) it is a guess 1.5 m wide; such a scan is held as before.
            log.debug("scan %d carried by its motion model (%s)", index, fit.why)
            predicted = self.active[0].origin.inverse().compose(self._pose_in_epoch(predictions[0]))
            # placed as the prediction, as sure as its motion model (the walls fixed nothing)
            prior = replace(
                fit.registration,
                pose=predicted,
                information=predictions[0].information(),
                scan_information=np.zeros((3, 3)),
            )
            carried = replace(fit, registration=prior)
            self._held.clear()  # a kidnap is scans contradicted in a row
            drift = self._drift
            step = self._place(seq, index, stamp, scan, segments, samples, odometry, carried, "carried")
            self._drift = drift
            self._carry()  # the walls did not check this step: its uncertainty adds to the next ones'
            self._track_drift = self._drift
            return [step]
        self._pose = self._pose_in_epoch(predictions[0])
        self._stamp, self._seq = stamp, seq
        self._odometry = odometry  # a scan without odometry breaks its chain (:meth:`_place`)
        self._carry()
        counts = fit.everywhere or not fit.contradicted  # (not carried: no odometry)
        self._held.append(_Held(seq, index, stamp, scan, segments, samples, odometry, counts))
        if sum(h.counts for h in self._held) < self.params.kidnap_after:
            log.debug("scan %d did not fit (%s)", index, fit.why)
            return [TrackStep("unplaced", self.epoch, None, None, registration=fit.registration)]
        return self._lost()

    def _typical_floor(self) -> float:
        """The score below which a fit is not typical of the robot's recent ones (:meth:`_fit`)."""
        if len(self._scores) < 3:
            return 0.0
        return self.params.typical_score_share * float(np.median(self._scores))

    def _pose_in_epoch(self, prediction: Prediction) -> Transform2D:
        base = self._pose if self._pose is not None else Transform2D()
        return base.compose(prediction.increment)

    def _advance_blind(self, seq: int, stamp: float, odometry: Transform2D | None) -> None:
        """A scan with nothing to track: the pose moves by odometry (or velocity) alone."""
        if self._pose is not None and self._stamp is not None:
            self._pose = self._pose_in_epoch(self._predictions(seq, stamp, odometry)[0])
            self._stamp, self._seq = stamp, seq
            self._odometry = odometry
            self._carry()
            if not self._held:
                self._track_drift = self._drift

    def _predictions(self, seq: int, stamp: float, odometry: Transform2D | None) -> list[Prediction]:
        """Where the scan should be: by odometry when the robot has it, then by constant velocity
        (each a motion model that can be wrong: a real robot's odometry is off by ten degrees or
        more on some fast turns, and a robot brakes or turns where constant velocity goes on).
        The time since the last scan is the clock's (:class:`ScanClock`): the stamps while they
        agree with the motion, else the scans' sequence. Odometry read at a stamp the clock does
        not trust is as wrong as the stamp: its uncertainty then grows by the motion over the
        stamp's error, and the first start is the two models fused by their information."""
        integration = self.config.integration
        seconds = stamp - self._stamp if self._stamp is not None else 0.0
        elapsed = self.clock.elapsed(seconds, seq - self._seq)
        velocity = from_velocity(self._velocity, elapsed, self.params, integration.motion.max_acceleration)
        out = []
        self._odometry_step = None
        if self.use_odometry and odometry is not None:
            increment, why = odometry_increment(self._odometry, odometry, elapsed, integration.motion.max_speed)
            if increment is not None:
                odometry_prediction = self._odometry_step = from_odometry(increment, self.params)
                if self.reversed_odometry > 0.5:
                    odometry_prediction = replace(
                        odometry_prediction, increment=Transform2D(-increment.x, -increment.y, increment.theta)
                    )
                if not self.clock.trusted:
                    # read at a wrong stamp, the odometry is off by the robot's motion over the
                    # stamp's error: the stamps' interval less the sequence's, a period at least
                    error = max(self.clock.period, abs(seconds - elapsed))
                    step = self._velocity * error
                    odometry_prediction = replace(
                        odometry_prediction,
                        sigma_translation=odometry_prediction.sigma_translation + math.hypot(step[0], step[1]),
                        sigma_rotation=odometry_prediction.sigma_rotation + abs(float(step[2])),
                    )
                out.append(odometry_prediction)
            elif self._odometry is not None:
                self.bad_odometry += 1
                if self.bad_odometry <= 5 or self.bad_odometry % 100 == 0:
                    log.warning("odometry ignored at %.3f s (%s; %d so far)", stamp, why, self.bad_odometry)
        if self.clock.trusted or not out:
            out.append(velocity)
        else:
            # neither model alone: constant velocity drifts along a corridor, the mistimed odometry
            # does not drift but is off scan by scan; each is also a start of its own
            out = [fused(velocity, out[0]), velocity, out[0]]
        self._step_variance = (out[0].sigma_translation ** 2, out[0].sigma_rotation ** 2)
        # The robot standing still where it was last placed is a motion model of its own (as in a
        # multiple-model estimator; Bar-Shalom, Li & Kirubarajan 2001, ch. 11): its uncertainty is that
        # pose's (a carried track's drift) and one step's, not the moving models' predictions
        # chained over the held scans, which a robot that stopped never drove
        t, r = self._track_drift
        self._standing = Prediction(
            Transform2D(),
            math.sqrt(out[-1].sigma_translation ** 2 + t),
            math.sqrt(out[-1].sigma_rotation ** 2 + r),
            "still",
        )
        if self._drift != (0.0, 0.0):
            # the steps since the last placed scan were not checked by the walls: their
            # uncertainty adds up (the covariance of a chain of motions, a random walk)
            t, r = self._drift
            out = [
                replace(
                    q,
                    sigma_translation=math.sqrt(q.sigma_translation**2 + t),
                    sigma_rotation=math.sqrt(q.sigma_rotation**2 + r),
                )
                for q in out
            ]
        return out

    def _within_gate(self, pose: Transform2D, prediction: Prediction) -> bool:
        """Whether a fit's pose (the matching submap's frame) lies within the prediction's 99 %
        validation gate: its squared Mahalanobis distance under the motion model's uncertainty
        within the chi-square bound of three degrees of freedom."""
        placed = self.active[0].origin.compose(pose)
        off = self._pose_in_epoch(prediction).inverse().compose(placed).as_array()
        off[2] = float(wrap_angle(off[2]))
        return float(off @ prediction.information() @ off) <= CHI2_3DOF_99

    def _carry(self) -> None:
        """The scan just predicted was not placed by the walls: its step's uncertainty adds to the
        next ones'."""
        self._drift = (self._drift[0] + self._step_variance[0], self._drift[1] + self._step_variance[1])

    def _judge_odometry_sign(self, moved: Transform2D) -> None:
        """Update the belief that the odometry's translation has lost its sign, from the motion the
        scan was placed with: a two-state hidden Markov model (the wheels' speed signed, or not),
        filtered forward (Rabiner 1989, the forward algorithm). Each state predicts the increment
        (the odometry's, or its translation negated, its turn kept), with the odometry's own
        uncertainty. Some logs' odometry adds up the wheels' speed without its sign, so reversing it
        drives forward (fr079's, and the corrected log made from it, which carries no speed to
        tell: 103 of its 4,790 steps); along a corridor the walls cannot say which way the robot
        went, and the odometry's prior decides. A robot changes its direction of travel only
        through standing still: after a step the odometry cannot tell from standing still (within
        ``odometry_translation_sigma``) either state is as likely, and the next steps' evidence
        decides; while the robot moves, the belief holds unless a step only the other state explains
        turns it by a likelihood ratio over 1e9. A step neither state explains (the chi-square
        validation gate) says nothing of the sign. Where the odometry keeps its sign the signed
        state predicts the motion and holds (docs/decisions/009-clocks-evidence-over-stamps.md)."""
        step = self._odometry_step
        if step is None:
            return
        signed = step.increment
        if math.hypot(signed.x, signed.y) < self.params.odometry_translation_sigma:
            self.reversed_odometry = 0.5  # standing still: either way next
            return
        unsigned = Transform2D(-signed.x, -signed.y, signed.theta)
        information = step.information()

        def distance(predicted: Transform2D) -> float:
            off = predicted.inverse().compose(moved).as_array()
            off[2] = float(wrap_angle(off[2]))
            return float(off @ information @ off)

        d_signed, d_unsigned = distance(signed), distance(unsigned)
        low = min(d_signed, d_unsigned)  # likelihoods relative to the likelier state's
        if low > CHI2_3DOF_99:
            return  # neither state explains the step (the validation gate): the odometry is off otherwise
        l_signed, l_unsigned = math.exp(-0.5 * (d_signed - low)), math.exp(-0.5 * (d_unsigned - low))
        # a belief held while moving is never quite certain: a step that only the other state
        # explains, by a likelihood ratio over 1e9, still turns it (a sparse log's robot can stop
        # and reverse between two scans)
        b = min(max(self.reversed_odometry, 1e-9), 1.0 - 1e-9)
        self.reversed_odometry = b * l_unsigned / (b * l_unsigned + (1.0 - b) * l_signed)

    def _fit(
        self,
        scan: RangeScan,
        samples: ScanSamples,
        segments: Array,
        predictions: list[Prediction],
        seq: int,
        stamp: float,
    ) -> _Fit:
        """The scan's fit on the matching submap.

        The first prediction's fit is taken when it is good and typical: its score at least
        ``typical_score_share`` of the median of the robot's recent fits (a fit that suddenly
        supports a third of what the last ones did has likely slid into a wrong minimum). Otherwise
        the other predictions, and the robot standing still, are tried too, and the pose-free
        integration (:meth:`_reacquire`) if none is typical; a later fit replaces an earlier good one
        only if it scores over ``1 / typical_score_share`` times as much (where the walls leave a
        direction free, as along a corridor, the fits score alike and the first prediction's
        stands). Failing all, the first fit, not good."""
        submap = self.active[0]
        share = self.params.typical_score_share
        floor = self._typical_floor()
        tried: list[Transform2D] = []
        fits: list[_Fit] = []
        last = self._good[1] if self._good is not None else self._pose or Transform2D()
        standing = self._standing
        # Two motion models that disagree on the heading by more than the first one's uncertainty:
        # one of them is wrong (a real robot's odometry can be off by 10-25 degrees on one fast
        # turn), and a registration started ten degrees off may settle in a wrong minimum. The walls
        # fix the heading everywhere, so both are registered and the better fit by score is taken.
        apart = (
            len(predictions) > 1
            and abs(float(wrap_angle(predictions[1].increment.theta - predictions[0].increment.theta)))
            > predictions[0].sigma_rotation
        )
        for n, prediction in enumerate([*predictions, standing]):
            if n and fits and fits[0].good and fits[0].registration.score >= floor and not (apart and n == 1):
                break
            # the robot standing still where it was last placed; the models from its last pose
            base = last.compose(prediction.increment) if prediction is standing else self._pose_in_epoch(prediction)
            predicted = submap.origin.inverse().compose(base)
            if any(_same_start(predicted, other, self.params) for other in tried):
                continue
            tried.append(predicted)
            reg = register(samples, submap.reference, predicted, predicted, prediction.information(), self.params)
            why, (contradicted, disputed) = self._judge(reg, scan, segments, submap)
            fits.append(_Fit(reg, why == "", why, contradicted, disputed))
        best = None
        for n, fit in enumerate(fits):
            # the two motion models' fits weigh alike by score, unless they turn alike and lie
            # beyond registration's reach of each other: two minima of one heading, apart along
            # what the walls leave free, where the scores cannot tell them apart and the first
            # prediction's stands as any other's does (down a corridor logged a scan a metre, the
            # better-scoring of two such fits lay 1.3-1.5 m along it: aces-corrected scans 26, 49,
            # 318; two fits within reach are one minimum found better, mit-csail's fast turns)
            settled = (
                apart and n == 1 and not _minima_along(fit.registration.pose, fits[0].registration.pose, self.params)
            )
            margin = 1.0 if settled else share
            if fit.good and (best is None or fit.registration.score * margin >= best.registration.score):
                best = fit
        if best is None or best.registration.score < floor:
            # a scan re-acquired by pose-free integration must fit as well as the robot's scans
            # usually do: one that explains a fraction of what they did matched a look-alike (a
            # carried robot's view of one corridor on another)
            again = self._reacquire(scan, samples, segments, submap, seq, stamp)
            if (
                again is not None
                and again.registration.score >= floor
                and (best is None or again.registration.score * share >= best.registration.score)
            ):
                best = again
        if best is not None:
            self._scores.append(best.registration.score)
            return best
        return replace(fits[0], everywhere=all(f.disputed for f in fits))

    def _judge(
        self, reg: Registration, scan: RangeScan, segments: Array, submap: Submap
    ) -> tuple[str, tuple[bool, bool]]:
        """Why the fit is not good ("" when it is), and whether the walls contradict it: the walls'
        evidence alone. How far the robot can have driven does not judge a registration started
        near the prediction (the clock may be wrong; the walls are not): it bounds only where the
        pose-free search looks (:meth:`_reacquire`).

        For a refused fit, also what the walls say against it (:meth:`_contradicts`): too little of
        the scan on the submap's walls says only that they cannot place it (open space, a few
        metres of wall, new walls, a person in front of the laser)."""
        p = self.params
        max_range = self.config.extraction.max_range
        through, visible = see_through(submap.reference, scan, reg.pose, p, max_range)
        seen_through = visible > 0 and through > p.max_see_through * visible
        if reg.matched_length >= p.min_matched_length and reg.matched_share >= p.min_matched_share:
            if seen_through:
                why = f"its beams pass through {through:.1f} of {visible:.1f} m of the submap's walls"
                return why, self._contradicts(reg, scan, segments, submap)
            return "", (False, False)
        why = f"{reg.matched_length:.1f} m ({100 * reg.matched_share:.0f} %) of the scan on the submap's walls"
        return why, self._contradicts(reg, scan, segments, submap)

    def _contradicts(self, reg: Registration, scan: RangeScan, segments: Array, submap: Submap) -> tuple[bool, bool]:
        """Whether the scan and the submap disagree on space both saw at the fit's pose: *contradicted*
        (more wall in dispute than agreed on) and *disputed* (at least as much wall in dispute as it
        takes to place a scan, ``min_matched_length``, whatever is agreed on). In dispute are the
        submap's walls the scan's beams pass through (against those they return from: a return
        short of a wall is something in between, none at all a failure, one beyond it a wrong pose;
        the beam model, Thrun, Burgard & Fox 2005, 6.3), and the scan's walls where the submap's
        own scans saw through more than they saw (the rule that judges a submap's walls,
        :func:`wall_evidence`; against the scan's wall matched). The beam test's margin grows by
        the uncertainty of the track the robot is carried on (99 %, one degree of freedom along
        the beam): a carried pose a metre off sees through walls it did not pass."""
        p = self.params
        max_range = self.config.extraction.max_range
        if self._track_drift != (0.0, 0.0):
            z = math.sqrt(CHI2_1DOF_99)
            p = replace(
                p,
                see_through_margin=p.see_through_margin + z * math.sqrt(self._track_drift[0]),
                see_through_slope=p.see_through_slope + z * math.sqrt(self._track_drift[1]),
            )
        through, hit = beam_evidence(submap.reference, scan, reg.pose, p, max_range)
        in_free_space = 0.0
        if submap.scans_in:
            walls = reg.pose.apply(segments)
            seen, passed = wall_evidence(walls, submap.scans_in, p, max_range, max_range)
            length = np.hypot(walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1])
            in_free_space = float(length[passed > seen].sum())
        enough = p.min_matched_length
        contradicted = (through >= enough and through > hit) or (
            in_free_space >= enough and in_free_space > reg.matched_length
        )
        return contradicted, through >= enough or in_free_space >= enough

    def _reachable(self, pose: Transform2D, seq: int, stamp: float) -> bool:
        """Whether the robot can have driven to ``pose`` (epoch frame) since its last placed scan:
        no farther than ``max_speed`` allows, and, once its velocity is known, no farther from where
        that velocity takes it than ``max_acceleration`` allows (plus ``witness_translation`` for the
        fits' own error). Physics, not a pose: a look-alike corridor matches well, but a robot
        driving at 1.5 m/s is not 1.4 m on 0.4 s later."""
        integration = self.config.integration
        if self._good is None:
            return True
        seconds = self.clock.elapsed(stamp - self._good[0], seq - self._good[2])
        last = self._good[1]
        margin = integration.pivot.witness_translation
        if integration.motion.max_speed > 0 and math.hypot(pose.x - last.x, pose.y - last.y) > (
            integration.motion.max_speed * seconds + margin
        ):
            return False
        if integration.motion.max_acceleration > 0 and self._velocity_known:
            v = self._velocity * seconds
            expected = last.compose(Transform2D(float(v[0]), float(v[1]), float(v[2])))
            off = math.hypot(pose.x - expected.x, pose.y - expected.y)
            return off <= 0.5 * integration.motion.max_acceleration * seconds * seconds + margin
        return True

    def _reacquire(
        self,
        scan: RangeScan,
        samples: ScanSamples,
        segments: Array,
        submap: Submap,
        seq: int,
        stamp: float,
    ) -> _Fit | None:
        """The paper's pose-free integration of the scan on the submap, within the robot's reach of
        its last placed scan (any heading), then registered and checked: a fit where the robot can
        have driven, or None."""
        built = submap.segment_map()
        if len(built) == 0:
            return None
        reach = self._reach(seq, stamp)
        last = submap.origin.inverse().compose(self._good[1] if self._good is not None else self._pose or Transform2D())
        near = _near(built, last, reach + self.config.extraction.max_range)
        if len(near) == 0:
            return None
        window = Window(last, reach, math.pi)
        found = integrate(
            near, SegmentMap(segments, ordered=True, oriented=True), self.config.integration, window=window
        )
        if not found.valid:
            return None
        start = found.transform
        # the prior is the integration's pose, loosely: the walls decide
        loose = np.diag([1.0 / 0.25**2, 1.0 / 0.25**2, 1.0 / 0.1**2])
        reg = register(samples, submap.reference, start, start, loose, self.params)
        why, _ = self._judge(reg, scan, segments, submap)
        if why != "" or not self._reachable(submap.origin.compose(reg.pose), seq, stamp):
            return None
        return _Fit(reg, True, "reacquired")

    def _reach(self, seq: int, stamp: float) -> float:
        """How far (m) the robot can have driven since its last placed scan."""
        integration = self.config.integration
        if self._good is None or integration.motion.max_speed <= 0:
            return self.config.extraction.max_range
        seconds = self.clock.elapsed(stamp - self._good[0], seq - self._good[2])
        return integration.motion.max_speed * seconds + integration.pivot.witness_translation

    def _place(
        self,
        seq: int,
        index: int,
        stamp: float,
        scan: RangeScan,
        segments: Array,
        samples: ScanSamples,
        odometry: Transform2D | None,
        fit: _Fit,
        status: str,
    ) -> TrackStep:
        submap = self.active[0]
        reg = fit.registration
        pose = submap.origin.compose(reg.pose)
        if self._good is not None:
            self._check_clock(index, stamp, pose, reg)
            seconds = self.clock.elapsed(stamp - self._good[0], seq - self._good[2])
            self._velocity, self._velocity_known = velocity_between(self._good[1], pose, seconds), True
        self._pose, self._stamp, self._seq, self._good = pose, stamp, seq, (stamp, pose, seq)
        self._drift = self._track_drift = (0.0, 0.0)
        # a scan without odometry breaks its chain: the next increment is measured from the next
        # reading, never across a stretch that no reading saw (a corrected log's scans with no
        # wheel reading between them, :func:`~fleetmap.shared.io.logs.read_carmen_odometry`)
        self._odometry = odometry
        submap.placed.append(PlacedScan(index, stamp, reg.pose))
        if self._due(stamp, pose):
            self._insert(index, stamp, scan, segments, samples, pose, reg)
        return TrackStep(status, self.epoch, submap.number, reg.pose, registration=reg)

    def _check_clock(self, index: int, stamp: float, pose: Transform2D, reg: Registration) -> None:
        """Judge the stamps by the motion since the last placed scan (:meth:`ScanClock.check`),
        uncertain as the walls fix the two poses along it; say once when they fail."""
        if self._good is None:
            return
        last = self._good[1]
        dx, dy = pose.x - last.x, pose.y - last.y
        distance = math.hypot(dx, dy)
        if distance == 0:
            return
        sigma = _sigma_along(reg.scan_information, self.active[0].origin.theta, dx / distance, dy / distance)
        was = self.clock.trusted
        self.clock.check(stamp - self._good[0], distance, math.sqrt(2.0) * sigma)
        if was and not self.clock.trusted:
            seconds = stamp - self._good[0]
            self._say_clock(f"scan {index} moved {distance:.2f} m in the {seconds:.4f} s its stamp allows")

    def _say_clock(self, evidence: str) -> None:
        """Say once per log that its stamps are not its scans' times, and why."""
        c = self.clock
        log.warning(
            "%s: the stamps are not the scans' times; tracking by their sequence at the log's mean period "
            "(%.3f s so far) from here (%d scans in: %d stamps repeated, %d going back)",
            evidence,
            c.period,
            c.scans,
            c.repeated,
            c.backwards,
        )

    def _due(self, stamp: float, pose: Transform2D) -> bool:
        p = self.params
        if self._inserted_at is None:
            return True
        when, where = self._inserted_at
        moved = math.hypot(pose.x - where.x, pose.y - where.y)
        turned = abs(float(wrap_angle(pose.theta - where.theta)))
        return moved >= p.insert_distance or turned >= p.insert_rotation or stamp - when >= p.insert_interval

    def _insert(
        self,
        index: int,
        stamp: float,
        scan: RangeScan,
        segments: Array,
        samples: ScanSamples,
        pose: Transform2D,
        reg: Registration | None,
    ) -> None:
        """Insert a placed scan (epoch-frame ``pose``) into the active submaps; finish and start
        submaps as they fill (see the module docstring)."""
        p = self.params
        self._inserted_at = (stamp, pose)
        for submap in self.active:
            submap.insert(scan, samples, segments, submap.origin.inverse().compose(pose))
        newest = self.active[-1]
        half = newest.path_length >= p.submap_length / 2 or newest.inserted >= max(p.submap_scans // 2, 1)
        if half and len(self.active) == 1:
            self._start_submap(index, pose, scan, segments, samples, reg)
        oldest = self.active[0]
        if len(self.active) > 1 and (oldest.path_length >= p.submap_length or oldest.inserted >= p.submap_scans):
            oldest.finished = True
            self.finished.append(self.active.pop(0))
            newest = self.active[-1]
            if newest.path_length >= p.submap_length / 2 or newest.inserted >= max(p.submap_scans // 2, 1):
                self._start_submap(index, pose, scan, segments, samples, reg)

    def _start_submap(
        self,
        index: int,
        pose: Transform2D,
        scan: RangeScan,
        segments: Array,
        samples: ScanSamples,
        reg: Registration | None,
    ) -> None:
        previous = self.active[-1] if self.active else None
        link = covariance = None
        if previous is not None:
            link = previous.origin.inverse().compose(pose)
            covariance = _link_covariance(reg, self.params) + drift_covariance(self.params, previous.path_length)
        walls = WallMap(self.config.integration.simplify_tolerance)
        submap = Submap(
            self.epoch,
            self._submaps,
            index,
            pose,
            link,
            covariance,
            ReferenceMap(self.params.voxel_size),
            walls,
            self.params,
            self.config.extraction.max_range,
        )
        self._submaps += 1
        submap.insert(scan, samples, segments, Transform2D())
        self.active.append(submap)

    def _start_epoch(
        self,
        seq: int,
        index: int,
        stamp: float,
        scan: RangeScan,
        segments: Array,
        samples: ScanSamples,
        odometry: Transform2D | None,
        new: bool,
    ) -> TrackStep:
        """Begin an epoch whose frame is this scan's pose."""
        for submap in self.active:
            submap.finished = True
            self.finished.append(submap)
        self.active = []
        self.epoch = max(self.epoch + 1, self.first_epoch)
        self._submaps = 0
        self._pose, self._stamp, self._seq, self._good = Transform2D(), stamp, seq, (stamp, Transform2D(), seq)
        self._drift = self._track_drift = (0.0, 0.0)
        self._odometry = odometry
        self._velocity, self._velocity_known = np.zeros(3), False
        self._inserted_at = None
        self._held = []
        self._scores.clear()
        self._start_submap(index, Transform2D(), scan, segments, samples, None)
        self._inserted_at = (stamp, Transform2D())
        self.active[0].placed.append(PlacedScan(index, stamp, Transform2D()))
        return TrackStep("first", self.epoch, 0, Transform2D(), new_epoch=new, first_scan=index)

    def _lost(self) -> list[TrackStep]:
        """``kidnap_after`` scans the walls contradict, with none placed between: a new epoch from the first of them."""
        held, self._held = self._held, []
        first = held[0]
        log.info("epoch %d from scan %d (%s)", self.epoch + 1, first.index, KIDNAP_REASON.format(n=len(held)))
        steps = [
            self._start_epoch(
                first.seq, first.index, first.stamp, first.scan, first.segments, first.samples, first.odometry, new=True
            )
        ]
        for h in held[1:]:
            steps += self._track(h.seq, h.index, h.stamp, h.scan, h.segments, h.odometry)
        return steps

    def submaps(self) -> Iterator[Submap]:
        """The active submaps, oldest first."""
        return iter(self.active)


def _minima_along(a: Transform2D, b: Transform2D, p: TrackingParams) -> bool:
    """Whether two fits of one scan are two minima of one heading: they turn alike (within
    :data:`REACH_ROTATION`) and lie beyond registration's reach of each other (:func:`_same_start`)."""
    return a.distance(b)[1] <= REACH_ROTATION and not _same_start(a, b, p)


def _same_start(a: Transform2D, b: Transform2D, p: TrackingParams) -> bool:
    """Whether registering from ``a`` only repeats registering from ``b``: they lie within
    registration's reach of each other (``max_correspondence``, :data:`REACH_ROTATION`). Not the
    motion model's uncertainty: on a fast turn the odometry's is 20 degrees, and a velocity
    prediction 14 degrees from it starts a registration the odometry's could not (mit-csail)."""
    d, r = a.distance(b)
    return d <= p.max_correspondence and r <= REACH_ROTATION


def _link_covariance(reg: Registration | None, p: TrackingParams) -> Array:
    """The covariance of a submap link from the registration that placed the new submap's frame,
    no tighter than ``link_min_sigma_translation`` and ``link_min_sigma_rotation``."""
    st, sr = p.link_min_sigma_translation, p.link_min_sigma_rotation
    floor = np.diag([st**2, st**2, sr**2])
    if reg is None:
        return floor
    try:
        cov = np.linalg.inv(reg.information)
    except np.linalg.LinAlgError:
        return floor
    cov = 0.5 * (cov + cov.T) + floor
    return cov


def _near(m: SegmentMap, pose: Transform2D, radius: float) -> SegmentMap:
    """The segments of ``m`` with an end within ``radius`` (box) of ``pose``."""
    seg = m.segments
    near = (np.abs(seg[:, 0:4:2] - pose.x) <= radius).any(axis=1) & (np.abs(seg[:, 1:4:2] - pose.y) <= radius).any(
        axis=1
    )
    return SegmentMap(seg[near], ordered=False, oriented=m.oriented)


def _sigma_along(information: Array, heading: float, ux: float, uy: float) -> float:
    """The standard deviation (m) along the unit direction ``(ux, uy)`` (epoch frame) of a pose
    fixed with ``information`` in a frame turned by ``heading``; infinite where the walls leave that
    direction free."""
    c, s = math.cos(heading), math.sin(heading)
    u = np.array([c * ux + s * uy, -s * ux + c * uy, 0.0])
    try:
        covariance = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return math.inf
    variance = float(u @ covariance @ u)
    return math.sqrt(variance) if variance > 0 and math.isfinite(variance) else math.inf
