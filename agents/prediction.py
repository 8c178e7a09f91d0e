"""Where a robot's next scan should be, and how far it can be from there: the tracker's motion
models (:mod:`fleetmap.agents.tracker`, step 1 of its walk-through, and the reach that bounds
steps 3 and 4).

The odometry's increment when the robot has odometry, else constant velocity
(:mod:`fleetmap.shared.core.motion`), each with its uncertainty; the robot standing still where it
was last placed as a model of its own. The uncertainty of the steps the walls did not check adds
up until they place a scan again (the *drift*). The odometry's sign is judged from the motion the
scans were placed with (:meth:`Predictor.judge_odometry_sign`).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import replace

import numpy as np
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.motion import (
    CHI2_3DOF_99,
    ODOMETRY_TRANSLATION_SIGMA,
    Prediction,
    ScanClock,
    from_odometry,
    from_velocity,
    fused,
    odometry_increment,
    velocity_between,
)
from fleetmap.shared.core.pivotmap import WITNESS_TRANSLATION
from fleetmap.shared.core.pointstep import point_step

log = logging.getLogger(__name__)

OTHER_SIGN = "odometry, the other sign"
"""The source of the odometry's prediction with its translation's sign turned (:meth:`Predictor.predictions`)."""
SIGN_DOUBT = 0.01
"""While the sign the odometry is not believed to have keeps at least this chance (the 1 % the
99 % gates leave out), it is a motion model of its own (:meth:`Predictor.predictions`)."""

MISFITS = 100
"""The recent exact readings whose misses' median widens the next (:meth:`Predictor.measure_misfit`):
a minute of a dense log, the last hundred metres of a sparse one, and bounded for a robot that runs
for days."""

Placed = tuple[float, Transform2D, int]
"""Stamp, epoch-frame pose and sequence number of a robot's last placed scan."""


class Predictor:
    """One robot's motion models between its placed scans."""

    def __init__(self, config: FleetmapConfig, odometry: bool = True) -> None:
        self.config = config
        self.use_odometry = odometry
        self.clock = ScanClock(config.integration.motion.max_speed)
        """The time between scans as the evidence supports it (the stamps, or the scans' sequence)."""
        self.odometry: Transform2D | None = None
        """The odometry reading of the last scan, which the next increment starts from."""
        self.own_readings = False
        """Whether the readings are the scans' own, not read at their stamps
        (:attr:`fleetmap.agents.bursts.BurstOdometry.own_readings`): a wrong clock leaves them right."""
        self.velocity = np.zeros(3)
        """Per second of :attr:`clock` time, in the laser's frame."""
        self.velocity_known = False
        """Whether two placed scans of the epoch gave the velocity."""
        self.velocity_sigma = math.inf
        """How sure the velocity's translation is (m/s, the same in every direction): the last step's
        own uncertainty as its placement measured it, over its time (inf: not measured, as before
        two placed scans)."""
        self.drift = (0.0, 0.0)
        """The motion model's variances (m^2, rad^2) added up over the steps since the last scan the
        walls placed: the prediction's uncertainty grows with every step they did not check
        (:meth:`predictions`)."""
        self.step_variance = (0.0, 0.0)
        """The last prediction's own variances, before :attr:`drift`."""
        self.standing = Prediction(Transform2D(), 0.0, 0.0, "still")
        """The last scan's start from where the robot was last placed (:meth:`predictions`)."""
        self.track_drift = (0.0, 0.0)
        """:attr:`drift` as of the last carried scan: the uncertainty of the track the robot is on,
        which the beam test excuses (:func:`fleetmap.agents.fitcheck.contradicts`). The scans held
        since add nothing: they are what is being tested, from that track."""
        self.odometry_step: Prediction | None = None
        """The last scan's odometry prediction as the wheels gave it (:meth:`judge_odometry_sign`)."""
        self.reversed_odometry = 0.0
        """The belief that the odometry's translation has lost its sign (:meth:`judge_odometry_sign`)."""
        self.stops = 0.0
        self.turns = 0.0
        """The robot's stops so far, the first aside, and how many of them turned the sign (expected
        counts): the chance that a stop turns it (:meth:`judge_odometry_sign`)."""
        self._stopped = False
        """Whether the last judged step was a stop (a stop of several steps counts once)."""
        self._belief_at_stop: float | None = None
        """:attr:`reversed_odometry` as the robot reached its last stop."""
        self.bad_odometry = 0
        """Odometry readings ignored (not finite, or a jump the robot cannot have driven)."""
        self.exact = True
        """Whether the scan's reading is the one taken where it was (not spread within a burst)."""
        self.by_pace = False
        """Whether that reading is the robot's pace's guess (:attr:`~fleetmap.agents.tracker.Tracker.by_pace`)."""
        self.misfits: deque[float] = deque(maxlen=MISFITS)
        """What the recent exact readings at stamps the clock does not trust missed the walls by:
        each miss squared, beyond the odometry's own uncertainty, as a share of the motion over the
        stamp's error squared (:meth:`measure_misfit`)."""
        self._widened: tuple[float, float, Transform2D] | None = None
        """The last prediction's motion over the stamp's error, its own uncertainty (m) and its
        increment (the sign as believed), if widened by that motion."""

    def restart(self, odometry: Transform2D | None) -> None:
        """An epoch begins at a scan with this odometry reading: nothing is known of the motion."""
        self.drift = self.track_drift = (0.0, 0.0)
        self.odometry = odometry
        self.velocity, self.velocity_known, self.velocity_sigma = np.zeros(3), False, math.inf

    def moved(self, last: Placed, pose: Transform2D, seq: int, stamp: float, information: Array) -> None:
        """The walls placed a scan at ``pose`` (epoch frame) after the last placed scan: the velocity
        between the two, as sure as the placement's ``information`` (the walls' and the prior's,
        as registration measured them) makes the step: a Kalman filter's velocity, measured by the
        step. Along a corridor whose walls fix nothing, the step is the prediction's, and so is the
        velocity: a velocity not yet measured stays so there, rather than becoming the standing
        start the prior was centred on (an epoch begun in such a corridor was placed 0.3 m short a
        scan until three epochs had begun)."""
        seconds = self.clock.elapsed(stamp - last[0], seq - last[2], seq)
        self.velocity, self.velocity_known = velocity_between(last[1], pose, seconds), True
        self.velocity_sigma = math.inf
        if seconds > 0:
            try:
                widest = float(np.linalg.eigvalsh(np.linalg.inv(information)[:2, :2]).max())
            except np.linalg.LinAlgError:
                return
            self.velocity_sigma = math.sqrt(max(widest, 0.0)) / seconds

    def carry(self) -> None:
        """The scan just predicted was not placed by the walls: its step's uncertainty adds to the
        next ones'."""
        self.drift = (self.drift[0] + self.step_variance[0], self.drift[1] + self.step_variance[1])

    def predictions(
        self, seq: int, stamp: float, odometry: Transform2D | None, last_stamp: float | None, last_seq: int
    ) -> list[Prediction]:
        """Where the scan should be, from the last scan (``last_stamp``, ``last_seq``): by odometry
        when the robot has it, then by constant velocity (each a motion model that can be wrong: a
        real robot's odometry is off by ten degrees or more on some fast turns, and a robot brakes
        or turns where constant velocity goes on). The time since the last scan is the clock's
        (:class:`ScanClock`): the stamps while they agree with the motion, else the scans' sequence.
        Odometry read at a stamp the clock does not trust is as wrong as the stamp: its uncertainty
        then grows by the motion over the stamp's error, as far as the exact readings were measured
        to miss (:meth:`measure_misfit`), and the first start is the two models
        fused by their information; readings shown to be the scans' own (:attr:`own_readings`) are
        not read at a stamp, and stay as sure as on a true clock."""
        seconds = stamp - last_stamp if last_stamp is not None else 0.0
        elapsed = self.clock.elapsed(seconds, seq - last_seq, seq)
        timed = self.clock.times(seq - last_seq, seq)
        velocity = self._velocity(elapsed)
        out = []
        self.odometry_step = self._widened = None
        odometry_prediction = None
        if self.use_odometry and odometry is not None:
            odometry_prediction = self._by_odometry(odometry, stamp, seconds, elapsed, velocity, timed)
            if odometry_prediction is not None:
                out.append(odometry_prediction)
        if timed or self.own_readings or not out:
            out.append(velocity)
        else:
            # neither model alone: constant velocity drifts along a corridor, the mistimed odometry
            # does not drift but is off scan by scan; each is also a start of its own
            out = [fused(velocity, out[0]), velocity, out[0]]
        self.step_variance = (out[0].sigma_translation ** 2, out[0].sigma_rotation ** 2)
        # The robot standing still where it was last placed is a motion model of its own (as in a
        # multiple-model estimator; Bar-Shalom, Li & Kirubarajan 2001, ch. 11): its uncertainty is that
        # pose's (a carried track's drift) and one step's, not the moving models' predictions
        # chained over the held scans, which a robot that stopped never drove
        t, r = self.track_drift
        self.standing = Prediction(
            Transform2D(),
            math.sqrt(out[-1].sigma_translation ** 2 + t),
            math.sqrt(out[-1].sigma_rotation ** 2 + r),
            "still",
        )
        if odometry_prediction is not None and min(self.reversed_odometry, 1.0 - self.reversed_odometry) >= SIGN_DOUBT:
            # the sign in doubt (a robot's first stops: either sign as likely): the other sign is a
            # motion model of its own, registered too, and the walls weigh the two (as a
            # multiple-model estimator weighs its models by the measurement; Bar-Shalom, Li &
            # Kirubarajan 2001, ch. 11). From the believed sign alone, a sparse log's registration
            # settles where the walls repeat and confirms it: freiburg-campus-corrected's fourth
            # piece drove 8 m backwards down a row of posts after a turn in place, scoring 15
            # against the other sign's 26 (docs/decisions/043)
            step = odometry_prediction.increment
            turned = Transform2D(-step.x, -step.y, step.theta)
            out.append(replace(odometry_prediction, increment=turned, source=OTHER_SIGN))
        return [self._drifted(q) for q in out]

    def velocity_by_sequence(self, seq: int, last_seq: int) -> Prediction:
        """Constant velocity over the time the scans' sequence takes since the last scan (the log's
        mean period a scan), whatever the stamps say; no state changes (the search that doubts the
        stamps: :meth:`fleetmap.agents.fitting.FitSearch._sequence_fit`)."""
        return self._drifted(self._velocity(max(seq - last_seq, 1) * self.clock.period))

    def _velocity(self, elapsed: float) -> Prediction:
        """Constant velocity over ``elapsed`` seconds."""
        motion = self.config.integration.motion
        velocity = from_velocity(self.velocity, elapsed, motion.max_acceleration)
        if motion.max_speed > 0:
            # no two placed scans have measured the motion yet, or the walls did not fix the last
            # step: the robot may be driving at any speed it can, or as fast as the step allows,
            # not standing still (an epoch begun in a corridor, whose walls fix nothing along it,
            # was placed as standing, 0.3 m short a scan)
            reach = min(self.velocity_sigma, motion.max_speed) * elapsed
            velocity = replace(velocity, sigma_translation=max(velocity.sigma_translation, reach))
        return velocity

    def _drifted(self, q: Prediction) -> Prediction:
        """``q`` as unsure as the steps since the last placed scan, which the walls did not check,
        make it: their uncertainty adds up (the covariance of a chain of motions, a random walk)."""
        if self.drift == (0.0, 0.0):
            return q
        t, r = self.drift
        return replace(
            q,
            sigma_translation=math.sqrt(q.sigma_translation**2 + t),
            sigma_rotation=math.sqrt(q.sigma_rotation**2 + r),
        )

    def _by_odometry(
        self, odometry: Transform2D, stamp: float, seconds: float, elapsed: float, velocity: Prediction, timed: bool
    ) -> Prediction | None:
        """The odometry's prediction (its sign as believed, :meth:`judge_odometry_sign`); None, with
        a warning, for a reading that is not finite or jumps farther than the robot can drive.
        ``velocity``: constant velocity's prediction of the same step."""
        integration = self.config.integration
        increment, why = odometry_increment(self.odometry, odometry, elapsed, integration.motion.max_speed)
        if increment is None:
            if self.odometry is not None:
                self.bad_odometry += 1
                if self.bad_odometry <= 5 or self.bad_odometry % 100 == 0:
                    log.warning("odometry ignored at %.3f s (%s; %d so far)", stamp, why, self.bad_odometry)
            return None
        self.odometry_step = from_odometry(increment)
        prediction = self.believed(self.odometry_step)
        if not timed and not self.own_readings:
            if self.by_pace and self.velocity_known:
                # A reading spread within a burst is a guess that the robot kept its pace between
                # the burst's two readings (:func:`fleetmap.agents.bursts.between`). It is off where
                # the robot did not, by about as far as the guess and the pace the walls last
                # measured (constant velocity) part: driven evenly down a corridor they agree, and
                # the guess holds the robot where the walls cannot; on a turn or a stop within the
                # burst they part, and the walls decide (docs/decisions/040). So is the burst's own
                # reading where the scan it was given to is a guess by the pace: given to the
                # right one, it agrees with the pace and stays sure (not widened by a whole
                # period's motion, which let registration slide along a corridor); given to the
                # wrong one (a driver that repeated a stamp), it is a scan's step off (record 054).
                apart = prediction.increment.as_array() - velocity.increment.as_array()
                return replace(
                    prediction,
                    sigma_translation=prediction.sigma_translation + math.hypot(apart[0], apart[1]),
                    sigma_rotation=prediction.sigma_rotation + abs(math.remainder(apart[2], 2 * math.pi)),
                )
            # read at a wrong stamp, the odometry is off by the robot's motion over the
            # stamp's error (the stamps' interval less the sequence's, a period at least), as far
            # as the recent exact readings' misfits say (covariance matching: Mehra 1970, by their
            # median: :meth:`measure_misfit`); a reading spread within a burst before the walls
            # measured the robot's pace, by all of it
            error = max(self.clock.period, abs(seconds - elapsed))
            step = self.velocity * error
            bound = math.hypot(step[0], step[1])
            # until the walls have measured a reading, it is off by the whole of that motion
            measured = self.exact and bool(self.misfits)
            share = math.sqrt(max(float(np.median(self.misfits)), 0.0)) if measured else 1.0
            if self.exact:
                self._widened = (bound, prediction.sigma_translation, prediction.increment)
            prediction = replace(
                prediction,
                sigma_translation=prediction.sigma_translation + share * bound,
                sigma_rotation=prediction.sigma_rotation + share * abs(float(step[2])),
            )
        return prediction

    def believed(self, step: Prediction) -> Prediction:
        """The odometry's ``step`` with the sign its translation is believed to have
        (:meth:`judge_odometry_sign`)."""
        if self.reversed_odometry <= 0.5:
            return step
        inc = step.increment
        return replace(step, increment=Transform2D(-inc.x, -inc.y, inc.theta))

    def measure_misfit(self, moved: Transform2D) -> None:
        """The walls placed the last scan ``moved`` on from the one before: what its exact reading,
        widened for a clock not trusted, missed that by (beyond the odometry's own uncertainty),
        as a share of the widening, joins :attr:`misfits`. A log whose readings are their scans'
        own, whatever the stamps say, measures them right and keeps them as sure as on a true
        clock; one whose readings are read at the wrong stamps measures them off (aces with a
        repeated stamp: the widened prior let registration slide along corridors, 96.9 -> 95.4 %).

        The widening is the misses' median, not their mean (covariance matching's, Mehra 1970): a
        miss is the walls' as much as the reading's, and one scan the walls placed wrong, or a
        reading given to the wrong scan of a burst, in a turn in place (a widening of centimetres,
        a miss of a metre) ruled the mean for the rest of the log and widened every right reading
        after it (docs/decisions/056)."""
        widened, self._widened = self._widened, None
        if widened is None or widened[0] <= 0.0:
            return
        bound, own, increment = widened
        miss = math.hypot(moved.x - increment.x, moved.y - increment.y)
        self.misfits.append((miss * miss - own * own) / (bound * bound))

    def reach(self, last: Placed | None, seq: int, stamp: float) -> float:
        """How far (m) the robot can have driven since its ``last`` placed scan."""
        integration = self.config.integration
        if last is None or integration.motion.max_speed <= 0:
            return self.config.extraction.max_range
        seconds = self.clock.elapsed(stamp - last[0], seq - last[2], seq)
        return integration.motion.max_speed * seconds + WITNESS_TRANSLATION

    def reachable(self, last: Placed | None, pose: Transform2D, seq: int, stamp: float) -> bool:
        """Whether the robot can have driven to ``pose`` (epoch frame) since its ``last`` placed scan:
        no farther than ``max_speed`` allows, and, once its velocity is known, no farther from where
        that velocity takes it than ``max_acceleration`` allows (plus ``WITNESS_TRANSLATION`` for the
        fits' own error). Physics, not a pose: a look-alike corridor matches well, but a robot
        driving at 1.5 m/s is not 1.4 m on 0.4 s later."""
        integration = self.config.integration
        if last is None:
            return True
        seconds = self.clock.elapsed(stamp - last[0], seq - last[2], seq)
        margin = WITNESS_TRANSLATION
        if integration.motion.max_speed > 0 and math.hypot(pose.x - last[1].x, pose.y - last[1].y) > (
            integration.motion.max_speed * seconds + margin
        ):
            return False
        if integration.motion.max_acceleration > 0 and self.velocity_known:
            v = self.velocity * seconds
            expected = last[1].compose(Transform2D(float(v[0]), float(v[1]), float(v[2])))
            off = math.hypot(pose.x - expected.x, pose.y - expected.y)
            return off <= 0.5 * integration.motion.max_acceleration * seconds * seconds + margin
        return True

    def judge_placed(
        self,
        before: Transform2D | None,
        after: Transform2D | None,
        anchor: tuple[Transform2D, Transform2D] | None,
        spread: bool,
        odometry: Transform2D | None,
    ) -> None:
        """The step just placed, from ``before`` to ``after``, measures the odometry's misfit
        (:meth:`measure_misfit`) and judges its sign (:meth:`judge_odometry_sign`) where the step
        is a measurement: a reading spread within a burst is a guess between two readings (a turn
        in place spread as a share of the burst's drive reads as a step forward the walls did not
        see, or a stop), so only a reading taken where its scan was is judged, from the last such
        scan as placed (``anchor``: its pose and reading) when spread ones came between."""
        if before is None or after is None or not self.exact:
            return
        if not spread:
            self.measure_misfit(before.inverse().compose(after))
            self.judge_odometry_sign(before.inverse().compose(after))
        elif anchor is not None and odometry is not None:
            at, reading = anchor
            measured = from_odometry(reading.inverse().compose(odometry))
            self.judge_odometry_sign(at.inverse().compose(after), measured)

    def judge_odometry_sign(self, moved: Transform2D, step: Prediction | None = None) -> None:
        """Update the belief that the odometry's translation has lost its sign, from the motion the
        scan was placed with: a two-state hidden Markov model (the wheels' speed signed, or not),
        filtered forward (Rabiner 1989, the forward algorithm). Each state predicts the increment
        (the odometry's, or its translation negated, its turn kept), with the odometry's own
        uncertainty. Some logs' odometry adds up the wheels' speed without its sign, so reversing it
        drives forward (fr079's, and the corrected log made from it, which carries no speed to
        tell: 103 of its 4,790 steps); along a corridor the walls cannot say which way the robot
        went, and the odometry's prior decides. A robot changes its direction of travel only
        through standing still: at a step the odometry cannot tell from standing still (within
        ``ODOMETRY_TRANSLATION_SIGMA``) the sign may turn, with the chance the robot's own stops
        give (:meth:`_stop`), and the next steps' evidence decides; while the robot moves, the
        belief holds unless a step only the other state explains turns it by a likelihood ratio
        over 1e9. A step neither state explains (the chi-square
        validation gate) says nothing of the sign. Where the odometry keeps its sign the signed
        state predicts the motion and holds (docs/decisions/009-clocks-evidence-over-stamps.md).
        ``step``: the odometry's increment over the step ``moved`` spans, when it is not the last
        scan's (:attr:`odometry_step`)."""
        step = self.odometry_step if step is None else step
        if step is None:
            return
        signed = step.increment
        if math.hypot(signed.x, signed.y) < ODOMETRY_TRANSLATION_SIGMA:
            if not self._stopped:
                self._stop()
            return
        self._stopped = False
        unsigned = Transform2D(-signed.x, -signed.y, signed.theta)
        d_signed, d_unsigned = step.distance2(signed, moved), step.distance2(unsigned, moved)
        low = min(d_signed, d_unsigned)  # likelihoods relative to the likelier state's
        if low > CHI2_3DOF_99:
            return  # neither state explains the step (the validation gate): the odometry is off otherwise
        l_signed, l_unsigned = math.exp(-0.5 * (d_signed - low)), math.exp(-0.5 * (d_unsigned - low))
        # a belief held while moving is never quite certain: a step that only the other state
        # explains, by a likelihood ratio over 1e9, still turns it (a sparse log's robot can stop
        # and reverse between two scans)
        b = min(max(self.reversed_odometry, 1e-9), 1.0 - 1e-9)
        self.reversed_odometry = b * l_unsigned / (b * l_unsigned + (1.0 - b) * l_signed)

    def _stop(self) -> None:
        """The robot stopped: the sign may turn here, with the chance its own stops so far give. The
        hidden Markov model's transition at a stop is learned as Baum-Welch learns one, from the
        expected number of stops that turned the sign (the belief as the robot reached the last stop
        against the belief as it reaches this one), with Laplace's rule of
        succession as its prior (Rabiner 1989, Section III.C): a robot's first stop leaves either
        sign as likely; a robot whose stops never turned its sign soon takes one weak step after a
        stop for what it is (aces cut in 4: a ratio of 3 turned robot 3's prediction round), while
        one that reverses at its stops (freiburg-079-corrected) keeps the chance high."""
        self._stopped = True
        b = self.reversed_odometry
        if self._belief_at_stop is not None:
            a = self._belief_at_stop
            self.turns += a * (1.0 - b) + (1.0 - a) * b
            self.stops += 1.0
        self._belief_at_stop = b
        chance = (self.turns + 1.0) / (self.stops + 2.0)
        self.reversed_odometry = b * (1.0 - chance) + (1.0 - b) * chance


def within_gate(placed: Transform2D, predicted: Transform2D, prediction: Prediction) -> bool:
    """Whether a fit's pose ``placed`` lies within the 99 % validation gate of a ``prediction`` that
    put the scan at ``predicted`` (both in one frame): its squared Mahalanobis distance under the
    motion model's uncertainty within the chi-square bound of three degrees of freedom."""
    return prediction.distance2(predicted, placed) <= CHI2_3DOF_99


def explains(prediction: Prediction, last: Transform2D, placed: Transform2D) -> bool:
    """Whether the odometry's ``prediction`` from the robot's ``last`` pose explains a fit at
    ``placed`` (both in one frame): within its 99 % gate (:func:`within_gate`) for either sign of
    its translation (:meth:`Predictor.judge_odometry_sign`). The tracker asks it of the fit from
    where the robot stood (``fleetmap.agents.tracker._explained``): the wheels measure
    standing still as they measure a turn. At an epoch's first scans no typical fit bounds a poor
    one: the standing start found 1.8 m of wall 104 degrees from the 62-degree turn the wheels
    measured (csail-corrected cut in 8, robot 2's scan 53), and its first two scans came out
    104-111 degrees from the rest of its chain (25 wrong relations). Refused, the odometry's own
    fit, itself refused for the little wall it matched, carries the scan.

    The other motion models' fits are not asked: a real robot's odometry lags on a fast turn and
    then jumps, beyond its own gate (mit-csail, five scans of its first 400; asked of every fit,
    the log restamped in bursts moved 19 scans 0.42 m from its true clock's map)."""
    step = prediction.increment
    return any(
        within_gate(placed, last.compose(increment), prediction)
        for increment in (step, Transform2D(-step.x, -step.y, step.theta))
    )


def borne_out(
    prediction: Prediction,
    last: Transform2D,
    placed: Transform2D,
    returns: tuple[Array, Array, float],
    step_variance: tuple[float, float],
) -> bool:
    """Whether a fit at ``placed`` stands against the odometry's ``prediction`` from the robot's
    ``last`` pose (both in one frame): it lies within the 99 % gate (:func:`explains`), or the
    scan's returns bear it out. ``returns``: the scan before's and the scan's returns (each in
    its own laser frame) and the former's beam spacing; ``step_variance``: the odometry's step's
    own (:attr:`Predictor.step_variance`).

    A gate alone cannot tell a look-alike from odometry that is off: along campus's row of posts
    a metre apart the walls fitted a scan a post from where the wheels said (0.5-1.2 m), yet
    mit-csail's wheels stall, 0 m for a few scans, then read the whole way at once, and there the
    fit beyond the gate is right (docs/decisions/087). The returns decide between the two
    (:func:`~fleetmap.shared.core.pointstep.point_step`: every step of a window that holds both,
    scored by the two scans' points, the odometry's step as the prior): where the steps are alike
    to them (the posts repeat) the prior's side is the likelier, and where the returns measure
    the step (a stall) theirs is. The fit stands when the distribution's mode lies nearer it than
    the odometry's prediction, each by the prediction's own metric (docs/decisions/088)."""
    if explains(prediction, last, placed):
        return True
    reference, scan, angle_increment = returns
    variance_t, variance_r = step_variance
    measured = point_step(
        reference,
        scan,
        prediction.increment,
        math.sqrt(variance_t),
        math.sqrt(variance_r),
        angle_increment,
        covering=last.inverse().compose(placed),
    )
    if measured is None:
        return True
    mode = last.compose(measured.peak)
    return prediction.distance2(placed, mode) <= prediction.distance2(last.compose(prediction.increment), mode)
