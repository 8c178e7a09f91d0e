"""The grid score's compiled lookups and the free grid's compiled march (shared/core/walllookup.py,
shared/core/freecells.py) against the numpy passes they replaced."""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.core import mapgrid
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.mapgrid import CHANNELS, Frame, free_grid, grid_scores, map_index
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.visibility import range_profile
from fleetmap.shared.core.walllookup import wall_sums

from tests.shared.test_mapgrid import WALLS


def _numpy_sums(hits, free, points, direction, weight, free_weight, t, origin, res, period):  # type: ignore[no-untyped-def]
    """The numpy passes :func:`wall_sums` replaced (mapgrid._lookups before decision record 073)."""
    c, s = np.cos(t[:, 2])[:, None], np.sin(t[:, 2])[:, None]
    x = c * points[:, 0] - s * points[:, 1] + t[:, 0, None]
    y = s * points[:, 0] + c * points[:, 1] + t[:, 1, None]
    i = np.floor((x - origin[0]) / res).astype(np.int64)
    j = np.floor((y - origin[1]) / res).astype(np.int64)
    on = (i >= 0) & (j >= 0) & (i < hits.shape[1]) & (j < hits.shape[2])
    i, j = np.where(on, i, 0), np.where(on, j, 0)
    layer = np.floor(np.mod(direction[None, :] + t[:, 2, None], period) / period * CHANNELS).astype(np.int64) % CHANNELS
    near = hits[layer, i, j] & on
    return near @ weight, (free[i, j] & on & ~near) @ free_weight


def test_the_compiled_lookups_sum_the_wall_length_the_numpy_passes_did() -> None:
    rng = np.random.default_rng(5)
    hits = rng.random((CHANNELS, 40, 30)) < 0.3
    free = rng.random((40, 30)) < 0.5
    # points that fall off the grid on every side too, walls of every direction, two weights
    points = rng.uniform(-1.0, 5.0, (300, 2))
    direction = rng.uniform(-math.pi, math.pi, 300)
    weight = np.full(300, 0.05)
    solid = np.where(rng.random(300) < 0.5, 0.05, 0.0)
    t = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(-4, 4, 50)])
    origin, res = np.array([0.2, -0.3]), 0.1
    for period in (math.pi, 2 * math.pi):
        for has_free in (True, False):
            got_hit, got_free = wall_sums(
                hits, free, points, direction, weight, solid, t, (*origin, res, period, CHANNELS, has_free)
            )
            want_hit, want_free = _numpy_sums(hits, free, points, direction, weight, solid, t, origin, res, period)
            # the same points counted: the same sums but for the order they were added in
            np.testing.assert_allclose(got_hit, want_hit, rtol=1e-12)
            np.testing.assert_allclose(got_free, want_free if has_free else 0.0, rtol=1e-12)
            assert want_hit.sum() > 10.0 and (not has_free or want_free.sum() > 10.0)  # not a test of zeros


def test_the_grid_score_of_a_map_on_itself_is_its_whole_wall_length_and_none_in_free_space() -> None:
    room = mapgrid.with_viewpoints(
        SegmentMap(WALLS, ordered=False, oriented=True), np.array([[2.0, 4.0, 0.0, -math.pi, math.pi]])
    )
    index = map_index(room, 0.1, 0.2, 0.2, 0.02)
    length = float(np.hypot(*(WALLS[:, 2:] - WALLS[:, :2]).T).sum())
    turned = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2]])  # the right pose, and one 90 degrees off
    hit, free = grid_scores(index, index, turned, fine=True)
    assert abs(hit[0] - length) < 0.1 * length and free[0] == 0.0
    assert hit[1] < 0.5 * length and free[1] > 1.0  # turned, its walls cross the room's seen free space


def _numpy_free_grid(segments, viewpoints, frame, margin, slope):  # type: ignore[no-untyped-def]
    """The numpy march :func:`free_grid` replaced, viewpoint by viewpoint (before record 073)."""
    free = np.zeros(frame.shape, dtype=bool)
    bins = mapgrid.PROFILE_BINS
    centre = (np.arange(bins) + 0.5) * (2 * math.pi / bins) - math.pi
    step = 0.7 * frame.resolution
    for x, y, th, b0, b1 in mapgrid.distinct_viewpoints(viewpoints):
        profile = range_profile(Transform2D(x, y, th).inverse().apply(segments), bins, mapgrid.PROFILE_WIDEN)
        profile[(centre < b0) | (centre > b1)] = 0.0
        reach = (profile - margin) / (1.0 + slope)
        count = np.where(reach > 0, np.floor(np.maximum(reach, 0) / step).astype(np.int64) + 1, 0)
        owner = np.repeat(np.arange(bins), count)
        pos = np.concatenate([np.arange(n) for n in count]) if count.sum() else np.zeros(0, np.int64)
        r = np.minimum((pos + 0.5) * step, reach[owner])
        a = centre[owner] + th
        i, j, on = frame.cells(x + r * np.cos(a), y + r * np.sin(a))
        free[i[on], j[on]] = True
    return free


def test_the_compiled_march_marks_the_cells_the_numpy_march_did() -> None:
    # the room seen from three places: all round, looking only ahead (a laser's half circle), and
    # from outside the room's walls
    viewpoints = np.array(
        [
            [2.0, 4.0, 0.3, -math.pi, math.pi],
            [6.0, 1.5, 2.0, -math.pi / 2, math.pi / 2],
            [-2.0, 3.0, 0.0, -math.pi, math.pi],
        ]
    )
    frame = Frame.around(np.vstack([WALLS.reshape(-1, 2), viewpoints[:, :2]]), 0.1)
    got = free_grid(WALLS, viewpoints, frame, 0.2, 0.02)
    assert np.array_equal(got, _numpy_free_grid(WALLS, viewpoints, frame, 0.2, 0.02))
    assert got.sum() > 1000  # most of the room: seen free
    # beyond the room's walls, where the L turns: seen from nowhere
    i, j, _ = frame.cells(np.array([6.0]), np.array([5.0]))
    assert not got[i[0], j[0]]
