"""The least-squares refinement's normal equations, compiled (:mod:`fleetmap.shared.core.refine`).

Each Gauss-Newton step of the refinement takes the pairs a transformation matches, keeps the near
parallel ones, clips each moved segment of S2 to its overlap with its S1 partner and sums the
point-to-line residuals of the overlap's two ends into a 3x3 normal matrix and a gradient. In numpy
that is some twenty passes over a few dozen pairs per step; a scan pair's pose-free integration in
a burst of scans refines a dozen starts a scan, about 50 steps, and those passes were a third of
the tracker's time there (aces in bursts: 73,111 steps in 1,500 scans, docs/decisions/065). One
compiled loop (Numba) does the same arithmetic pair by pair; only the sums' rounding differs.

Numba is imported and the loop compiled (or loaded from its cache beside this file) on the first
call (:mod:`fleetmap.shared.core.compiled`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fleetmap.shared.core.compiled import Compiled
from fleetmap.shared.core.geometry import Array


def _build() -> Callable[..., int]:
    # one function, calling no other built here (:mod:`fleetmap.shared.core.compiled`)
    import numba

    @numba.njit(cache=True, nogil=True)
    def normal(s1, s2, i, k, x, y, theta, cos_tolerance, tolerance, h, g):
        c, s = np.cos(theta), np.sin(theta)
        for a in range(3):
            g[a] = 0.0
            for b in range(3):
                h[a, b] = 0.0
        n = 0
        for r in range(len(i)):
            p, q = i[r], k[r]
            px, py = s1[p, 0], s1[p, 1]
            ux, uy = s1[p, 2] - px, s1[p, 3] - py
            ax = c * s2[q, 0] - s * s2[q, 1] + x
            ay = s * s2[q, 0] + c * s2[q, 1] + y
            bx = c * s2[q, 2] - s * s2[q, 3] + x
            by = s * s2[q, 2] + c * s2[q, 3] + y
            vx, vy = bx - ax, by - ay
            length = np.hypot(ux, uy)
            cos = (ux * vx + uy * vy) / (length * np.hypot(vx, vy))
            if abs(cos) < cos_tolerance:
                continue
            n += 1
            ux, uy = ux / length, uy / length
            nx, ny = -uy, ux
            ta = (ax - px) * ux + (ay - py) * uy
            tb = (bx - px) * ux + (by - py) * uy
            span = tb - ta
            safe = span if abs(span) > 1e-12 else 1e-12
            lam0 = min(max((0.0 - ta) / safe, 0.0), 1.0)
            lam1 = min(max((length - ta) / safe, 0.0), 1.0)
            lo, hi = min(lam0, lam1), max(lam0, lam1)
            weight = abs(span) * (hi - lo)
            offset = nx * px + ny * py
            for lam in (lo, hi):
                qx, qy = ax + lam * vx, ay + lam * vy
                res = nx * qx + ny * qy - offset
                ratio = res / tolerance
                w = weight * 0.5 / (1.0 + ratio * ratio)
                j0, j1, j2 = nx, ny, ny * (qx - x) - nx * (qy - y)
                h[0, 0] += w * j0 * j0
                h[0, 1] += w * j0 * j1
                h[0, 2] += w * j0 * j2
                h[1, 1] += w * j1 * j1
                h[1, 2] += w * j1 * j2
                h[2, 2] += w * j2 * j2
                g[0] += w * j0 * res
                g[1] += w * j1 * res
                g[2] += w * j2 * res
        h[1, 0], h[2, 0], h[2, 1] = h[0, 1], h[0, 2], h[1, 2]
        return n

    return normal


_normal = Compiled(_build)


def normal_equations(
    s1: Array, s2: Array, i: Array, k: Array, t: Array, cos_tolerance: float, tolerance: float
) -> tuple[Array, Array, int]:
    """The normal matrix and gradient of the point-to-line residuals of the pairs ``(i[r], k[r])``
    (S1's segment, S2's segment moved by ``t``: x, y and heading of S2 in S1's frame, the heading
    about S2's origin) that are near parallel (the cosine of their angle at least
    ``cos_tolerance`` in magnitude), each end of a moved segment's overlap with its partner weighted
    by half the overlap's length and a Cauchy factor of its distance (``tolerance``); and how many
    pairs were near parallel."""
    h, g = np.zeros((3, 3)), np.zeros(3)
    if len(i) == 0:
        return h, g, 0
    n = _normal(
        *(np.ascontiguousarray(a, dtype=np.float64) for a in (s1, s2)),
        *(np.ascontiguousarray(a, dtype=np.int64) for a in (i, k)),
        *(float(v) for v in np.asarray(t, dtype=np.float64).reshape(3)),
        float(cos_tolerance),
        float(tolerance),
        h,
        g,
    )
    return h, g, int(n)
