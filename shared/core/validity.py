"""The validity rules of one integration: whether INTEGRATE's best transformation is trusted.

The paper leaves validity to a user threshold on the value (V-B) and reports that right
integrations of its local maps scored about 10 m and wrong ones about 5 m. A fixed threshold
cannot serve both a pair of scans (a few metres of wall) and a pair of local maps (tens of
metres), so there are two rules (docs/decisions/007-validity-of-an-integration.md).

Scans (either map ``ordered``): the value is at least ``valid_min_value`` metres *and* at least
``valid_min_fraction`` of the total segment length of the smaller map (a fair share of what the
smaller map saw is explained by the other), at most ``valid_max_violation`` of it lies in the
other scan's seen free space, and no clearly different transformation scores within
``valid_max_ambiguity`` of it (nothing refutes the mirror image of a rectangular room).

Two partial maps: value at least ``valid_min_map_value``; at most ``valid_max_map_violation`` of
it in the other map's seen free space, counting only the walls farther than
``map_free_space_clearance`` from the other map's own walls (two local maps place the same wall a
little apart) and, with ``map_free_space_min_length``, only long walls (clutter moves); from
``valid_strong_map_value`` on, ``valid_max_strong_map_violation`` (a large overlap's shared walls,
placed a little apart, violate in proportion to it); no clearly different transformation within
``valid_max_map_ambiguity`` of its score on the large-map path, where the free space judges the
rivals too (``valid_max_ambiguity`` on the small one): a rival that puts metres of wall where a
laser saw through, while the best puts next to none there, is refuted and does not count
(``valid_refute_violation``, :func:`unrefuted`); and each map that carries its scans' viewpoints
has at least ``valid_min_map_scans`` of them (a map of two or three scans in a symmetric building
matches turned round as well as where it is). Long corridors match wherever they align, so
between maps only a clear, unambiguous match is trusted; an unplaced map is better than a wrong
one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from fleetmap.shared.config import IntegrationParams, ValidityParams
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_angle
from fleetmap.shared.core.mapgrid import VIEWPOINTS
from fleetmap.shared.core.segmap import SegmentMap


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
            and value >= params.validity.valid_min_fraction * min(scans)
            and violation <= params.validity.valid_max_violation * value
            and runner_up <= params.validity.valid_max_ambiguity * score
        )
    if not scans:
        # Two partial maps: the paper's right ~10 m / wrong ~5 m, with free space and ambiguity;
        # and each seen from enough places (a map of two scans in a symmetric building matches
        # turned round as well as it matches where it is).
        return (
            seen_from_enough_places(m1, m2, params)
            and value >= params.validity.valid_min_map_value
            and (violation if solid_violation is None else solid_violation) <= max_map_violation(value, params) * value
            and runner_up
            <= (params.validity.valid_max_map_ambiguity if large else params.validity.valid_max_ambiguity) * score
        )
    smaller = min(m1.total_length, m2.total_length)
    return (
        value >= params.validity.valid_min_value
        and value >= params.validity.valid_min_fraction * smaller
        and violation <= params.validity.valid_max_violation * value
        and runner_up <= params.validity.valid_max_ambiguity * score
    )


def max_map_violation(value: float, params: IntegrationParams) -> float:
    """The fraction of its value an integration of two partial maps may put in their seen free
    space: ``valid_max_strong_map_violation`` from ``valid_strong_map_value`` on."""
    strong = params.validity.valid_strong_map_value
    if strong > 0 and value >= strong:
        return max(params.validity.valid_max_map_violation, params.validity.valid_max_strong_map_violation)
    return params.validity.valid_max_map_violation


def seen_from_enough_places(m1: SegmentMap, m2: SegmentMap, params: IntegrationParams) -> bool:
    """Whether each of two partial maps that carries its scans' viewpoints has at least
    ``valid_min_map_scans`` of them: otherwise they cannot merge, whatever their geometry."""
    seen = [len(x.extras[VIEWPOINTS]) for x in (m1, m2) if VIEWPOINTS in x.extras]
    return min(seen, default=params.validity.valid_min_map_scans) >= params.validity.valid_min_map_scans


def clearly_different(best: Transform2D, centre: Array | None, p: ValidityParams) -> Callable[[Array], Array]:
    """Which of ``(n, 3)`` transformations are clearly different from ``best``: they move ``centre``
    (S2's origin by default) more than ``ambiguity_translation`` from where ``best`` puts it, or turn
    more than ``ambiguity_rotation`` from it."""
    c = np.zeros(2) if centre is None else centre
    at_best = best.apply_points(c[None])[0]

    def far(t: Array) -> Array:
        t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        cos, sin = np.cos(t[:, 2]), np.sin(t[:, 2])
        moved = np.column_stack([cos * c[0] - sin * c[1] + t[:, 0], sin * c[0] + cos * c[1] + t[:, 1]])
        turn = np.abs(wrap_angle(t[:, 2] - best.theta))
        return np.asarray((np.hypot(*(moved - at_best).T) > p.ambiguity_translation) | (turn > p.ambiguity_rotation))

    return far


def unrefuted(
    rivals: list[tuple[Transform2D, float]], value: float, score: float, free: SeenFreeSpace, p: IntegrationParams
) -> list[tuple[Transform2D, float]]:
    """Two partial maps: the rivals that the maps' seen free space does not refute (fleetmap).

    A rival is refuted when it puts at least ``valid_refute_violation`` metres of wall, and more
    than ``valid_max_map_violation`` of its value, where the other robot's laser saw through, while
    the best puts at most ``valid_refute_clean`` of its value there. Wall where a laser saw free
    space is evidence against a transformation; a smaller overlap is only the absence of evidence
    for it. In a warehouse lane, the alignments a rack or two off match more wall than the right
    one (they slide the map over more of the other) but put rack ends in the forklift's bay; the
    score (value less violation) still ranks them within a tenth of the right one.
    """
    limit = p.validity.valid_refute_violation
    if limit <= 0 or not rivals or not free.active or value - score > p.validity.valid_refute_clean * value:
        return rivals
    t = np.array([r.as_array() for r, _ in rivals])
    violation = free.violation(t)
    scores = np.array([s for _, s in rivals])
    refuted = (violation >= limit) & (violation > p.validity.valid_max_map_violation * (scores + violation))
    return [r for r, out in zip(rivals, refuted, strict=True) if not out]
