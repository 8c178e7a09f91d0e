"""INTEGRATE (paper III, Algorithm 1): the transformation of S2 on S1 from geometry alone.

1. Find transformations (Algorithm 2/3, :mod:`fleetmap.shared.core.candidates`).
2. Evaluate them and keep the best (Algorithm 4, :mod:`fleetmap.shared.core.transformation_value`), then refine
   the few best distinct ones by least squares (:mod:`fleetmap.shared.core.refine`) and keep the one
   with the highest transformation value.
3. Fuse S1 and S2^t (Algorithm 5, :mod:`fleetmap.shared.core.fusion`), on demand.

Validity (``valid``) is judged by :mod:`fleetmap.shared.core.validity`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from fleetmap.shared.config import HEURISTICS, IntegrationParams
from fleetmap.shared.core import mapgrid
from fleetmap.shared.core.candidates import IntArray
from fleetmap.shared.core.distinct import (
    AUTO_ORDER,
    Window,
    _also_by_value,
    _in_window,
    _pick_distinct,
    distinct_candidates,
    gather_candidates,
    settled_ahead,
)
from fleetmap.shared.core.geometry import Array, Transform2D, lengths
from fleetmap.shared.core.mapgrid import VIEWPOINTS, MapIndex, grid_scores, map_index, ranking_scores
from fleetmap.shared.core.ransac import ransac_align
from fleetmap.shared.core.refine import refine_transform
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.transformation_value import (
    PreparedPairs,
    matched_pairs,
    prepare,
    transformation_value,
    transformation_values,
)
from fleetmap.shared.core.validity import (
    clearly_different,
    is_valid,
    unrefuted,
)
from fleetmap.shared.core.visibility import FreeSpace
from fleetmap.shared.core.work import Work, WorkExhausted
from fleetmap.shared.errors import BadInput

MAX_SEARCH_SEGMENTS = 150
"""Maps with more segments are searched on their longest this many; the best transformations are
then refined and valued on the full maps (a bound on the search's cost, whatever the maps hold)."""
MAX_EVALUATED = 8000
"""At most this many distinct transformations are evaluated, the most supported first."""
SHORTLIST = 64
"""Candidates (best values first) whose free-space consistency is measured before the choice."""
REFINE = True
"""Refine the best transformations by least squares on the matched segment pairs (the value is flat
near the truth: the best candidate of an angle match is a little off; docs/decisions/006)."""
REFINE_CANDIDATES = 12
"""How many of the best distinct transformations are refined before the best is chosen ..."""
REFINE_FIRST_STEPS = 3
"""... each this many Gauss-Newton steps first ..."""
REFINE_KEEP = 0.6
"""... and further only if it scores at least this fraction of the best so far (a bound on the
refinement's cost)."""
ALSO_BY_VALUE = 4
"""Between scans, this many of the best-valued candidates are refined too, beside the best-scored:
147 of 160 consecutive real scan pairs right against 132 without, at 1.3 times the time (12: 151,
1.65 times; docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
REFINE_COARSE_FACTOR = 8.0
"""Those are refined first with POINTDISTANCETOLERANCE this many times larger (edmonton's first 30
consecutive pairs: 24 right, 22 without; docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
RIVALS = 8
"""An integration keeps this many of its best-scoring clearly different transformations (what the
merger's cycles and joins weigh against it; docs/decisions/002-pose-graph.md)."""
FREE_SPACE_MARGIN = 0.10
"""A wall point closer to a scan's sensor than the wall it saw, by more than this (m), lies in the
scan's seen free space (:mod:`fleetmap.shared.core.visibility`; docs/decisions/007)."""
MAP_FREE_SPACE_MIN_LENGTH = 0.0
"""Two partial maps: the free-space limit on the best counts only segments at least this long (m; 0:
every wall). Long walls only (0.8 m) merged more maps wrong on the corrected logs (14 against 5;
docs/decisions/005-parameters-beyond-the-paper.md)."""

FIRST_CHUNK = 256
"""The most supported candidates are evaluated in full first; their best score seeds the early stop."""


@dataclass(frozen=True)
class Integration:
    """The outcome of integrating S2 on S1: ``transform`` maps S2's frame into S1's."""

    transform: Transform2D
    value: float
    valid: bool
    seconds: float
    candidates: int
    """Distinct transformations evaluated (ransac: hypotheses whose supports were counted)."""
    heuristic: str
    """The heuristic whose transformation won (for auto: the one that found it first)."""
    violation: float = 0.0
    """Wall length (m) each map puts in the other's seen free space (scans only)."""
    solid_violation: float = 0.0
    """Between two partial maps, the part of ``violation`` that is evidence against the alignment,
    what the validity rule limits: the walls farther than ``map_free_space_clearance`` from the
    other map's walls (nearer, they are its walls, placed a little apart), of segments at least
    :data:`MAP_FREE_SPACE_MIN_LENGTH` long (clutter); ``violation`` otherwise. The rest still lowers
    the score."""
    runner_up: float = 0.0
    """Score of the best transformation clearly different from the chosen one (more than
    ``AMBIGUITY_TRANSLATION`` or ``AMBIGUITY_ROTATION`` away): close to the best's in a repetitive world."""
    matches: tuple[IntArray, IntArray] = field(repr=False, default=(np.zeros(0, np.int64), np.zeros(0, np.int64)))
    """Matched segment pairs (index in S1, index in S2) under ``transform``."""
    rivals: tuple[tuple[Transform2D, float], ...] = field(repr=False, default=())
    """The best few transformations clearly different from ``transform`` (as for ``runner_up``),
    with their scores, best first: where a repetitive world puts S2 too. Between two partial
    maps, only those the seen free space does not refute (:func:`~fleetmap.shared.core.validity.unrefuted`)."""
    work: int = 0
    """Units of work done (:mod:`fleetmap.shared.core.work`)."""
    exhausted: bool = False
    """The integration stopped at its work budget before it could judge an alignment: not valid,
    the identity with no value."""

    def to_json_dict(self) -> dict[str, float | bool]:
        return {
            "x": self.transform.x,
            "y": self.transform.y,
            "theta": self.transform.theta,
            "value": self.value,
            "valid": self.valid,
            "seconds": self.seconds,
        }


def check_map(m: SegmentMap, name: str) -> None:
    if len(m) == 0:
        raise BadInput(name, "the map is empty (no segments)")
    if not np.isfinite(m.segments).all():
        raise BadInput(name, "the map has NaN or infinite coordinates")
    if (lengths(m.segments) <= 0).any():
        raise BadInput(name, "the map has a zero-length segment")


def integrate(
    m1: SegmentMap,
    m2: SegmentMap,
    params: IntegrationParams | None = None,
    heuristic: str | None = None,
    index1: MapIndex | None = None,
    index2: MapIndex | None = None,
    window: Window | None = None,
    work: Work | None = None,
) -> Integration:
    """Integrate S2 on S1 (Algorithm 1, steps 1-2): the best transformation, its value and validity
    (with ``aligner`` ransac, the transformation is Ballesta et al.'s instead: :func:`_integrate_ransac`).

    The best transformation has the highest *score*: its transformation value minus the wall
    length it puts in the seen free space of the other map (:mod:`fleetmap.shared.core.visibility` for
    scans, :mod:`fleetmap.shared.core.mapgrid` for maps that carry viewpoints; zero for maps that carry
    none, so the score is the paper's value there).

    Large maps (more than :data:`MAX_SEARCH_SEGMENTS` segments) take fleetmap's large-map path (see
    :func:`_integrate_large`); ``index1``/``index2`` are their :func:`index_for` indexes when the
    caller keeps them (built here otherwise). With a ``window``, only the candidates inside it are
    valued (the best and its rivals alike). With ``work``, the integration stops once it has done
    ``work.limit`` units of work (:mod:`fleetmap.shared.core.work`) and is then ``exhausted``: not
    valid, whatever it had found.
    """
    p = params or IntegrationParams()
    h = heuristic or p.heuristic
    if h not in HEURISTICS:
        raise BadInput("heuristic", f"unknown heuristic {h!r} (known: {', '.join(HEURISTICS)})")
    check_map(m1, "S1")
    check_map(m2, "S2")
    work = Work() if work is None else work
    start = time.perf_counter()
    try:
        if p.aligner == "ransac":
            return _integrate_ransac(m1, m2, p, index1, index2, window, work)
        return _integrate_paper(m1, m2, h, p, index1, index2, window, work)
    except WorkExhausted:
        return exhausted(start, work)


def exhausted(start: float, work: Work) -> Integration:
    """What an integration that stopped at its work budget gives: nothing judged, not valid."""
    return Integration(
        transform=Transform2D.identity(),
        value=0.0,
        valid=False,
        seconds=time.perf_counter() - start,
        candidates=0,
        heuristic="",
        work=work.spent,
        exhausted=True,
    )


def _integrate_paper(
    m1: SegmentMap,
    m2: SegmentMap,
    h: str,
    p: IntegrationParams,
    index1: MapIndex | None,
    index2: MapIndex | None,
    window: Window | None,
    work: Work,
) -> Integration:
    """The paper's INTEGRATE (:func:`integrate`), the small-map or the large-map path."""
    start = time.perf_counter()
    large = takes_large_path(m1, m2, p)
    solid: float | None = None
    if large:
        # Large partial maps are searched on their longest segments; the choice is made on the full maps.
        search1, search2 = _longest(m1, MAX_SEARCH_SEGMENTS), _longest(m2, MAX_SEARCH_SEGMENTS)
        best, rivals, count, prep, solid = _integrate_large(
            m1, m2, search1, search2, h, p, index1, index2, window, work
        )
    else:
        best, rivals, count, prep = _integrate_small(m1, m2, h, p, window, work)
    runner_up = max((score for _, score in rivals), default=0.0)
    matches = _matches(prep, best.transform, p) if best.value > 0 else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    seconds = time.perf_counter() - start
    violation = best.value - best.score
    solid_violation = violation if solid is None else solid
    return Integration(
        transform=best.transform,
        value=best.value,
        valid=is_valid(best.value, violation, max(runner_up, 0.0), m1, m2, p, large, solid_violation),
        seconds=seconds,
        candidates=count,
        heuristic=AUTO_ORDER[best.label] if h == "auto" else h,
        violation=violation,
        solid_violation=solid_violation,
        runner_up=max(runner_up, 0.0),
        matches=matches,
        rivals=tuple(rivals),
        work=work.spent,
    )


def _integrate_ransac(
    m1: SegmentMap,
    m2: SegmentMap,
    p: IntegrationParams,
    index1: MapIndex | None,
    index2: MapIndex | None,
    window: Window | None,
    work: Work,
) -> Integration:
    """S2 on S1 by Ballesta et al.'s RANSAC over landmark correspondences
    (:mod:`fleetmap.shared.core.ransac`), its transformation refined on the walls and valued and
    judged as :func:`integrate` values and judges its own: the paper's transformation value, the wall
    put in the other map's seen free space, the validity rule, whose rivals are RANSAC's next
    hypotheses clearly different from the best. An independent search, the same verdict. Its
    work is counted from the valuing on (RANSAC's own draws are bounded by
    ``ITERATIONS``)."""
    start = time.perf_counter()
    found = ransac_align(m1.segments, m2.segments, p, None if window is None else window.contains)
    large = takes_large_path(m1, m2, p)
    prep = prepare(m1.segments, m2.segments, m1.oriented and m2.oriented, p, m1.ordered, m2.ordered, work)
    free: FreeSpace | GridFreeSpace
    if large:
        i1 = index1 if index1 is not None else index_for(m1, p)
        i2 = index2 if index2 is not None else index_for(m2, p)
        free = GridFreeSpace(i1, i2, work)
    else:
        free = FreeSpace(m1.segments, m2.segments, m1.ordered, m2.ordered, FREE_SPACE_MARGIN)
    refuse = not (large and free.active)
    best = _Choice(Transform2D.identity(), 0.0, 0.0, 0)
    rivals: list[tuple[Transform2D, float]] = []
    if found.supports:
        best = _evaluated(prep, free, found.transform, 0, p)
        if REFINE:
            # Landmarks place S2 within their support distance: refined coarse first, as a candidate
            # picked by its value alone is (the right transformation's walls may lie beyond the
            # paper's matching reach).
            best = _refined(prep, free, replace(best, coarse=True), p, 12, refuse)
        if best.score <= 0:
            best = _Choice(Transform2D.identity(), 0.0, 0.0, 0)
    if best.value > 0 and found.others:
        centre = _overlap_centre(prep, best.transform, p) if large else None
        hypotheses = np.array([t.as_array() for t, _ in found.others])
        open_ = clearly_different(best.transform, centre)(hypotheses)
        while open_.any() and len(rivals) < RIVALS:
            other = _evaluated(prep, free, Transform2D.from_array(hypotheses[int(np.argmax(open_))]), 0, p)
            rivals.append((other.transform, other.score))
            open_ &= clearly_different(other.transform, centre)(hypotheses)
    rivals = _best_rivals(rivals, p)
    runner_up = max((score for _, score in rivals), default=0.0)
    violation = best.value - best.score
    solid = violation
    limited = MAP_FREE_SPACE_MIN_LENGTH > 0 or p.validity.map_free_space_clearance > 0
    maps = not (m1.ordered or m2.ordered)
    if limited and maps and isinstance(free, GridFreeSpace) and free.active and best.value > 0:
        solid = float(free.violation(best.transform.as_array(), solid=True)[0])
    matches = _matches(prep, best.transform, p) if best.value > 0 else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    return Integration(
        transform=best.transform,
        value=best.value,
        valid=is_valid(best.value, violation, runner_up, m1, m2, p, large, solid),
        seconds=time.perf_counter() - start,
        candidates=found.hypotheses,
        heuristic="ransac",
        violation=violation,
        solid_violation=solid,
        runner_up=runner_up,
        matches=matches,
        rivals=tuple(rivals),
        work=work.spent,
    )


def takes_large_path(m1: SegmentMap, m2: SegmentMap, p: IntegrationParams) -> bool:
    """Whether :func:`integrate` takes the large-map path: a map has more than
    :data:`MAX_SEARCH_SEGMENTS` segments, or carries viewpoints (then it is judged by its free space)."""
    limit = MAX_SEARCH_SEGMENTS
    return any((limit > 0 and len(m) > limit) or VIEWPOINTS in m.extras for m in (m1, m2))


def _integrate_small(
    m1: SegmentMap, m2: SegmentMap, h: str, p: IntegrationParams, window: Window | None, work: Work
) -> tuple[_Choice, list[tuple[Transform2D, float]], int, PreparedPairs]:
    """Scans and small maps: every candidate valued by Algorithm 4 (with the early stop)."""
    oriented = m1.oriented and m2.oriented
    prep = prepare(m1.segments, m2.segments, oriented, p, m1.ordered, m2.ordered, work)
    free = FreeSpace(m1.segments, m2.segments, m1.ordered, m2.ordered, FREE_SPACE_MARGIN)
    raw, labels = gather_candidates(m1, m2, h, p)
    cand, labels = _in_window(*distinct_candidates(raw, labels, p), window)
    if 0 < MAX_EVALUATED < len(cand):
        cand, labels = cand[:MAX_EVALUATED], labels[:MAX_EVALUATED]  # the most supported
    best = _Choice(Transform2D.identity(), 0.0, 0.0, AUTO_ORDER.index(h) if h != "auto" else 0)
    rivals: list[tuple[Transform2D, float]] = []
    if len(cand):
        values = np.full(len(cand), -1.0)
        head = slice(0, min(FIRST_CHUNK, len(cand)))
        values[head] = transformation_values(prep, cand[head], p)
        head_best = _shortlist_scores(cand[head], values[head], free)
        if len(cand) > FIRST_CHUNK:
            known = float(head_best.max()) if len(head_best) else 0.0
            values[FIRST_CHUNK:] = transformation_values(prep, cand[FIRST_CHUNK:], p, best_known=max(known, 0.0))
        shortlist = np.argsort(-values, kind="stable")[:SHORTLIST]
        shortlist = shortlist[values[shortlist] > 0]
        scores = values[shortlist] - free.violation(cand[shortlist]) if free.active else values[shortlist]
        k = max(1, REFINE_CANDIDATES) if REFINE else 1
        picked = _pick_distinct(cand[shortlist], scores, k, p)
        by_score = len(picked)
        if REFINE and free.active:
            picked += _also_by_value(cand[shortlist], values[shortlist], picked, ALSO_BY_VALUE, p)
        finals = [
            _Choice(
                Transform2D.from_array(cand[shortlist[j]]),
                float(values[shortlist[j]]),
                float(scores[j]),
                int(labels[shortlist[j]]),
                coarse=n >= by_score,
            )
            for n, j in enumerate(picked)
        ]
        best, rivals, centre = _choose(prep, free, finals, p, True)
        # The clearly different candidates that were not refined count too.
        others = np.flatnonzero(clearly_different(best.transform, centre)(cand[shortlist]))
        rivals += [(Transform2D.from_array(cand[shortlist[j]]), float(scores[j])) for j in others]
    return best, _best_rivals(rivals, p), len(cand), prep


GRID_FINE = 1024
"""Large-map path: candidates with the best coarse grid scores that get the fine grid score."""


def _integrate_large(
    m1: SegmentMap,
    m2: SegmentMap,
    search1: SegmentMap,
    search2: SegmentMap,
    h: str,
    p: IntegrationParams,
    index1: MapIndex | None,
    index2: MapIndex | None,
    window: Window | None,
    work: Work,
) -> tuple[_Choice, list[tuple[Transform2D, float]], int, PreparedPairs, float | None]:
    """Large partial maps (fleetmap): the paper's candidates ranked by the grid score, the best
    few valued exactly (Algorithm 4) and refined.

    The candidates come from the paper's heuristics on each map's longest segments. Valuing tens
    of thousands of them exactly is slow, and between large maps the value ranks them poorly
    (long parallel walls match wherever corridors align), so they are ranked by the grid score of
    :mod:`fleetmap.shared.core.mapgrid` (matched wall length less wall length in the other's seen free
    space) on a few points per map, then on points every 10 cm for the best GRID_FINE; the best
    distinct ones are valued on the full maps and refined. Where the maps carry viewpoints, the
    free space judges crossings, and SEGMENTLENGTHREFUSE (steps 6-8), which one crossing pair
    among thousands would trip, is not applied.
    """
    i1 = index1 if index1 is not None else index_for(m1, p)
    i2 = index2 if index2 is not None else index_for(m2, p)
    free = GridFreeSpace(i1, i2, work)
    raw, labels = gather_candidates(search1, search2, h, p)
    cand, labels = _in_window(*distinct_candidates(raw, labels, p), window)
    first, fine = np.zeros(0, np.int64), np.zeros(0)
    if len(cand):
        # ranked before the full maps' pairs are prepared: the costliest stage between large maps,
        # so a budget it would pass stops the integration before any of it
        first = np.argsort(-_ranked(i1, i2, cand, False, work), kind="stable")[:GRID_FINE]
        fine = _ranked(i1, i2, cand[first], True, work)
    prep = prepare(m1.segments, m2.segments, m1.oriented and m2.oriented, p, m1.ordered, m2.ordered, work)
    best = _Choice(Transform2D.identity(), 0.0, 0.0, AUTO_ORDER.index(h) if h != "auto" else 0)
    rivals: list[tuple[Transform2D, float]] = []
    if len(cand):
        order = np.argsort(-fine, kind="stable")
        ranked = first[order]
        shortlist = ranked[:SHORTLIST]
        picked = _pick_distinct(cand[shortlist], fine[order[:SHORTLIST]], max(1, REFINE_CANDIDATES) if REFINE else 1, p)
        finals = [
            _evaluated(prep, free, Transform2D.from_array(cand[shortlist[j]]), int(labels[shortlist[j]]), p)
            for j in picked
        ]
        best, rivals, centre = _choose(prep, free, finals, p, not free.active, large=True)
        # More alignments clearly different from the best, best fine grid score first, among all
        # that got one (a small map in a symmetric building can fill the shortlist with one
        # alignment): the first, and between two partial maps up to :data:`RIVALS`, each clearly different
        # from the others, since the free space refutes some aliases and not others in racks
        # (:func:`~fleetmap.shared.core.validity.unrefuted`), and one left out could be the clean one.
        maps = not (m1.ordered or m2.ordered)
        ranked_t = cand[ranked]
        open_ = clearly_different(best.transform, centre)(ranked_t)
        for t, _ in rivals if maps else ():
            open_ &= clearly_different(t, centre)(ranked_t)
        for _ in range(RIVALS if maps else 1):
            if not open_.any():
                break
            other = _evaluated(prep, free, Transform2D.from_array(ranked_t[int(np.argmax(open_))]), 0, p)
            rivals.append((other.transform, other.score))
            open_ &= clearly_different(other.transform, centre)(ranked_t)
        if maps:
            rivals = unrefuted(rivals, best.value, best.score, free, p)
    solid = None
    limited = MAP_FREE_SPACE_MIN_LENGTH > 0 or p.validity.map_free_space_clearance > 0
    if limited and not (m1.ordered or m2.ordered) and free.active and best.value > 0:
        solid = float(free.violation(best.transform.as_array(), solid=True)[0])
    return best, _best_rivals(rivals, p), len(cand), prep, solid


def _choose(
    prep: PreparedPairs,
    free: FreeSpace | GridFreeSpace,
    finals: list[_Choice],
    p: IntegrationParams,
    refuse: bool,
    large: bool = False,
) -> tuple[_Choice, list[tuple[Transform2D, float]], Array | None]:
    """Refine the picks, and return the best, the clearly different ones (the rivals), and the
    point of S2 at which "clearly different" is measured
    (:func:`~fleetmap.shared.core.validity.clearly_different`; None: S2's origin).

    For large maps, "clearly different" is measured where the maps overlap (the centroid of S2's
    matched segments under the best), not at S2's origin: far from the overlap, a turn of a
    degree moves the origin by metres and would make the same alignment look like another.
    """
    if REFINE:
        # Two stages: a few steps for every pick, then to convergence for those still in the race.
        finals = [_refined(prep, free, c, p, REFINE_FIRST_STEPS, refuse) for c in finals]
        top, scores = max((c.score for c in finals), default=0.0), np.array([c.score for c in finals])
        ahead = settled_ahead(np.array([c.transform.as_array() for c in finals]).reshape(-1, 3), scores, p)
        finals = [
            _refined(prep, free, c, p, 12, refuse) if c.score >= REFINE_KEEP * top and not ahead[n] else c
            for n, c in enumerate(finals)
        ]
    best = finals[0] if finals else _Choice(Transform2D.identity(), 0.0, 0.0, 0)
    for choice in finals:
        if choice.score > best.score:
            best = choice
    if best.score <= 0:
        best = _Choice(Transform2D.identity(), 0.0, 0.0, best.label)
    centre = _overlap_centre(prep, best.transform, p) if large else None
    if not finals:
        return best, [], centre
    mask = clearly_different(best.transform, centre)(np.array([c.transform.as_array() for c in finals]))
    return best, [(c.transform, c.score) for c, f in zip(finals, mask, strict=True) if f], centre


def _best_rivals(rivals: list[tuple[Transform2D, float]], p: IntegrationParams) -> list[tuple[Transform2D, float]]:
    """The :data:`RIVALS` best-scoring rivals with a positive score, best first."""
    kept = sorted((r for r in rivals if r[1] > 0), key=lambda r: -r[1])
    return kept[:RIVALS]


def _overlap_centre(prep: PreparedPairs, best: Transform2D, p: IntegrationParams) -> Array | None:
    """The centroid of S2's segments matched under ``best`` (None if none is)."""
    _, k, mv = matched_pairs(prep, best.as_array(), p)
    if len(k) == 0:
        return None
    mid = 0.5 * (prep.s2[k, 0:2] + prep.s2[k, 2:4])
    return np.asarray((mid * mv[:, None]).sum(axis=0) / mv.sum())


@dataclass(frozen=True)
class _Choice:
    transform: Transform2D
    value: float
    score: float
    label: int
    coarse: bool = False
    """Picked for its value alone (:func:`_also_by_value`): refined coarse first."""


def _evaluated(
    prep: PreparedPairs, free: FreeSpace | GridFreeSpace, t: Transform2D, label: int, p: IntegrationParams
) -> _Choice:
    """A transformation with its value (and score) on the full maps."""
    v = transformation_value(prep, t.as_array(), p, refuse=not (isinstance(free, GridFreeSpace) and free.active))
    return _Choice(t, v, v - float(free.violation(t.as_array())[0]) if free.active else v, label)


def _longest(m: SegmentMap, limit: int) -> SegmentMap:
    """``m`` itself, or its ``limit`` longest segments (in their order) when it has more."""
    if limit <= 0 or len(m) <= limit:
        return m
    keep = np.sort(np.argsort(-lengths(m.segments), kind="stable")[:limit])
    return SegmentMap(m.segments[keep], ordered=m.ordered, oriented=m.oriented)


def _refined(
    prep: PreparedPairs,
    free: FreeSpace | GridFreeSpace,
    c: _Choice,
    p: IntegrationParams,
    steps: int,
    refuse: bool,
) -> _Choice:
    """``c`` refined by least squares, if that raises its score; first coarse
    (:data:`REFINE_COARSE_FACTOR`) if it was picked for its value alone (``c.coarse``). With noisy
    walls the candidates an angle match gives near the right transformation are a few tenths of a
    metre or a few degrees off, beyond the pairs the tolerance matches, and would stay there. The
    picks by score are refined at the given tolerance only: a coarse step there slows large merges
    and helps nothing (docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
    t = c.transform
    if c.coarse and REFINE_COARSE_FACTOR > 1:
        wide = replace(p, point_distance_tolerance=REFINE_COARSE_FACTOR * p.point_distance_tolerance)
        t = refine_transform(prep, t, wide, iterations=steps)
    t = refine_transform(prep, t, p, iterations=steps)
    v = transformation_value(prep, t.as_array(), p, refuse=refuse)
    score = v - float(free.violation(t.as_array())[0]) if free.active else v
    return _Choice(t, v, score, c.label) if score >= c.score else c


def _ranked(i1: MapIndex, i2: MapIndex, t: Array, fine: bool, work: Work) -> Array:
    """:func:`~fleetmap.shared.core.mapgrid.ranking_scores`, its lookups charged to ``work`` first."""
    samples = (i1.fine, i2.fine) if fine else (i1.coarse, i2.coarse)
    work.charge(len(t) * sum(len(s.points) for s in samples))
    return ranking_scores(i1, i2, t, fine=fine)


class GridFreeSpace:
    """The free-space check of the large-map path: wall length of each map in the other's free grid."""

    def __init__(self, index1: MapIndex, index2: MapIndex, work: Work | None = None) -> None:
        self.index1, self.index2 = index1, index2
        self.work = Work() if work is None else work

    @property
    def active(self) -> bool:
        return self.index1.has_free or self.index2.has_free

    def violation(self, t: Array, solid: bool = False) -> Array:
        """Wall length of each map in the other's free grid (if ``solid``, only what the validity
        rule limits: solid walls, clear of the other map's walls)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        self.work.charge(len(t) * (len(self.index1.fine.points) + len(self.index2.fine.points)))
        return grid_scores(self.index1, self.index2, t, fine=True, solid=solid)[1]


def index_for(m: SegmentMap, p: IntegrationParams) -> MapIndex:
    """The grid index of a map for the large-map path (keep it to integrate the map again)."""
    return map_index(
        m,
        mapgrid.GRID_RESOLUTION,
        p.segment_distance_threshold * p.point_distance_tolerance,
        mapgrid.MAP_FREE_SPACE_MARGIN,
        mapgrid.MAP_FREE_SPACE_SLOPE,
        MAP_FREE_SPACE_MIN_LENGTH,
        p.validity.map_free_space_clearance,
    )


def _shortlist_scores(t: Array, values: Array, free: FreeSpace) -> Array:
    """Scores of the best few candidates of a batch (value minus free-space violation)."""
    top = np.argsort(-values, kind="stable")[:8]
    top = top[values[top] > 0]
    if len(top) == 0:
        return np.zeros(0)
    return values[top] - free.violation(t[top]) if free.active else values[top]


def _matches(prep: PreparedPairs, t: Transform2D, p: IntegrationParams) -> tuple[IntArray, IntArray]:
    i, k, _ = matched_pairs(prep, t.as_array(), p)
    return i, k
