"""Merging a sequence of partial maps whose order is known (paper IV).

- :func:`sequential` (IV-A): S_{1..i} = INTEGRATE(S_{1..i-1}, S_i).
- :func:`tree` (IV-B): integrate neighbours level by level, with the S_i / S_{i+2} shortcut.
- :func:`pivot` (IV-C, Algorithm 6): integrate neighbours once, compose the transforms, and fuse
  into the growing map either the pair map S_{i-1,i} (``variant="pairs"``, Fig. 13a) or S_i itself
  (``variant="maps"``, the cleaner Fig. 13b).

Every method returns the merged map in S_1's frame and the pose of every input map in that frame
(None for a map that could not be placed). Where the paper assumes every integration succeeds,
fleetmap checks validity: a map that does not integrate with its predecessor is left unplaced and
the next one is integrated with the last map that was placed. :class:`PivotMapBuilder` is the pivot
method online, as a robot agent grows its local map scan by scan.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.errors import BadInput
from fleetmap.shared.fusion import fuse
from fleetmap.shared.geometry import Transform2D
from fleetmap.shared.integration import Integration, integrate
from fleetmap.shared.mapfile import SegmentMap

METHODS = ("sequential", "tree", "pivot")


@dataclass(frozen=True)
class SequenceResult:
    """The merged map (S_1's frame) and each input map's pose in it (None: not placed)."""

    map: SegmentMap
    poses: list[Transform2D | None]
    integrations: int
    """Calls to INTEGRATE (the paper counts them: n - 1, n(n - 1)/2, n - 1)."""


def _check(maps: list[SegmentMap]) -> None:
    if not maps:
        raise BadInput("maps", "no maps to merge")
    for k, m in enumerate(maps):
        if len(m) == 0:
            raise BadInput(f"map {k}", "the map is empty (no segments)")


def sequential(maps: list[SegmentMap], params: IntegrationParams | None = None) -> SequenceResult:
    """IV-A: the first two maps are integrated, then each next map with the growing map."""
    _check(maps)
    p = params or IntegrationParams()
    merged = maps[0]
    poses: list[Transform2D | None] = [Transform2D.identity()] + [None] * (len(maps) - 1)
    calls = 0
    for k in range(1, len(maps)):
        r = integrate(merged, maps[k], p)
        calls += 1
        if r.valid:
            poses[k] = r.transform
            merged = fuse(merged, maps[k], r.transform, p)
    return SequenceResult(merged, poses, calls)


@dataclass
class _Partial:
    """A partial map of the tree method: its frame is that of its first input map."""

    map: SegmentMap
    first: int
    poses: dict[int, Transform2D] = field(default_factory=dict)


def tree(
    maps: list[SegmentMap], params: IntegrationParams | None = None, shortcut_from_level: int | None = 1
) -> SequenceResult:
    """IV-B: S_{i,i+1} for every neighbour pair, then the same on the new sequence, to one map.

    With ``shortcut_from_level`` (None: never), from that level on S_i is first integrated with
    S_{i+2}: when that is valid, S_{i,i+2} replaces both S_{i,i+1} and S_{i+1,i+2} (at level >= 1
    S_{i+1} lies within S_i and S_{i+2}, so nothing is lost).
    """
    _check(maps)
    p = params or IntegrationParams()
    level = [_Partial(m, k, {k: Transform2D.identity()}) for k, m in enumerate(maps)]
    calls = 0
    depth = 0
    while len(level) > 1:
        nxt: list[_Partial] = []
        k = 0
        while k < len(level) - 1:
            if shortcut_from_level is not None and depth >= shortcut_from_level and k + 2 < len(level):
                r = integrate(level[k].map, level[k + 2].map, p)
                calls += 1
                if r.valid:
                    nxt.append(_join(level[k], level[k + 2], r, p))
                    k += 2
                    continue
            r = integrate(level[k].map, level[k + 1].map, p)
            calls += 1
            if r.valid:
                nxt.append(_join(level[k], level[k + 1], r, p))
            elif nxt and level[k].first in nxt[-1].poses:
                # fleetmap: S_{k+1} did not integrate with S_k alone; try the partial map just built,
                # which holds S_k and more context, rather than losing S_{k+1}.
                r = integrate(nxt[-1].map, level[k + 1].map, p)
                calls += 1
                nxt[-1] = _join(nxt[-1], level[k + 1], r, p) if r.valid else nxt[-1]
                if not r.valid:
                    nxt.append(level[k])
            else:
                nxt.append(level[k])
            k += 1
        level = nxt  # one shorter at least: the loop ends
        depth += 1
    root = level[0]
    poses: list[Transform2D | None] = [root.poses.get(k) for k in range(len(maps))]
    return SequenceResult(root.map, poses, calls)


def _join(a: _Partial, b: _Partial, r: Integration, p: IntegrationParams) -> _Partial:
    """Fuse partial map b into a (b's frame placed by ``r``); a's pose estimates win on overlap."""
    poses = dict(a.poses)
    for k, pose in b.poses.items():
        poses.setdefault(k, r.transform.compose(pose))
    return _Partial(fuse(a.map, b.map, r.transform, p), a.first, poses)


def pivot(maps: list[SegmentMap], params: IntegrationParams | None = None, variant: str = "maps") -> SequenceResult:
    """IV-C, Algorithm 6: the pivot method; ``variant`` "maps" (fuse S_i) or "pairs" (fuse S_{i-1,i})."""
    if variant not in ("maps", "pairs"):
        raise BadInput("variant", f"expected 'maps' or 'pairs', got {variant!r}")
    _check(maps)
    p = params or IntegrationParams()
    builder = PivotMapBuilder(p, fuse_pairs=variant == "pairs")
    poses: list[Transform2D | None] = []
    for m in maps:
        step = builder.add(m)
        poses.append(step.pose)
    return SequenceResult(builder.map, poses, builder.integrations)


@dataclass(frozen=True)
class PivotStep:
    """What adding one map to a :class:`PivotMapBuilder` did."""

    pose: Transform2D | None
    """The new map's pose in the built map's frame (None: it did not integrate)."""
    integration: Integration | None
    """INTEGRATE(previous placed map, new map); None for the first map."""


class PivotMapBuilder:
    """The pivot method online (Algorithm 6): add maps one at a time, each integrated with the
    previous placed one, its transform composed with the previous pose, and fused once.

    The built map's frame is the first map's. With ``use_map`` (fleetmap, beyond Algorithm 6), a
    map that does not integrate validly with the previous one is integrated with the whole map
    built so far, which has more context (the previous scan may have been blocked by a person, or
    turned away). A map that integrates with neither is not fused and gets no pose; the next map
    is integrated with the last placed one. (An agent takes failures as the sign of a kidnap and
    starts a new builder: a new epoch.)
    """

    def __init__(self, params: IntegrationParams | None = None, fuse_pairs: bool = False, use_map: bool = True) -> None:
        self.params = params or IntegrationParams()
        self.fuse_pairs = fuse_pairs
        self.use_map = use_map
        self.map = SegmentMap(np.zeros((0, 4)), ordered=False, oriented=True)
        self.poses: list[Transform2D | None] = []
        self.integrations = 0
        self._last: SegmentMap | None = None
        self._last_pose = Transform2D.identity()

    def add(self, m: SegmentMap) -> PivotStep:
        if self._last is None:
            self._last = m
            self.map = SegmentMap(m.segments.copy(), ordered=False, oriented=m.oriented)
            self.poses.append(Transform2D.identity())
            return PivotStep(Transform2D.identity(), None)
        r = integrate(self._last, m, self.params)
        self.integrations += 1
        if r.valid:
            # Step 4: t_{1,i} = t_{1,i-1} composed with t_{i-1,i}.
            pose = self._last_pose.compose(r.transform)
        elif self.use_map and len(self.poses) > 1:
            r = integrate(self.map, m, self.params)
            self.integrations += 1
            if not r.valid:
                self.poses.append(None)
                return PivotStep(None, r)
            pose = r.transform
            r = integrate(self._last, m, self.params) if self.fuse_pairs else r
        else:
            self.poses.append(None)
            return PivotStep(None, r)
        if self.fuse_pairs:
            # Fig. 13a: fuse S_{i-1,i} (in S_{i-1}'s frame) placed by t_{1,i-1}.
            pair = fuse(self._last, m, r.transform, self.params)
            self.map = fuse(self.map, pair, self._last_pose, self.params)
        else:
            # Fig. 13b, steps 5-6: fuse S_i itself, placed by t_{1,i}.
            self.map = fuse(self.map, m, pose, self.params)
        self._last, self._last_pose = m, pose
        self.poses.append(pose)
        return PivotStep(pose, r)
