"""A scan's step from the scan before it, measured by the two scans' points (pure core).

Registration places a scan by its walls. Where a scan holds too few of them to be placed (open
ground: posts, hedges, a metre of wall), the robot is carried by its motion model, and a turn in
place that the wheels over-read turns the track with it (docs/decisions/044). Yet the beams that
return still measure the step: a turn among posts sweeps every return by the turn, and points
15 m away move 26 cm a degree. Here the step between two consecutive scans is measured by their
points as a correlative matcher measures it (Olson, "Real-time correlative scan matching", ICRA
2009, Section III): every pose of the prior's window is scored by a rasterized lookup of how far
each of the scan's points lies from the nearest of the reference scan's, as a Gaussian of the
points' own noise truncated at :data:`OUTLIER_SIGMAS` (a point farther from every reference point
matches none: a person, a branch, a wall seen only now); the score is a log-likelihood (each point
a share of a measurement, :data:`CORRELATED_POINTS`), the prior's Gaussian is added to it, and the
step is the mean and covariance of that distribution over the window. The covariance is the
distribution's spread, not a peak's curvature: two places that fit alike make a wide one, and the
prior decides between them. (:func:`fleetmap.shared.core.correlative.window_support`, the same
search for the fit check, scores walls' support at one heading and keeps the best; a step needs
the heading and the whole distribution.)

A point's noise is the laser's range noise and half the spacing of the reference's beams at the
points' typical range (the next scan's beams fall between the reference's): derived from the
scans, no parameter. The window is the prior's :data:`WINDOW_SIGMAS` standard deviations, searched
at steps of the noise in translation and of the turn that moves the farthest point as far, looked
up in cells half as wide.

Everything here is numpy in, numpy out: no clock, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D, wrap_scalar
from fleetmap.shared.core.tracking import RESIDUAL_SIGMA
from scipy.ndimage import distance_transform_edt

__all__ = ["PointStep", "point_step"]

CORRELATED_POINTS = 8.0
"""The points' misfits are not independent: neighbouring beams fall on one surface, and where the
reference scan saw it from elsewhere they miss it together. The log-likelihood counts each point
as a share of one measurement, one in this many: measured, not derived. With it the steps' normalised
errors against the corrected poses of eight logs have medians 1.8-4.8 (chi-square with 3 degrees of
freedom: 2.4); counted each as one, 8-16, and a turn into new space that a wrong alignment fits
better outweighs the prior that placed it right (docs/decisions/083)."""
OUTLIER_SIGMAS = 3.0
"""A point farther than this many of its noise's standard deviations from every reference point
matches none (the Gaussian is truncated there: a robust likelihood)."""
WINDOW_SIGMAS = 3.0
"""The window searched: the prior's mean plus and minus this many of its standard deviations."""
MAX_CELLS = 4_000_000
"""The window's poses times the scan's points looked up at most (about a tenth of a second): a
wider prior is searched at coarser steps."""


@dataclass(frozen=True)
class PointStep:
    """The step the two scans' points measure."""

    increment: Transform2D
    """The scan's pose in the reference scan's frame: the distribution's mean."""
    covariance: Array
    """Its 3 x 3 covariance over (x, y, theta): the distribution's spread."""
    peak: Transform2D
    """The window's most likely step, prior included (the distribution's mode): where two places
    fit alike, the mean lies between them and the mode at the likelier one."""


def point_step(
    reference: Array,
    scan: Array,
    prior: Transform2D,
    sigma_translation: float,
    sigma_rotation: float,
    angle_increment: float,
    covering: Transform2D | None = None,
) -> PointStep | None:
    """The step from the scan whose returns are ``reference`` (``(n, 2)``, its laser frame) to the
    scan whose returns are ``scan`` (``(m, 2)``, its own frame), measured by their points over
    the prior (``prior``, the step predicted, with standard deviations ``sigma_translation`` (m,
    each axis) and ``sigma_rotation`` (rad)); ``angle_increment`` is the reference's beam spacing
    (rad). The window is widened to hold the step ``covering`` too, where given (a step another
    measurement found beyond the prior's window), the prior unchanged. None where either scan has
    no returns. A few returns fit a step almost anywhere, and
    counted a share of a measurement each (:data:`CORRELATED_POINTS`) they leave the prior in
    charge: no count of returns is asked for (a guard of 10 cost freiburg-campus-corrected 0.5
    points of its short relations: docs/decisions/084)."""
    if len(reference) == 0 or len(scan) == 0:
        return None
    typical = float(np.median(np.hypot(reference[:, 0], reference[:, 1])))
    sigma = math.hypot(RESIDUAL_SIGMA, typical * abs(angle_increment) / 2.0)
    cell = sigma / 2.0
    reach = float(np.max(np.hypot(scan[:, 0], scan[:, 1])))
    half_t = WINDOW_SIGMAS * sigma_translation
    half_r = min(WINDOW_SIGMAS * sigma_rotation, math.pi)
    if covering is not None:
        half_t = max(half_t, abs(covering.x - prior.x) + sigma, abs(covering.y - prior.y) + sigma)
        half_r = min(max(half_r, abs(wrap_scalar(covering.theta - prior.theta)) + sigma / max(reach, sigma)), math.pi)
    # Olson's steps: a translation step of the lookup's noise, a turn moving the farthest point as
    # far; coarser (both alike) where the window would cost more than MAX_CELLS lookups
    step_t, step_r = sigma, sigma / max(reach, sigma)
    count = (2 * half_t / step_t + 1) ** 2 * (2 * half_r / step_r + 1) * len(scan)
    coarser = max(1.0, (count / MAX_CELLS) ** (1.0 / 3.0))
    step_t, step_r = step_t * coarser, step_r * coarser
    offsets = np.arange(-math.floor(half_t / step_t), math.floor(half_t / step_t) + 1) * step_t
    turns = prior.theta + np.arange(-math.floor(half_r / step_r), math.floor(half_r / step_r) + 1) * step_r
    gx, gy = np.meshgrid(prior.x + offsets, prior.y + offsets, indexing="ij")
    shifts = np.column_stack([gx.ravel(), gy.ravel()])
    low, cost = _lookup(reference, sigma, cell)
    shape = np.array(cost.shape)
    outlier = OUTLIER_SIGMAS**2 / 2.0
    log_likelihood = np.empty((len(turns), len(shifts)))
    for i, theta in enumerate(turns):
        c, s = math.cos(theta), math.sin(theta)
        turned = scan @ np.array([[c, s], [-s, c]])
        cells = np.floor((turned[None, :, :] + shifts[:, None, :] - low) / cell).astype(np.int64)
        inside = np.all((cells >= 0) & (cells < shape), axis=-1)
        costs = np.full(inside.shape, outlier)
        costs[inside] = cost[cells[..., 0][inside], cells[..., 1][inside]]
        log_likelihood[i] = -costs.sum(axis=1) / CORRELATED_POINTS
    d_translation = ((shifts[:, 0] - prior.x) ** 2 + (shifts[:, 1] - prior.y) ** 2) / sigma_translation**2
    d_rotation = (turns - prior.theta) ** 2 / sigma_rotation**2
    log_p = log_likelihood - 0.5 * d_translation[None, :] - 0.5 * d_rotation[:, None]
    weights = np.exp(log_p - log_p.max()).ravel()
    weights /= weights.sum()
    poses = np.column_stack([np.tile(shifts, (len(turns), 1)), np.repeat(turns, len(shifts))])
    mean = weights @ poses
    spread = poses - mean
    covariance = (spread * weights[:, None]).T @ spread
    # the grid's own resolution: a distribution on one cell still spans a step
    covariance += np.diag([step_t**2, step_t**2, step_r**2]) / 12.0
    top = poses[int(np.argmax(weights))]
    return PointStep(
        Transform2D(float(mean[0]), float(mean[1]), wrap_scalar(float(mean[2]))),
        covariance,
        Transform2D(float(top[0]), float(top[1]), wrap_scalar(float(top[2]))),
    )


def _lookup(reference: Array, sigma: float, cell: float) -> tuple[Array, Array]:
    """The rasterized cost: each cell's squared distance to the nearest reference point over
    ``2 sigma^2``, truncated at :data:`OUTLIER_SIGMAS` (beyond the grid, every point costs that
    too); and the grid's lower corner."""
    margin = OUTLIER_SIGMAS * sigma + cell
    low = reference.min(axis=0) - margin
    shape = np.ceil((reference.max(axis=0) + margin - low) / cell).astype(np.int64) + 1
    empty = np.ones(tuple(shape), dtype=bool)
    cells = np.floor((reference - low) / cell).astype(np.int64)
    empty[cells[:, 0], cells[:, 1]] = False
    distance = distance_transform_edt(empty) * cell
    return low, np.minimum(distance, OUTLIER_SIGMAS * sigma) ** 2 / (2.0 * sigma**2)
