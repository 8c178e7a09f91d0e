"""The refinement's compiled normal equations (shared/core/refinekernel.py) against the same sums in numpy."""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.refinekernel import normal_equations


def _numpy_normal_equations(s1, s2, i, k, t, cos_tolerance, tolerance):  # type: ignore[no-untyped-def]
    """The point-to-line normal equations as numpy wrote them before they were compiled."""
    s2t = Transform2D.from_array(t).apply(s2[k])
    s1 = s1[i]
    u1 = s1[:, 2:4] - s1[:, 0:2]
    u2 = s2t[:, 2:4] - s2t[:, 0:2]
    cos = np.einsum("ij,ij->i", u1, u2) / (np.hypot(*u1.T) * np.hypot(*u2.T))
    parallel = np.abs(cos) >= cos_tolerance
    s1, s2t = s1[parallel], s2t[parallel]
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
    lam0 = np.clip((0.0 - ta) / safe, 0.0, 1.0)
    lam1 = np.clip((length - ta) / safe, 0.0, 1.0)
    lo, hi = np.minimum(lam0, lam1), np.maximum(lam0, lam1)
    d = qb - qa
    q = np.stack([qa + lo[:, None] * d, qa + hi[:, None] * d], axis=1).reshape(-1, 2)
    weight = np.abs(span) * (hi - lo)
    offset = np.einsum("ij,ij->i", normal, p)
    n = np.repeat(normal, 2, axis=0)
    r = np.einsum("ij,ij->i", n, q) - np.repeat(offset, 2)
    w = np.repeat(weight, 2) * 0.5 / (1.0 + (r / tolerance) ** 2)
    rel = q - t[:2]
    jac = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * rel[:, 0] - n[:, 0] * rel[:, 1]])
    return jac.T @ (jac * w[:, None]), jac.T @ (w * r), int(parallel.sum())


def test_the_compiled_normal_equations_are_the_numpy_sums_to_rounding():
    rng = np.random.default_rng(3)
    # walls of a room and the same walls seen again, moved a little and noisy: most pairs near
    # parallel and overlapping, some crossing, some apart along their line, some far from parallel
    s1 = rng.uniform(-6, 6, (40, 4))
    s2 = s1 + rng.normal(0, 0.05, s1.shape)
    s2[30:] = rng.uniform(-6, 6, (10, 4))
    s2[5] = s1[5] + [3, 0, 3, 0]  # one pair apart: its overlap is empty
    i, k = (a.ravel() for a in np.indices((len(s1), len(s2))))
    cos_tolerance, tolerance = math.cos(math.radians(10)), 0.1
    for t in (np.zeros(3), np.array([0.2, -0.1, 0.05]), np.array([1.0, 2.0, -0.4])):
        h, g, n = normal_equations(s1, s2, i, k, t, cos_tolerance, tolerance)
        want_h, want_g, want_n = _numpy_normal_equations(s1, s2, i, k, t, cos_tolerance, tolerance)
        assert n == want_n and n > 40
        assert np.allclose(h, want_h, rtol=1e-12, atol=1e-12) and np.allclose(g, want_g, rtol=1e-12, atol=1e-12)
        assert np.array_equal(h, h.T)
    h, g, n = normal_equations(s1, s2, i[:0], k[:0], np.zeros(3), cos_tolerance, tolerance)
    assert n == 0 and not h.any() and not g.any()
