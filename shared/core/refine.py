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
from fleetmap.shared.core.transformation_value import PreparedPairs, matched_pairs

SLACK_TRANSLATION = 0.10
"""A refinement that lowers the value within ``pivot_refine_slack`` is kept after a move of at most
this (m) ..."""
SLACK_ROTATION = 0.035
"""... and this (rad, 2 degrees): the value is flat near the true pose, and a scan turned half a degree
can score a little more than the least-squares pose (docs/decisions/005-parameters-beyond-the-paper.md)."""


def pair_residuals(s1: Array, s2t: Array) -> tuple[Array, Array, Array, Array]:
    """For each pair: the two points of s2^t bounding its overlap with s1, s1's unit normal and
    a point of s1's line, and the overlap weight.

    Returns ``points (m, 2, 2)``, ``normal (m, 2)`` with ``offset (m,)`` (so the residual of a
    point q is ``normal . q - offset``), and ``weight (m,)``.
    """
    p = s1[:, 0:2]
    u = s1[:, 2:4] - p
    length = np.hypot(u[:, 0], u[:, 1])
    u = u / length[:, None]
    normal = np.column_stack([-u[:, 1], u[:, 0]])
    qa, qb = s2t[:, 0:2], s2t[:, 2:4]
    ta = np.einsum("ij,ij->i", qa - p, u)
    tb = np.einsum("ij,ij->i", qb - p, u)
    span = tb - ta
    safe = np.where(np.abs(span) > 1e-12, span, 1e-12)
    # Parameters along s2^t where its projection enters and leaves [0, length].
    lam0 = np.clip((0.0 - ta) / safe, 0.0, 1.0)
    lam1 = np.clip((length - ta) / safe, 0.0, 1.0)
    lo, hi = np.minimum(lam0, lam1), np.maximum(lam0, lam1)
    d = qb - qa
    points = np.stack([qa + lo[:, None] * d, qa + hi[:, None] * d], axis=1)
    weight = np.abs(span) * (hi - lo)
    offset = np.einsum("ij,ij->i", normal, p)
    return points, normal, offset, weight


def _normal_equations(prep: PreparedPairs, t: Array, params: IntegrationParams) -> tuple[Array, Array] | None:
    """The Gauss-Newton normal matrix and gradient of the point-to-line residuals of the pairs
    matched at ``t`` (parameters x, y and heading of S2 in S1's frame; the heading about S2's
    origin); None with fewer than two parallel pairs."""
    i, k, _mv = matched_pairs(prep, t, params)
    if len(i) < 2:
        return None
    s2t = Transform2D.from_array(t).apply(prep.s2[k])
    s1 = prep.s1[i]
    u1 = s1[:, 2:4] - s1[:, 0:2]
    u2 = s2t[:, 2:4] - s2t[:, 0:2]
    cos = np.einsum("ij,ij->i", u1, u2) / (np.hypot(*u1.T) * np.hypot(*u2.T))
    parallel = np.abs(cos) >= math.cos(params.angle_difference_tolerance)
    if parallel.sum() < 2:
        return None
    points, normal, offset, weight = pair_residuals(s1[parallel], s2t[parallel])
    q = points.reshape(-1, 2)
    n = np.repeat(normal, 2, axis=0)
    r = np.einsum("ij,ij->i", n, q) - np.repeat(offset, 2)
    w = np.repeat(weight, 2) * 0.5 / (1.0 + (r / params.point_distance_tolerance) ** 2)
    rel = q - t[:2]
    jac = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * rel[:, 0] - n[:, 0] * rel[:, 1]])
    return jac.T @ (jac * w[:, None]), jac.T @ (w * r)


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
