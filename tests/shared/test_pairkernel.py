"""The compiled matching value (shared/core/pairkernel.py) against Algorithm 4's, geometry.matching_value."""

from __future__ import annotations

import numpy as np
from fleetmap.shared.core.geometry import matching_value
from fleetmap.shared.core.pairkernel import near_matching_values


def test_the_compiled_pairs_are_those_near_enough_with_a_positive_matching_value_to_the_bit():
    rng = np.random.default_rng(11)
    s1 = rng.uniform(-5, 5, (60, 4))
    s2 = rng.uniform(-5, 5, (50, 4))
    # collinear pairs, overlapping and apart, that only the intersection test tells apart;
    # parallel ones a little off the line; and one pair the same segment
    s1[:6] = [[0, 0, 2, 0], [0, 1, 2, 1], [0, 2, 1, 3], [3, 3, 4, 4], [-1, -1, 1, 1], [0, 5, 0, 6]]
    s2[:6] = [[1, 0, 3, 0], [3, 1, 4, 1], [0, 2.02, 1, 3.02], [3, 3, 4, 4], [2, 2, 3, 3], [0.01, 5, 0.01, 6]]
    i, k = (a.ravel() for a in np.indices((len(s1), len(s2))))
    mid1, mid2 = 0.5 * (s1[:, :2] + s1[:, 2:]), 0.5 * (s2[:, :2] + s2[:, 2:])
    half1 = 0.5 * np.hypot(*(s1[:, 2:] - s1[:, :2]).T)
    half2 = 0.5 * np.hypot(*(s2[:, 2:] - s2[:, :2]).T)
    d_max, tolerance, threshold, base = 0.3, 0.1, 3.0, 0.5
    got_i, got_k, got = near_matching_values(s1, s2, mid1, half1, mid2, half2, i, k, d_max, tolerance, threshold, base)
    near = ((mid1[i] - mid2[k]) ** 2).sum(axis=1) <= (half1[i] + half2[k] + d_max) ** 2
    mv = matching_value(s1[i[near]], s2[k[near]], tolerance, threshold, base)
    keep = mv > 0
    assert np.array_equal(got_i, i[near][keep]) and np.array_equal(got_k, k[near][keep])
    assert np.array_equal(got, mv[keep])  # the same arithmetic: the same values, not close ones
    # the collinear pairs: overlapping ones match, the pair apart along its line does not
    assert {(0, 0), (2, 2), (3, 3), (5, 5)} <= set(zip(got_i.tolist(), got_k.tolist(), strict=True))
    assert (1, 1) not in set(zip(got_i.tolist(), got_k.tolist(), strict=True))
    assert len(got) > 10  # random pairs matched too
