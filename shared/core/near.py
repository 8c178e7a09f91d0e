"""Registration near a prediction: a submap's walls registered where the fleet already places it.

Where the pose graph predicts where a submap lies (the merger's placed submaps, a join's pairs),
the pose-free search is not needed: the walls are registered from the prediction, as the tracker
registers a scan (:func:`~fleetmap.shared.core.tracking.register`), and the result judged valid as an
integration is (:mod:`fleetmap.shared.core.validity`), with its transformation value.
"""

from __future__ import annotations

import time

import numpy as np
from fleetmap.shared.config import IntegrationParams, TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import (
    GridFreeSpace,
    Integration,
    _evaluated,
    _matches,
    check_map,
    exhausted,
    index_for,
)
from fleetmap.shared.core.mapgrid import MapIndex
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.tracking import MAX_ITERATIONS, SAMPLE_SPACING, ReferenceMap, register, sample_segments
from fleetmap.shared.core.transformation_value import prepare
from fleetmap.shared.core.validity import is_valid
from fleetmap.shared.core.work import Work, WorkExhausted

NEAR_PRIOR_TRANSLATION = 1.0
"""How far (m) registration near a prediction lets the prediction pull: loosely, so that the walls
decide ..."""
NEAR_PRIOR_ROTATION = 0.35
"""... and how far it turns (rad, 20 degrees)."""


def align_near(
    m1: SegmentMap,
    m2: SegmentMap,
    predicted: Transform2D,
    params: IntegrationParams,
    tracking: TrackingParams,
    reference1: ReferenceMap,
    index1: MapIndex | None = None,
    index2: MapIndex | None = None,
    work: Work | None = None,
) -> Integration:
    """S2 on S1 where it is expected to be (fleetmap): the walls of S2 registered on S1's from
    ``predicted`` (robust point-to-line ICP, :func:`fleetmap.shared.core.tracking.register`), then valued
    as :func:`integrate` values its best transformation: the paper's transformation value
    (Algorithm 4), the wall put in the other map's seen free space, and the validity rule, with no
    rival (a prediction names one place; the search near it finds the walls there or fails).

    This is the constraint search of production back ends (Cartographer's constraint builder)
    for a robot the fleet has placed: its tracking says where its new submap lies among the others,
    so the pose-free search, a hundred times the cost, is needed only for robots nobody has placed.
    ``reference1`` is S1's registration grid (:class:`fleetmap.shared.core.tracking.ReferenceMap`);
    ``work`` bounds the cost as for :func:`integrate` (the registration is charged its most
    iterations, each a lookup per sample point)."""
    check_map(m1, "S1")
    check_map(m2, "S2")
    work = Work() if work is None else work
    start = time.perf_counter()
    try:
        return _align_near(m1, m2, predicted, params, tracking, reference1, index1, index2, work, start)
    except WorkExhausted:
        return exhausted(start, work)


def _align_near(
    m1: SegmentMap,
    m2: SegmentMap,
    predicted: Transform2D,
    params: IntegrationParams,
    tracking: TrackingParams,
    reference1: ReferenceMap,
    index1: MapIndex | None,
    index2: MapIndex | None,
    work: Work,
    start: float,
) -> Integration:
    samples = sample_segments(m2.segments, SAMPLE_SPACING)
    near_t, near_r = NEAR_PRIOR_TRANSLATION, NEAR_PRIOR_ROTATION
    loose = np.diag([1.0 / near_t**2, 1.0 / near_t**2, 1.0 / near_r**2])
    work.charge(len(samples) * MAX_ITERATIONS)
    reg = register(samples, reference1, predicted, predicted, loose, tracking)
    t = reg.pose
    prep = prepare(m1.segments, m2.segments, m1.oriented and m2.oriented, params, m1.ordered, m2.ordered, work)
    i1 = index1 if index1 is not None else index_for(m1, params)
    i2 = index2 if index2 is not None else index_for(m2, params)
    free = GridFreeSpace(i1, i2, work)
    choice = _evaluated(prep, free, t, 0, params)
    violation = choice.value - choice.score
    solid = float(free.violation(t.as_array(), solid=True)[0]) if free.active and choice.value > 0 else violation
    valid = is_valid(choice.value, violation, 0.0, m1, m2, params, large=True, solid_violation=solid)
    matches = _matches(prep, t, params) if choice.value > 0 else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    return Integration(
        transform=t,
        value=choice.value,
        valid=valid,
        seconds=time.perf_counter() - start,
        candidates=1,
        heuristic="near",
        violation=violation,
        solid_violation=solid,
        matches=matches,
        work=work.spent,
    )
