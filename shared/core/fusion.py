"""Matching chains and fusion (paper III-C: Algorithm 4 steps 24-30, Algorithm 5, greedy version).

Under the best transformation, matched segment pairs (positive matching value) are grouped into
*matching chains*: the connected components of the "matched with" relation between S1's and
S2^t's segments. Each chain is replaced by one polyline; unmatched segments are kept as they are.

Two choices the paper leaves open, made here:

- A pair enters a chain only when its segments are within ANGLEDIFFERENCETOLERANCE of parallel
  (and, for oriented maps, face the same way). A short segment near a corner can have a small
  positive matching value with both walls; letting it join them would fuse two perpendicular
  walls into one chain and cut the corner.
- A segment of S2^t left out of every chain but lying, end to end, within
  SEGMENTDISTANCETHRESHOLD * POINTDISTANCETOLERANCE of S1's segments is *absorbed*: that part
  of the environment is already in the map. Real scans hold many short pieces (clutter, range
  quantisation) whose directions are too noisy to chain; without this, a map built from a
  hundred scans keeps most of their segments and grows without bound.
- The greedy polyline (Algorithm 5 with each segment considered once) is built along the chain's
  main direction u: P0 joins the two farthest extremes; then, repeatedly, the chain segment
  farthest (distance d of III-B) from the polyline piece facing it is inserted in place of the
  vertices it spans, and joined to its neighbours, until every remaining segment is within
  FUSIONTOLERANCE or has been inserted once. The polyline runs along +u, so a fused wall keeps
  its side (free space on the left) when the chain's segments agree on it.
"""

from __future__ import annotations

import math

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.candidates import IntArray
from fleetmap.shared.core.geometry import Array, Transform2D, lengths, segment_distance, segment_points
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.transformation_value import matched_pairs, prepare
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def matching_chains(
    s1: Array, s2t: Array, i: IntArray, k: IntArray, params: IntegrationParams, oriented: bool
) -> list[tuple[IntArray, IntArray]]:
    """Algorithm 4, steps 24-30: the chains as (indices in S1, indices in S2^t)."""
    if len(i) == 0:
        return []
    u1 = s1[i, 2:4] - s1[i, 0:2]
    u2 = s2t[k, 2:4] - s2t[k, 0:2]
    cos = np.einsum("ij,ij->i", u1, u2) / (lengths(s1[i]) * lengths(s2t[k]))
    limit = math.cos(params.angle_difference_tolerance)
    parallel = cos >= limit if oriented else np.abs(cos) >= limit
    i, k = i[parallel], k[parallel]
    n1, n2 = len(s1), len(s2t)
    graph = coo_matrix((np.ones(len(i)), (i, n1 + k)), shape=(n1 + n2, n1 + n2))
    _, label = connected_components(graph, directed=False)
    chains = []
    members = np.unique(np.concatenate([i, n1 + k]))
    for lab in np.unique(label[members]):
        nodes = members[label[members] == lab]
        chains.append((nodes[nodes < n1], nodes[nodes >= n1] - n1))
    return chains


def chain_polyline(segments: Array, tolerance: float) -> Array:
    """Algorithm 5 (greedy) for one chain: the polyline's vertices ``(p, 2)``."""
    seg = np.asarray(segments, dtype=np.float64)
    d = seg[:, 2:4] - seg[:, 0:2]
    w = lengths(seg)
    # Unoriented chains may hold segments drawn either way: read them all like the longest.
    d = np.where((d @ d[int(np.argmax(w))] < 0)[:, None], -d, d)
    # Main direction: length-weighted mean of the segment directions (they are near parallel).
    u = (d / np.maximum(w, 1e-12)[:, None] * w[:, None]).sum(axis=0)
    if np.hypot(*u) < 1e-12:
        u = d[int(np.argmax(w))]
    u = u / np.hypot(*u)
    ends = seg.reshape(-1, 2)
    # Step 4: P0 joins the pair of farthest extremes.
    diff = ends[:, None, :] - ends[None, :, :]
    a, b = np.unravel_index(int(np.argmax((diff**2).sum(axis=2))), (len(ends), len(ends)))
    poly = [ends[a], ends[b]]
    if np.dot(poly[1] - poly[0], u) < 0:
        poly.reverse()
    used = np.zeros(len(seg), dtype=bool)
    while True:
        verts = np.array(poly)
        proj = verts @ u
        pieces = np.hstack([verts[:-1], verts[1:]])
        # Steps 5/10: the segment farthest from the polyline piece facing its middle.
        mids = 0.5 * (seg[:, 0:2] + seg[:, 2:4]) @ u
        facing = np.clip(np.searchsorted(proj, mids) - 1, 0, len(pieces) - 1)
        dist = segment_distance(seg, pieces[facing])
        dist[used] = -1.0
        j = int(np.argmax(dist))
        if dist[j] <= tolerance:
            break
        used[j] = True
        # Step 9: s replaces the vertices it spans and is joined to the rest.
        p, q = seg[j, 0:2], seg[j, 2:4]
        if np.dot(q - p, u) < 0:
            p, q = q, p
        lo, hi = float(p @ u), float(q @ u)
        keep_before = [v for v, t in zip(poly, proj, strict=True) if t < lo]
        keep_after = [v for v, t in zip(poly, proj, strict=True) if t > hi]
        poly = [*keep_before, p, q, *keep_after]
    return np.array(poly)


def fuse(m1: SegmentMap, m2: SegmentMap, transform: Transform2D, params: IntegrationParams | None = None) -> SegmentMap:
    """S_{1,2}: S1 and S2^t with each matching chain replaced by its polyline (Algorithm 5).

    The result is in S1's frame, unordered; it is oriented when both inputs are.
    """
    p = params or IntegrationParams()
    s1 = m1.segments
    s2t = transform.apply(m2.segments)
    oriented = m1.oriented and m2.oriented
    if len(s1) == 0 or len(s2t) == 0:
        return SegmentMap(np.vstack([s1, s2t]).reshape(-1, 4), ordered=False, oriented=oriented)
    prep = prepare(s1, s2t, oriented, p)
    i, k, _ = matched_pairs(prep, np.zeros(3), p)
    chains = matching_chains(s1, s2t, i, k, p, oriented)
    in_chain1 = np.zeros(len(s1), dtype=bool)
    in_chain2 = np.zeros(len(s2t), dtype=bool)
    out = []
    for c1, c2 in chains:
        in_chain1[c1] = True
        in_chain2[c2] = True
        verts = chain_polyline(np.vstack([s1[c1], s2t[c2]]), p.fusion_tolerance)
        pieces = np.hstack([verts[:-1], verts[1:]])
        out.append(pieces[lengths(pieces) > 1e-6])
    # Algorithm 5, step 2: the unmatched segments of both maps (less those S1 already holds).
    out.append(s1[~in_chain1])
    rest = s2t[~in_chain2]
    out.append(rest[~absorbed(s1, rest, p.segment_distance_threshold * p.point_distance_tolerance)])
    return SegmentMap(np.vstack(out), ordered=False, oriented=oriented)


ABSORB_SPACING = 0.05
"""Spacing (m) of the points checked along a segment that may be absorbed."""


def absorbed(s1: Array, s2: Array, distance: float) -> Array:
    """Which segments of s2 lie entirely (sampled every ABSORB_SPACING) within ``distance`` of s1."""
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(len(s2), dtype=bool)
    ref, _ = segment_points(s1, ABSORB_SPACING / 2)
    pts, owner = segment_points(s2, ABSORB_SPACING)
    d, _ = cKDTree(ref).query(pts, distance_upper_bound=distance + ABSORB_SPACING / 4)
    far = np.bincount(owner, weights=~np.isfinite(d), minlength=len(s2))
    return far == 0
