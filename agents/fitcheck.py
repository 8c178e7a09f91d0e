"""Whether a scan's fit on its submap is good, and what the walls say against a fit that is not:
the tracker's fit check and its evidence of a kidnap (:mod:`fleetmap.agents.tracker`, steps 3 and
6 of its walk-through).

A fit is good when enough of the scan's walls lie on the submap's (:data:`MIN_MATCHED_SHARE`,
:data:`MIN_MATCHED_LENGTH`) and the scan's beams pass through little of the submap's walls
(:data:`MAX_SEE_THROUGH`: a laser does not see through walls). A refused fit is *contradicted* when
the scan and the submap disagree on space both saw at its pose (:func:`contradicts`): the walls say
the scan was not taken there. A fit refused only for the little wall it matched says nothing of
where the scan was taken: the tracker carries the robot by its motion model instead. Contradicted
scans are held until one fits again or ``kidnap_after`` of them make a new epoch
(docs/decisions/009-clocks-evidence-over-stamps.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from fleetmap.agents.submap import Submap
from fleetmap.shared.core.correlative import window_support
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_scalar
from fleetmap.shared.core.motion import CHI2_1DOF_99, Prediction
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.tracking import (
    MAX_CORRESPONDENCE,
    MIN_CORRESPONDENCE,
    REACH_ROTATION,
    SEE_THROUGH,
    Registration,
    ScanSamples,
    beam_evidence,
    see_through,
    wall_evidence,
)

WINDOW_STARTS = 3
"""The best-supported positions of a wide prediction's window, apart by registration's reach, that
are registered (:func:`window_fit`). Without odometry (short relations within 0.10 m,
2 deg): 1: orebro-c 57.3 %, freiburg-101-c 92.9 %, aces-c 67.8 %; 3: 60.3, 94.2, 72.2 %; 6: 63.2,
92.9, 70.0 % at half as much again of the time."""

MIN_MATCHED_SHARE = 0.3
"""A fit is good only if at least this share of the scan's wall length lies on the submap's walls ..."""
MIN_MATCHED_LENGTH = 1.0
"""... and at least this much of it (m; also how much wall in dispute refuses a fit) ..."""
MAX_SEE_THROUGH = 0.5
"""... and the scan's beams pass through at most this share of the submap wall they could have seen:
a laser cannot see through a wall (docs/decisions/009-clocks-evidence-over-stamps.md)."""
TYPICAL_SCORE_SHARE = 0.5
"""A fit scoring below this share of the robot's recent fits' median is checked against the other
motion models and pose-free integration, and the best taken; a later start's fit must score over
its inverse times as much to replace the first's."""


def typical_floor(scores: Iterable[float]) -> float:
    """The score below which a fit is not typical of the robot's recent ones, ``scores``
    (:data:`TYPICAL_SCORE_SHARE` of their median; none below three of them)."""
    recent = list(scores)
    return TYPICAL_SCORE_SHARE * float(np.median(recent)) if len(recent) >= 3 else 0.0


KIDNAP_REASON = (
    "{n} scans that the submap's walls contradict fit neither the submap nor, by pose-free "
    "integration, anywhere near it"
)
"""The reason of an epoch started by lost tracking (EpochLink.reason and the event's detail)."""


@dataclass(frozen=True)
class Fit:
    """A scan's registration on the matching submap, and the check's verdict on it."""

    registration: Registration
    good: bool
    why: str
    contradicted: bool = False
    """The scan and the submap disagree on space both saw at this fit's pose (:func:`judge`): the
    walls say the scan was not taken there. A fit refused only for the little wall it matched says
    nothing of where the scan was taken."""
    disputed: bool = False
    """The scan and the submap disagree at this pose on at least as much wall as it takes to place a
    scan, whatever they agree on."""
    everywhere: bool = False
    """(A refused scan's first fit) the walls dispute every start tried, not only this one."""
    beams: tuple[float, float] | None = None
    """(A good fit a window search weighs: :func:`weighed`) the submap's wall (m) the scan's beams
    pass through at this pose and the wall they return from
    (:func:`~fleetmap.shared.core.tracking.beam_evidence`)."""
    spread: Array | None = None
    """(A fit chosen from a window of several good minima: :func:`window_fit`) their covariance
    about this one (the submap's frame): how far the walls leave the choice open."""


def judge(
    reg: Registration,
    scan: RangeScan,
    segments: Array,
    submap: Submap,
    max_range: float,
    track_drift: tuple[float, float],
) -> Fit:
    """The fit check's verdict on a registration: good or why not ("" when it is), and whether the
    walls contradict it. The walls' evidence alone: how far the robot can have driven does not
    judge a registration started near the prediction (the clock may be wrong; the walls are not):
    it bounds only where the pose-free search looks (:meth:`fleetmap.agents.tracker.Tracker.add`,
    step 4).

    For a refused fit, also what the walls say against it (:func:`contradicts`): too little of
    the scan on the submap's walls says only that they cannot place it (open space, a few
    metres of wall, new walls, a person in front of the laser)."""
    through, visible = see_through(submap.reference, scan, reg.pose, max_range)
    seen_through = visible > 0 and through > MAX_SEE_THROUGH * visible
    if reg.matched_length >= MIN_MATCHED_LENGTH and reg.matched_share >= MIN_MATCHED_SHARE:
        if not seen_through:
            return Fit(reg, True, "")
        why = f"its beams pass through {through:.1f} of {visible:.1f} m of the submap's walls"
    else:
        why = f"{reg.matched_length:.1f} m ({100 * reg.matched_share:.0f} %) of the scan on the submap's walls"
    contradicted, disputed = contradicts(reg, scan, segments, submap, max_range, track_drift)
    return Fit(reg, False, why, contradicted, disputed)


def contradicts(
    reg: Registration,
    scan: RangeScan,
    segments: Array,
    submap: Submap,
    max_range: float,
    track_drift: tuple[float, float],
) -> tuple[bool, bool]:
    """Whether the scan and the submap disagree on space both saw at the fit's pose: *contradicted*
    (more wall in dispute than agreed on) and *disputed* (at least as much wall in dispute as it
    takes to place a scan, :data:`MIN_MATCHED_LENGTH`, whatever is agreed on). In dispute are the
    submap's walls the scan's beams pass through (against those they return from: a return
    short of a wall is something in between, none at all a failure, one beyond it a wrong pose;
    the beam model, Thrun, Burgard & Fox 2005, 6.3), and the scan's walls where the submap's
    own scans saw through more than they saw (the rule that judges a submap's walls,
    :func:`wall_evidence`; against the scan's wall matched). The beam test's margin grows by
    the uncertainty of the track the robot is carried on (``track_drift``, 99 %, one degree of
    freedom along the beam): a carried pose a metre off sees through walls it did not pass."""
    margin = beam_margin(track_drift)
    through, hit = beam_evidence(submap.reference, scan, reg.pose, max_range, margin)
    in_free_space = 0.0
    if submap.scans_in:
        walls = reg.pose.apply(segments)
        seen, passed = wall_evidence(walls, submap.scans_in, max_range, max_range, margin)
        length = np.hypot(walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1])
        in_free_space = float(length[passed > seen].sum())
    enough = MIN_MATCHED_LENGTH
    contradicted = (through >= enough and through > hit) or (
        in_free_space >= enough and in_free_space > reg.matched_length
    )
    return contradicted, through >= enough or in_free_space >= enough


def beam_margin(track_drift: tuple[float, float]) -> tuple[float, float]:
    """The beam test's margin (:data:`~fleetmap.shared.core.tracking.SEE_THROUGH`) grown by the
    uncertainty of the track the robot is carried on (``track_drift``, its variances along and
    across; 99 %, one degree of freedom along the beam): a carried pose a metre off sees through
    walls it did not pass."""
    if track_drift == (0.0, 0.0):
        return SEE_THROUGH
    z = math.sqrt(CHI2_1DOF_99)
    return (SEE_THROUGH[0] + z * math.sqrt(track_drift[0]), SEE_THROUGH[1] + z * math.sqrt(track_drift[1]))


def best_fit(fits: list[Fit], apart: bool, priors: list[Prediction] | None = None) -> Fit | None:
    """The best good fit of one scan from several starts (the first prediction's first): a later
    fit replaces an earlier one only if it scores over ``1 / TYPICAL_SCORE_SHARE`` times as much,
    except that the two motion models' fits (``apart``: they disagree on the heading) weigh alike
    by score, and so do the fits of the models left when the first prediction's fit was refused
    (``priors``: each fit's motion model), where the later one's is as sure as the best's so far.
    The margin is the believed model's prior: the first prediction is the model the robot goes
    by. Once the walls refuse its fit, constant velocity and standing still are each a guess as
    wide as the other (on a sparse log both 1.5 m and 177 degrees), and which of them was tried
    first says nothing: freiburg-campus-corrected scan 1168, whose odometry read 13 degrees of a
    4-degree turn, was placed by constant velocity 0.85 m off, its fit scoring half the fit near
    where the robot stood (record 044)."""
    best, chosen = None, 0
    for n, fit in enumerate(fits):
        # the two motion models' fits weigh alike by score, unless they turn alike and lie
        # beyond registration's reach of each other: two minima of one heading, apart along
        # what the walls leave free, where the scores cannot tell them apart and the first
        # prediction's stands as any other's does (down a corridor logged a scan a metre, the
        # better-scoring of two such fits lay 1.3-1.5 m along it: aces-corrected scans 26, 49,
        # 318; two fits within reach are one minimum found better, mit-csail's fast turns)
        settled = apart and n == 1 and not minima_along(fit.registration.pose, fits[0].registration.pose)
        fallback = priors is not None and chosen > 0 and _as_sure(priors[n], priors[chosen])
        margin = 1.0 if settled or fallback else TYPICAL_SCORE_SHARE
        if fit.good and (best is None or fit.registration.score * margin >= best.registration.score):
            best, chosen = fit, n
    return best


def _as_sure(challenger: Prediction, best: Prediction) -> bool:
    """Whether a fit's motion model is as sure of the step as the best fit's so far, in both
    translation and heading: then neither prior outweighs the other, and the walls' score decides."""
    return challenger.sigma_translation <= best.sigma_translation and challenger.sigma_rotation <= best.sigma_rotation


def minima_along(a: Transform2D, b: Transform2D) -> bool:
    """Whether two fits of one scan are two minima of one heading: they turn alike (within
    :data:`REACH_ROTATION`) and lie beyond registration's reach of each other (:func:`same_start`)."""
    return a.distance(b)[1] <= REACH_ROTATION and not same_start(a, b)


def same_start(a: Transform2D, b: Transform2D) -> bool:
    """Whether registering from ``a`` only repeats registering from ``b``: they lie within
    registration's reach of each other (``MAX_CORRESPONDENCE``, :data:`REACH_ROTATION`). Not the
    motion model's uncertainty: on a fast turn the odometry's is 20 degrees, and a velocity
    prediction 14 degrees from it starts a registration the odometry's could not (mit-csail)."""
    d, r = a.distance(b)
    return d <= MAX_CORRESPONDENCE and r <= REACH_ROTATION


def turned_fits(
    mean: Transform2D,
    sigma_rotation: float,
    floor: float,
    tried: list[Transform2D],
    registered: Callable[[Transform2D], Fit],
) -> list[Fit]:
    """Fits ``registered`` from starts turned about the prediction's ``mean`` (the submap's frame)
    across its heading uncertainty (``sigma_rotation``), nearest first, each start not ``tried``
    yet (and added to it), up to the first good one scoring ``floor`` or more (typical). A
    registration settles within :data:`REACH_ROTATION` of its start, so a prediction less sure
    of its heading than that leaves the rest unsearched; the starts, ``2 REACH_ROTATION`` apart
    over two sigma either side (95 % of the prior), search it as a correlative matcher searches
    its prior's window (Olson, ICRA 2009). The prior stays the prediction's. The cases: a
    burst's spread reading inside an uneven turn, 14 degrees short of a 29-degree step a metre
    long (acapulco-corrected, scan 115), whose registration settled in a wrong minimum; the
    robot was carried on that heading, and the submap it built turned the map. And an odometry
    reading 8 degrees off with a sigma of 7 (freiburg-079-corrected, scan 4386): one sigma left
    no start to search, and an atypical fit 10 degrees off was taken (record 015)."""
    step = 2.0 * REACH_ROTATION
    fits: list[Fit] = []
    for k in range(1, int(min(2.0 * sigma_rotation, math.pi) / step) + 1):
        for turn in (k * step, -k * step):
            start = Transform2D(mean.x, mean.y, mean.theta + turn)
            if any(same_start(start, other) for other in tried):
                continue
            tried.append(start)
            fits.append(registered(start))
            if fits[-1].good and fits[-1].registration.score >= floor:
                return fits
    return fits


def window_fit(
    best: Fit,
    submap: Submap,
    samples: ScanSamples,
    mean: Transform2D,
    radius: float,
    prediction: Prediction,
    registered: Callable[[Transform2D], Fit],
    seeds: Sequence[Transform2D] = (),
) -> Fit:
    """The good fit of ``best`` and those ``registered`` from the best-supported positions of the
    prediction's window whose score, weighed by the prediction (:func:`weighed`), is highest: the
    window is ``radius`` around the prediction's ``mean`` (the submap's frame),
    scored every :data:`MIN_CORRESPONDENCE` at the heading the walls gave ``best``
    (:func:`~fleetmap.shared.core.correlative.window_support`), registered from its
    :data:`WINDOW_STARTS` best positions apart by registration's reach (:func:`same_start`), and
    first from each of the ``seeds`` (where another search put the scan; each registered, however
    near the others).

    A prediction that measures nothing (constant velocity over a second between scans of a log
    without odometry: 1.5 m and 177 degrees) picks one minimum of many, the nearest to a guess; a
    correlative matcher searches its prior's window and refines its best pose (Olson, ICRA 2009).
    Down a corridor logged a scan a metre, the prediction's fit lay 1-3 m short of where the robot
    was while the fit there supported the scan 1.5-3 times as well (orebro-corrected, scans 26-37;
    docs/decisions/017-a-prior-that-measures-nothing-is-searched.md).

    The search finds the walls' minima; the prediction still weighs them. Along a corridor whose
    doors repeat every two metres, two minima support the scan alike (9.28 and 9.30 m of wall:
    orebro-corrected, scan 111), and the better score alone moved the robot two metres back at
    every other scan (docs/decisions/023-the-window-weighed-by-its-prior.md).

    The window's support counts the scan's points near the submap's walls, and a scan placed short
    of where it was taken overlaps more of what the submap has seen: on a robot's second scan, one
    submap of one scan, every best-supported position lay behind the robot (orebro-corrected
    scan 151, 1.2 m on: support 10.4 at 0.75 m back, 9.3 where it was), and the fit registered from
    them 1.8 m back was taken, 3 m off. The scan pair's integration, though ambiguous, put it
    0.09 m from the truth, and registered from there it fits better (7.0 against 5.9, no beam
    through a wall): that start is a seed (docs/decisions/069)."""
    center = Transform2D(mean.x, mean.y, best.registration.pose.theta)
    positions, support = window_support(
        submap.reference, samples, center, radius, MIN_CORRESPONDENCE, MIN_CORRESPONDENCE
    )
    tried = [best.registration.pose]
    goods = [best]

    def register(start: Transform2D) -> None:
        nonlocal best
        tried.append(start)
        fit = registered(start)
        if fit.good and not any(same_start(fit.registration.pose, g.registration.pose) for g in goods):
            goods.append(fit)
        if fit.good and weighed(fit, mean, prediction) > weighed(best, mean, prediction):
            best = fit

    for seed in seeds:  # (each registered, however near a start already tried)
        register(seed)
    searched = 0
    for k in np.argsort(-support, kind="stable").tolist():
        start = Transform2D(float(positions[k, 0]), float(positions[k, 1]), center.theta)
        if any(same_start(start, other) for other in tried):
            continue
        if searched == WINDOW_STARTS:
            break
        searched += 1
        register(start)
    if len(goods) < 2:
        return best
    return replace(best, spread=minima_spread(best, goods, [weighed(g, mean, prediction) for g in goods]))


def swept_fit(
    best: Fit | None,
    submap: Submap,
    samples: ScanSamples,
    mean: Transform2D,
    radius: float,
    prediction: Prediction,
    registered: Callable[[Transform2D], Fit],
) -> Fit | None:
    """:func:`window_fit` over headings too: ``best`` (None: no good fit yet) or the better good
    fit, weighed by the prediction (:func:`weighed`), registered from the poses of the window
    ``radius`` around the prediction's ``mean``, at headings ``2 REACH_ROTATION`` apart across two sigma of its heading
    either side, whose support times the prediction's Gaussian is at least ``TYPICAL_SCORE_SHARE``
    of the best pose's (each apart from the others by registration's reach). For a fit found from
    a turned start alone where the prediction knows the heading no better than the position
    (constant velocity over a sparse log's second: 177 degrees): turned starts at the predicted
    position reach only what lies within registration's reach of it, and a turn that also
    carried the robot a metre aside is left unsearched. The real-time correlative matcher
    searches rotations as it searches translations (Olson, ICRA 2009, Section III-A;
    Cartographer's ``RealTimeCorrelativeScanMatcher2D``).
    orebro-corrected, scan 216: 1.9 m on and 24 degrees round, where the corrected pose's fit
    scores 2.6; from starts turned at the prediction the best was 128 degrees off (docs/decisions/062)."""
    step = 2.0 * REACH_ROTATION
    turns = int(min(2.0 * prediction.sigma_rotation, math.pi) / step)
    information = prediction.information()
    c, s = math.cos(mean.theta), math.sin(mean.theta)
    poses, weights = [], []
    for k in range(-turns, turns + 1):
        if k * step <= -math.pi + 1e-9:
            continue  # (a full turn: the same heading as the last)
        center = Transform2D(mean.x, mean.y, mean.theta + k * step)
        positions, support = window_support(
            submap.reference, samples, center, radius, MIN_CORRESPONDENCE, MIN_CORRESPONDENCE
        )
        # each position's support times the prediction's Gaussian there (its frame: the mean's)
        dx, dy = positions[:, 0] - mean.x, positions[:, 1] - mean.y
        off = np.column_stack([c * dx + s * dy, -s * dx + c * dy, np.full(len(positions), wrap_scalar(k * step))])
        poses += [(x, y, center.theta) for x, y in positions.tolist()]
        weights.append(support * np.exp(-0.5 * np.einsum("ij,jk,ik->i", off, information, off)))
    weight = np.concatenate(weights) if weights else np.zeros(0)
    tried = [] if best is None else [best.registration.pose]
    for n in np.argsort(-weight, kind="stable").tolist():
        if weight[n] < TYPICAL_SCORE_SHARE * weight.max():
            break  # (the rest the walls and the prediction support less than half as well as the best)
        start = Transform2D(*poses[n])
        if any(same_start(start, other) for other in tried):
            continue
        tried.append(start)
        fit = registered(start)
        if fit.good and (best is None or weighed(fit, mean, prediction) > weighed(best, mean, prediction)):
            best = fit
    return best


def minima_spread(chosen: Fit, fits: list[Fit], weights: list[float]) -> Array:
    """The covariance about ``chosen`` of the window's good minima ``fits``, each weighed as the
    search weighed it (its posterior: :func:`weighed`). The correlative matcher's covariance is the
    moment of its whole posterior over the window, not the curvature at its peak (Olson, ICRA
    2009, Section III-C): along a corridor whose doors repeat, each minimum is as sharp as the
    right one, and the choice between them is what is uncertain (docs/decisions/048)."""
    w = np.asarray(weights, dtype=np.float64)
    if w.sum() <= 0.0:
        w = np.ones(len(fits))  # (the walls refute every one: as open as each other)
    c = chosen.registration.pose
    d = np.array(
        [
            [f.registration.pose.x - c.x, f.registration.pose.y - c.y, wrap_scalar(f.registration.pose.theta - c.theta)]
            for f in fits
        ]
    )
    return (d * (w / w.sum())[:, None]).T @ d


def weighed(fit: Fit, mean: Transform2D, prediction: Prediction) -> float:
    """A fit's score, times the share of the submap's wall its beams meet that they bear out (return
    from rather than pass through, :attr:`Fit.beams`), times the prediction's Gaussian at the fit's
    pose, ``exp(-d^2 / 2)`` with ``d`` its Mahalanobis distance from the prediction's ``mean`` under
    its uncertainty. The real-time correlative scan matcher's form (Olson, ICRA 2009, the
    posterior as the scan's likelihood times the motion prior; Cartographer's
    ``RealTimeCorrelativeScanMatcher2D`` weighs each candidate's score the same way), with the
    prediction's own uncertainty for its weights, and the beam model's negative information in the
    likelihood: a beam does not pass through a wall (Thrun, Burgard & Fox 2005, 6.3). Along a
    corridor a fit that slid short of the robot matches less of the scan and its beams pass
    through the walls ahead: orebro-corrected cut in four, scan 198, 1.4 m beyond a prediction
    1.55 m wide, the true fit scored 5.69 with no wall passed through, the fit 1.8 m short 3.99 with
    1.8 m of 10 passed through; weighed by score alone they tied (3.81 against 3.82), and the slid
    one was taken. A share, not the wall passed through taken off the score: outdoors and in
    clutter the right fit's beams also pass through metres of what the submap holds (trees,
    people, its own misplaced scans), and the difference decided against it (docs/decisions/063)."""
    if fit.beams is None:
        raise ValueError("a fit is weighed only with what its beams say (FitSearch._against)")
    through, hit = fit.beams
    share = hit / (hit + through) if hit + through > 0.0 else 1.0
    return fit.registration.score * share * math.exp(-0.5 * prediction.distance2(mean, fit.registration.pose))
