"""Least-squares refinement of a transformation on its matched segment pairs (fleetmap, beyond the paper).

The paper's best transformation superimposes one angle on another, so its accuracy is that of
two noisy segments. Here every matched pair votes: the parts of S2^t's segments that overlap
their S1 partner are pulled onto the partner's supporting line (point-to-line, like Cox's
matcher the paper cites), weighted by overlap length and a Cauchy loss, and the pairs are
re-associated after each step. A direction the pairs do not constrain (a corridor with no
ends) is left where the angle match put it: the damping keeps the step in that direction zero.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.refinekernel import normal_equations
from fleetmap.shared.core.transformation_value import PreparedPairs, matched_pairs

SLACK_TRANSLATION = 0.10
"""A refinement that lowers the value within ``pivot_refine_slack`` is kept after a move of at most
this (m) ..."""
SLACK_ROTATION = 0.035
"""... and this (rad, 2 degrees): the value is flat near the true pose, and a scan turned half a degree
can score a little more than the least-squares pose (docs/decisions/005-parameters-beyond-the-paper.md)."""


def _normal_equations(prep: PreparedPairs, t: Array, params: IntegrationParams) -> tuple[Array, Array] | None:
    """The Gauss-Newton normal matrix and gradient of the point-to-line residuals of the pairs
    matched at ``t`` (parameters x, y and heading of S2 in S1's frame; the heading about S2's
    origin); None with fewer than two parallel pairs."""
    i, k, _mv = matched_pairs(prep, t, params)
    if len(i) < 2:
        return None
    h, g, parallel = normal_equations(
        prep.s1, prep.s2, i, k, t, math.cos(params.angle_difference_tolerance), params.point_distance_tolerance
    )
    return None if parallel < 2 else (h, g)


def refine_transform(
    prep: PreparedPairs, start: Transform2D, params: IntegrationParams, iterations: int = 12
) -> Transform2D:
    """Gauss-Newton on point-to-line residuals of the matched pairs, re-associating each step."""
    t = start.as_array()
    for _ in range(iterations):
        system = _normal_equations(prep, t, params)
        if system is None:
            break
        h, g = system
        damping = 1e-6 * (np.trace(h) + 1e-12)
        step = -np.linalg.solve(h + damping * np.eye(3), g)
        t = t + step
        if abs(step[0]) + abs(step[1]) < 1e-6 and abs(step[2]) < 1e-7:
            break
    return Transform2D.from_array(t)


def fit_information(prep: PreparedPairs, t: Transform2D, params: IntegrationParams) -> Array | None:
    """How firmly the matched pairs fix ``t``: the 3x3 normal matrix of their point-to-line fit
    (x and y of S2 in S1's frame, in m, and its heading about S2's origin, in rad; each pair
    weighted by its overlap length and a Cauchy factor of its distance at ``t``), whose small
    eigenvalues are directions the walls leave free (along a corridor with no ends). None where
    fewer than two parallel pairs match."""
    system = _normal_equations(prep, t.as_array(), params)
    return None if system is None else system[0]


def refinement_kept(
    start: Transform2D, refined: Transform2D, before: float, after: float, params: IntegrationParams
) -> bool:
    """Whether a refined transformation replaces its start: it scores more, or a little less
    (``pivot_refine_slack``) after a small move (see :class:`~fleetmap.shared.config.IntegrationParams`)."""
    if after >= before:
        return True
    dt, dr = start.distance(refined)
    small = dt <= SLACK_TRANSLATION and dr <= SLACK_ROTATION
    return small and after >= before - params.pivot.pivot_refine_slack * abs(before)
