"""Merging a sequence of partial maps whose order is known (paper IV).

- :func:`sequential` (IV-A): S_{1..i} = INTEGRATE(S_{1..i-1}, S_i).
- :func:`tree` (IV-B): integrate neighbours level by level, with the S_i / S_{i+2} shortcut.
- :func:`pivot` (IV-C, Algorithm 6): integrate neighbours once, compose the transforms, and fuse
  into the growing map either the pair map S_{i-1,i} (``variant="pairs"``, Fig. 13a) or S_i itself
  (``variant="maps"``, the cleaner Fig. 13b).

Every method returns the merged map in S_1's frame and the pose of every input map in that frame
(None for a map that could not be placed). Where the paper assumes every integration succeeds,
fleetmap checks validity: a map that does not integrate with its predecessor is left unplaced and
the next one is integrated with the last map that was placed. The pivot method runs online, as a
robot agent grows its local map scan by scan, in :class:`fleetmap.shared.core.pivotmap.PivotMapBuilder`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.fusion import fuse
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Integration, integrate
from fleetmap.shared.core.pivotmap import PivotMapBuilder
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.errors import BadInput

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
