"""The validity rules of one integration: whether INTEGRATE's best transformation is trusted.

The paper leaves validity to a user threshold on the value (V-B) and reports that right
integrations of its local maps scored about 10 m and wrong ones about 5 m. A fixed threshold
cannot serve both a pair of scans (a few metres of wall) and a pair of local maps (tens of
metres), so there are two rules (docs/decisions/007-validity-of-an-integration.md).

Scans (either map ``ordered``): the value is at least ``valid_min_value`` metres *and* at least
:data:`VALID_MIN_FRACTION` of the total segment length of the smaller map (a fair share of what the
smaller map saw is explained by the other), at most :data:`VALID_MAX_VIOLATION` of it lies in the
other scan's seen free space, and no clearly different transformation scores within
:data:`VALID_MAX_AMBIGUITY` of it (nothing refutes the mirror image of a rectangular room).

Two partial maps: value at least :data:`VALID_MIN_MAP_VALUE`; at most :data:`VALID_MAX_MAP_VIOLATION` of
it in the other map's seen free space, counting only the walls farther than
``map_free_space_clearance`` from the other map's own walls (two local maps place the same wall a
little apart) and, with :data:`MAP_FREE_SPACE_MIN_LENGTH`, only long walls (clutter moves); from
:data:`VALID_STRONG_MAP_VALUE` on, :data:`VALID_MAX_STRONG_MAP_VIOLATION` (a large overlap's shared walls,
placed a little apart, violate in proportion to it); no clearly different transformation within
:data:`VALID_MAX_MAP_AMBIGUITY` of its score on the large-map path, where the free space judges the
rivals too (:data:`VALID_MAX_AMBIGUITY` on the small one): a rival that puts metres of wall where a
laser saw through, while the best puts next to none there, is refuted and does not count
(:data:`VALID_REFUTE_VIOLATION`, :func:`unrefuted`); and each map that carries its scans' viewpoints
has at least :data:`VALID_MIN_MAP_SCANS` of them (a map of two or three scans in a symmetric building
matches turned round as well as where it is). Long corridors match wherever they align, so
between maps only a clear, unambiguous match is trusted; an unplaced map is better than a wrong
one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.mapgrid import VIEWPOINTS
from fleetmap.shared.core.segmap import SegmentMap

VALID_MIN_FRACTION = 0.2
"""Scans: the value is at least this fraction of the smaller map's segment length (a fair share of
what it saw is explained by the other; 007)."""
VALID_MAX_VIOLATION = 0.2
"""Scans: at most this fraction of the value lies in the other scan's seen free space (007)."""
VALID_MAX_AMBIGUITY = 0.8
"""Scans, and a scan on a partial map: no clearly different transformation scores more than this
fraction of the best's score (nothing refutes the mirror image of a rectangular room; 007)."""
AMBIGUITY_TRANSLATION = 0.5
"""A transformation is clearly different from the best when it moves the overlap more than this (m)
from where the best puts it ..."""
AMBIGUITY_ROTATION = 0.17
"""... or turns more than this (rad, 10 degrees): the edge of what 007 counts as wrong (1 m, 10 degrees)."""
VALID_MIN_MAP_VALUE = 8.0
"""Two partial maps: the value is at least this (m): the paper's right ~10 m, wrong ~5 m; on 843
integrations of local maps of the corrected logs, 106 right valid against 9 wrong with the rules
below (docs/decisions/007-validity-of-an-integration.md)."""
VALID_MIN_MAP_SCANS = 5
"""Two partial maps: each that carries its scans' viewpoints has at least this many (at 1 the
simulated warehouse's pivot maps merge 2 maps wrong, one turned round; 007)."""
VALID_MAX_MAP_VIOLATION = 0.1
"""Two partial maps: at most this fraction of the value lies in the maps' seen free space (007) ..."""
VALID_STRONG_MAP_VALUE = 16.0
"""... and from this value (m) on ..."""
VALID_MAX_STRONG_MAP_VIOLATION = 0.15
"""... this fraction: a large overlap's shared walls, placed a little apart, violate in proportion to
it (maps fused from the corrected poses: 11-14 %; 52 right valid against 44, the same 2 wrong; 007)."""
VALID_MAX_MAP_AMBIGUITY = 0.5
"""Two partial maps on the large-map path: no clearly different transformation scores more than this
fraction of the best's score (the free space judges the rivals too there; 007)."""
VALID_REFUTE_VIOLATION = 3.0
"""Two partial maps: a rival putting at least this much wall (m), and more than
:data:`VALID_MAX_MAP_VIOLATION` of its value, in the seen free space is refuted ..."""
VALID_REFUTE_CLEAN = 0.025
"""... provided the best puts at most this fraction of its value there (a warehouse lane's aliases a
rack off put rack ends in the forklift's bay; 007)."""


class SeenFreeSpace(Protocol):
    """The maps' seen free space, prepared for many transformations (the large-map grid check)."""

    @property
    def active(self) -> bool: ...

    def violation(self, t: Array) -> Array: ...


def is_valid(
    value: float,
    violation: float,
    runner_up: float,
    m1: SegmentMap,
    m2: SegmentMap,
    params: IntegrationParams,
    large: bool = False,
    solid_violation: float | None = None,
) -> bool:
    """The validity rule of the module docstring (``large``: the large-map path's rule; between two
    partial maps, ``solid_violation``, where given, is the violation limited)."""
    score = value - violation
    scans = [x.total_length for x in (m1, m2) if x.ordered]
    if large and scans:
        # A scan integrated with a partial map must still be explained in a fair share by it.
        return (
            value >= params.validity.valid_min_value
            and value >= VALID_MIN_FRACTION * min(scans)
            and violation <= VALID_MAX_VIOLATION * value
            and runner_up <= VALID_MAX_AMBIGUITY * score
        )
    if not scans:
        # Two partial maps: the paper's right ~10 m / wrong ~5 m, with free space and ambiguity;
        # and each seen from enough places (a map of two scans in a symmetric building matches
        # turned round as well as it matches where it is).
        return (
            seen_from_enough_places(m1, m2, params)
            and value >= VALID_MIN_MAP_VALUE
            and (violation if solid_violation is None else solid_violation) <= max_map_violation(value, params) * value
            and runner_up <= (VALID_MAX_MAP_AMBIGUITY if large else VALID_MAX_AMBIGUITY) * score
        )
    smaller = min(m1.total_length, m2.total_length)
    return (
        value >= params.validity.valid_min_value
        and value >= VALID_MIN_FRACTION * smaller
        and violation <= VALID_MAX_VIOLATION * value
        and runner_up <= VALID_MAX_AMBIGUITY * score
    )


def max_map_violation(value: float, params: IntegrationParams) -> float:
    """The fraction of its value an integration of two partial maps may put in their seen free
    space: :data:`VALID_MAX_STRONG_MAP_VIOLATION` from :data:`VALID_STRONG_MAP_VALUE` on."""
    strong = VALID_STRONG_MAP_VALUE
    if strong > 0 and value >= strong:
        return max(VALID_MAX_MAP_VIOLATION, VALID_MAX_STRONG_MAP_VIOLATION)
    return VALID_MAX_MAP_VIOLATION


def refuted_by_free_space(value: float, violation: float, params: IntegrationParams) -> bool:
    """Whether the wall one partial map puts in the other's seen free space refutes an alignment on
    its own: at least :data:`VALID_REFUTE_VIOLATION` metres of it, and more than
    :func:`max_map_violation` allows ``value`` (the join check's pair verdict; what
    ``benchmarks/free_space.py`` counts at the corrected poses)."""
    return violation >= VALID_REFUTE_VIOLATION and violation > max_map_violation(value, params) * value


def seen_from_enough_places(m1: SegmentMap, m2: SegmentMap, params: IntegrationParams) -> bool:
    """Whether each of two partial maps that carries its scans' viewpoints has at least
    :data:`VALID_MIN_MAP_SCANS` of them: otherwise they cannot merge, whatever their geometry."""
    seen = [len(x.extras[VIEWPOINTS]) for x in (m1, m2) if VIEWPOINTS in x.extras]
    return min(seen, default=VALID_MIN_MAP_SCANS) >= VALID_MIN_MAP_SCANS


def clearly_different(best: Transform2D, centre: Array | None) -> Callable[[Array], Array]:
    """Which of ``(n, 3)`` transformations are clearly different from ``best``: they move ``centre``
    (S2's origin by default) more than :data:`AMBIGUITY_TRANSLATION` from where ``best`` puts it, or turn
    more than :data:`AMBIGUITY_ROTATION` from it."""
    c = np.zeros(2) if centre is None else centre
    at_best = best.apply_points(c[None])[0]

    def far(t: Array) -> Array:
        t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        cos, sin = np.cos(t[:, 2]), np.sin(t[:, 2])
        moved = np.column_stack([cos * c[0] - sin * c[1] + t[:, 0], sin * c[0] + cos * c[1] + t[:, 1]])
        turn = np.abs(wrap_angle(t[:, 2] - best.theta))
        return np.asarray((np.hypot(*(moved - at_best).T) > AMBIGUITY_TRANSLATION) | (turn > AMBIGUITY_ROTATION))

    return far


def unrefuted(
    rivals: list[tuple[Transform2D, float]], value: float, score: float, free: SeenFreeSpace, p: IntegrationParams
) -> list[tuple[Transform2D, float]]:
    """Two partial maps: the rivals that the maps' seen free space does not refute (fleetmap).

    A rival is refuted when it puts at least :data:`VALID_REFUTE_VIOLATION` metres of wall, and more
    than :data:`VALID_MAX_MAP_VIOLATION` of its value, where the other robot's laser saw through, while
    the best puts at most :data:`VALID_REFUTE_CLEAN` of its value there. Wall where a laser saw free
    space is evidence against a transformation; a smaller overlap is only the absence of evidence
    for it. In a warehouse lane, the alignments a rack or two off match more wall than the right
    one (they slide the map over more of the other) but put rack ends in the forklift's bay; the
    score (value less violation) still ranks them within a tenth of the right one.
    """
    limit = VALID_REFUTE_VIOLATION
    if limit <= 0 or not rivals or not free.active or value - score > VALID_REFUTE_CLEAN * value:
        return rivals
    t = np.array([r.as_array() for r, _ in rivals])
    violation = free.violation(t)
    scores = np.array([s for _, s in rivals])
    refuted = (violation >= limit) & (violation > VALID_MAX_MAP_VIOLATION * (scores + violation))
    return [r for r, out in zip(rivals, refuted, strict=True) if not out]
