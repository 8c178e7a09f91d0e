"""Matching chains and fusion (Algorithm 5)."""

from __future__ import annotations

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.fusion import chain_polyline, fuse
from fleetmap.shared.core.geometry import lengths, point_segment_distance
from fleetmap.shared.core.integration import integrate
from fleetmap.shared.core.segmap import SegmentMap

from tests.shared.test_integration import PAIRS


def _max_distance(points: np.ndarray, segments: np.ndarray) -> float:
    return float(point_segment_distance(points[:, None, :], segments[None, :, :]).min(axis=1).max())


def test_fusion_keeps_the_geometry_within_fusion_tolerance_plus_40mm_and_reduces_segments() -> None:
    p = IntegrationParams()
    for a, b, _ in PAIRS[:4]:
        r = integrate(a, b, p)
        fused = fuse(a, b, r.transform, p)
        originals = np.vstack([a.segments, r.transform.apply(b.segments)])
        assert len(fused) < len(originals)
        # Every original extreme lies near the fused map (III-D: greedy error bound) ...
        assert _max_distance(originals.reshape(-1, 2), fused.segments) <= p.fusion_tolerance + 0.040
        # ... and the fused map adds nothing far from the originals.
        samples = np.vstack(
            [fused.segments[:, 0:2], fused.segments[:, 2:4], 0.5 * (fused.segments[:, 0:2] + fused.segments[:, 2:4])]
        )
        assert _max_distance(samples, originals) <= p.fusion_tolerance + 0.040
        assert fused.oriented and not fused.ordered


def test_a_chain_of_collinear_pieces_becomes_one_segment() -> None:
    chain = np.array([[0, 0, 1.0, 0.004], [0.9, -0.003, 2.0, 0.0], [1.5, 0.002, 3.0, 0.0]])
    poly = chain_polyline(chain, 0.015)
    assert len(poly) == 2
    assert abs(poly[0, 0]) < 1e-9 and abs(poly[1, 0] - 3.0) < 1e-9


def test_a_bent_chain_keeps_its_bend_and_direction() -> None:
    chain = np.array([[0, 0, 2.0, 0.0], [2.0, 0.0, 4.0, 0.3], [0.5, 0.005, 1.8, 0.005]])
    poly = chain_polyline(chain, 0.015)
    segs = np.hstack([poly[:-1], poly[1:]])
    assert _max_distance(np.array([[2.0, 0.0], [4.0, 0.3], [0.0, 0.0]]), segs) < 0.02
    assert (segs[:, 2] > segs[:, 0]).all()  # runs along +x like the chain


def test_maps_that_do_not_overlap_are_kept_whole() -> None:
    a = SegmentMap(np.array([[0, 0, 1, 0.0]]), oriented=True)
    b = SegmentMap(np.array([[5, 5, 6, 5.0]]), oriented=True)
    from fleetmap.shared.core.geometry import Transform2D

    fused = fuse(a, b, Transform2D.identity())
    assert len(fused) == 2 and np.isclose(lengths(fused.segments).sum(), 2.0)
