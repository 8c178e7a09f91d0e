"""The fleet's pose graph: submaps chained by each robot's tracking, joined by the paper's integrations.

Nodes are submaps (``<robot>/<epoch>/<submap>``). Edges are of two kinds:

- **links**: a robot's own chain of consecutive submaps, measured by its tracking, with the
  tracking's covariance (:class:`~fleetmap.shared.io.messages.SubmapLink`); never rejected;
- **integrations**: the paper's pose-free integration (Algorithms 1-4) between submaps of
  different robots, or non-consecutive submaps of one robot (a loop), or, for a submap the fleet
  has placed, its walls registered near where the graph predicts them
  (:func:`~fleetmap.shared.core.near.align_near`); each with its transformation value, validity
  and how firmly its walls fix it.

The merge order nobody gave is read off the graph: a maximum spanning forest (links first, then
valid integrations by value), every other valid integration checked against its cycle, a tree
integration that more cycles accuse than support rejected. Map files (``fleetmap merge``) are
nodes with no links, solved the same way. The
cycle check allows what the path can have drifted: the base tolerance for each integration on the
path, and three standard deviations of what its links' covariances add up to, so a long loop of a
robot's own submaps closes and a wrong match across a room does not. Each component's poses are
then refined together by robust least squares over SE(2) (GTSAM's Levenberg-Marquardt: links as
their covariance says, integrations through a Cauchy loss, the anchor fixed), and an integration
that still disagrees with the refined poses by more than one integration's base tolerance (no
drift term: the refined poses already spread the drift) is rejected and the
component solved again, the grossest first
(:meth:`~fleetmap.merger.refinement.RefinedGraph._grossest`): only edges that agree with the graph
count, so one wrong integration cannot move a map, nor take right ones out with it. Each
component is one global map; its walls are the submaps' fused one segment per stretch of wall
(:class:`~fleetmap.shared.core.walls.WallMap`).

A step costs what it adds (issue 49): the forest, its verdicts and the refined poses are kept
from solve to solve, and a step that only adds submaps, their links and integrations that close
loops or that the groups do not bear out, or does such an integration again as its submaps grow,
carries them on (:meth:`PoseGraph._kept_solve`); the rest solves the whole graph again
(:meth:`PoseGraph._whole_solve`).

The parts, each a layer of the class: the robots' links and their drift,
:mod:`fleetmap.merger.chains`; what a pair of submaps says of a join, :mod:`fleetmap.merger.pairs`;
how a join of two groups is judged, :mod:`fleetmap.merger.joins`; the spanning forest and its
cycle checks, :mod:`fleetmap.merger.spanning` (its paths and their drift, and the state kept
between solves, :mod:`fleetmap.merger.forest`); the refinement, :mod:`fleetmap.merger.refinement`.
This module solves: the kept forest carried on, or the whole graph, and the global maps ranked
and given their walls.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from fleetmap.merger.chains import _chain_of, _map_file
from fleetmap.merger.forest import KeptForest
from fleetmap.merger.graph import Component, Edge, MergeResult, _bfs_order, _unite
from fleetmap.merger.joins import JOIN_HYPOTHESES, _within
from fleetmap.merger.pairs import VERDICT_VERSIONS
from fleetmap.merger.refinement import RefinedGraph
from fleetmap.merger.spanning import _robot_of
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.kalman_fusion import offset_information
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.simplify import SIMPLIFY_TOLERANCE
from fleetmap.shared.core.tracking import MAX_CORRESPONDENCE, REACH_ROTATION, RESIDUAL_SIGMA, SAMPLE_SPACING
from fleetmap.shared.core.validity import VALID_REFUTE_VIOLATION
from fleetmap.shared.core.walls import WallMap

log = logging.getLogger(__name__)

MAX_REJECTION_ROUNDS = 5
"""The refined poses are solved again, without the integrations they disagree with, at most this many
times (one round instead: the warehouse's error 0.010 -> 0.014 m; docs/decisions/002-pose-graph.md).
Each round but the last leaves out the grossest half
(:meth:`~fleetmap.merger.refinement.RefinedGraph._grossest`); 12 rounds, to halve from 2^11
tolerances (600 m) down to one, map freiburg-campus-corrected cut in 2 and 4 as 5 do (docs/decisions/086)."""


class PoseGraph(RefinedGraph):
    """Submaps, their links and their integrations; :meth:`solve` gives the global maps."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # as ChainGraph's
        super().__init__(*args, **kwargs)
        self._walls_now: dict[tuple[object, ...], tuple[tuple[SegmentMap, ...], Array]] = {}
        """The walls of each component of the last solve, with its maps (:meth:`_walls`)."""
        self._last_walls = self._walls_now
        self._with_walls_now: dict[int, tuple[Component, Component]] = {}
        """Each component of the last solve with its walls, by the component without (:meth:`_fused`)."""
        self._with_walls = self._with_walls_now
        self._ranks: dict[int, tuple[Component, tuple[int, int, int]]] = {}
        """Each component's rank for the global map (:meth:`_global_first`), by the component."""
        self.whole_solves = 0
        self.kept_solves = 0
        """Solves of the whole graph, and solves that carried the last one on."""
        self._settled = -1
        """The :attr:`edits` when the last solve's forest held every edge (none changed since: no second look)."""

    def _work(self, key: str, m: SegmentMap) -> SegmentMap:
        # a submap's walls are already one segment per stretch of wall (fleetmap.shared.core.walls);
        # a map file (a pivot local map: many short pieces of each wall) is simplified as the map
        # graph simplifies it
        return super()._work(key, m) if _map_file(key) else m

    def solve(self, fuse_maps: bool = True) -> MergeResult:
        """The global maps: the forest and the refined poses kept from the last solve where the
        step only added to them (:meth:`_kept_solve`), else found again from the whole graph
        (:meth:`_whole_solve`)."""
        self._last_walls, self._walls_now = self._walls_now, {}
        self._with_walls, self._with_walls_now = self._with_walls_now, {}
        # no link or integration added, changed or gone: a quiet step (new versions of the active
        # submaps, at most) looks at no edge, not every edge in the graph
        quiet = self._kept is not None and self.edits == self._settled and self._ambiguity_stands(self._kept)
        kept = self._kept_solve(None) if quiet else None
        if kept is None:  # (a kept solve that fails has changed its forest: the whole solve then)
            links, priors, valid = self._edges_to_solve()
            if not quiet and self._kept is not None and not priors:
                kept = self._kept_solve((links, valid))
        if kept is None:
            self.whole_solves += 1
            components, tree, loops, rejected = self._whole_solve(links, valid, priors)
            self._settled = -1 if priors else self.edits
        else:
            self.kept_solves += 1
            components, tree, loops, rejected = kept
            self._settled = self.edits
        if fuse_maps:  # the walls of the final round's components only
            edges = _edges_by_component(components, [*tree, *loops])
            components = [self._fused(c, edges[i]) for i, c in enumerate(components)]
        poses: dict[str, Transform2D | None] = {k: None for k in self.keys}
        for c in components:
            if len(c.members) > 1:
                poses.update(c.poses)
        return MergeResult(poses, components, tree, loops, rejected)

    def _kept_solve(
        self, edges: tuple[list[Edge], list[Edge]] | None
    ) -> tuple[list[Component], list[Edge], list[Edge], list[Edge]] | None:
        """The last solve's forest and poses carried on by what this step added, where that alone
        decides the answer (issue 49: a step costs what it adds); None where the whole graph must
        be solved again (:meth:`_whole_solve`).

        Kept, the forest grows as Kruskal's would from its new edges, most valuable first: a new
        submap hangs from its robot's chain by its link (a leaf: the rooted forest grows by one
        node, the chain's refined poses stand and the leaf's follows from its link, exactly the
        least-squares answer), an integration within one tree is checked against the tree's path
        (a loop that closes: the component is refined again from its last poses), and one between
        two trees that the groups do not bear out is refused, as the whole solve would. Everything
        else that could change the answer calls for the whole solve: a submap or an edge gone, a
        link, a tree edge, an ambiguous integration or a cycle's accuser changed (an integration
        that closed a loop or was refused as a join between groups still apart, done again, is
        taken again as a new edge: :func:`_new_edges`), a join taken, a cycle that does not close,
        a link between two grown groups, a join or a culprit that a grown group may now decide
        otherwise, an integration the refined poses now disagree with or agree with again. A step
        that adds nothing but new versions of submaps changes no pose."""
        kept = self._kept
        assert kept is not None
        new: list[Edge] = []
        if edges is not None:  # (None: the graph's edges are those the forest was found to hold)
            if any(k not in self._nodes for k in kept.versions):
                return None
            links, valid = edges
            taken = {e.key(): e for e in links}
            aside = 0
            for e in valid:
                key = e.key()
                if key in kept.aside:
                    if kept.aside[key] is not e and kept.aside[key] != e:
                        return None  # integrated again: the whole solve judges it
                    aside += 1
                    continue
                taken[key] = e
            found = _new_edges(kept, taken)
            if found is None or aside != len(kept.aside):
                return None  # an edge left, or one changed that only the whole solve can take
            new = found
        grown = {k for k, n in self._nodes.items() if kept.versions.get(k) != n.version}
        if not new and not grown:
            return self._kept_result(kept)
        root, rel, members, adjacency, forest = kept.root, kept.rel, kept.members, kept.adjacency, kept.forest
        for k in self._nodes:
            if k not in root:
                root[k], rel[k], members[k], adjacency[k] = k, Transform2D.identity(), [k], []
                forest.add_root(k)
        order = {k: n.order for k, n in self._nodes.items()}
        new.sort(key=lambda e: (-e.value, order[e.a], order[e.b]))
        touched: set[str] = set()  # the groups this step changed
        refine: set[str] = set()  # ... and of those, the ones whose cycles changed
        for e in new:
            if not self._kept_edge(kept, e, touched, refine):
                return None
        if any(root[e.a] == root[e.b] for e in kept.apart):
            return None  # a new submap's link put two submaps in one tree that an integration did not join
        touched.update(root[k] for k in grown)
        if not self._kept_verdicts_stand(kept, touched, grown):
            return None
        for r in sorted(touched):  # in a fixed order: a refinement warm-starts the next solve
            if not self._kept_component(kept, r, r in refine):
                return None
        kept.edges.update((e.key(), e) for e in new)
        kept.versions = {k: n.version for k, n in self._nodes.items()}
        return self._kept_result(kept)

    def _kept_edge(self, kept: KeptForest, e: Edge, touched: set[str], refine: set[str]) -> bool:
        """One new edge taken into the kept forest as :meth:`_kruskal` would take it, the groups it
        changed added to ``touched`` (and to ``refine`` where it closed a cycle); False where only
        the whole solve can decide it: a join, a cycle that does not close, a link between two grown
        groups."""
        root, rel, members, adjacency, forest = kept.root, kept.rel, kept.members, kept.adjacency, kept.forest
        ra, rb = root[e.a], root[e.b]
        if ra != rb:
            if not e.valid:
                kept.apart.append(e)  # an ambiguous integration joins nothing (_kruskal)
                return True
            if not e.link:
                if self._join_accepted(e, members[ra], members[rb], rel, adjacency):
                    return False  # a join: the whole solve judges it with its rivals
                kept.conflicts.append(e)
                kept.rejected.append(e)
                kept.apart.append(e)
                return True
            if len(members[ra]) > 1 and len(members[rb]) > 1:
                return False
            leaf = e if len(members[rb]) == 1 else e.reversed()
            _unite(e, root, rel, members, kept.tree, adjacency)
            forest.add_leaf(leaf, self._link_covariances)
            kept.components.pop(rb if root[e.a] == ra else ra, None)  # the group that joined the other
            touched.add(root[e.a])
            return True
        touched.add(ra)
        if e.link:
            kept.loops.append(e)
            refine.add(ra)
            return True
        tol_t, tol_r = self._tolerance_between(forest, e.a, e.b)
        predicted = rel[e.a].inverse().compose(rel[e.b])
        if e.valid:
            if not _within(predicted, e.transform, tol_t, tol_r):
                return False  # a cycle that does not close: the culprit rule decides
            kept.loops.append(e)
            refine.add(ra)
            return True
        hypotheses = [e, *(replace(e, transform=t) for t in e.rivals[: JOIN_HYPOTHESES - 1])]
        agreeing = [h for h in hypotheses if _within(predicted, h.transform, tol_t, tol_r)]
        if len(agreeing) == 1:
            kept.loops.append(replace(agreeing[0], valid=True))
            refine.add(ra)
        return True

    def _kept_verdicts_stand(self, kept: KeptForest, touched: set[str], grown: set[str]) -> bool:
        """Whether what the forest decided about the groups this step changed stands: the joins
        it refused still fail, its joins still hold (:meth:`_kept_joins_hold`, ``grown``: the
        submaps new or with a new version), and no culprit appears (each decided as
        :meth:`_kruskal` and :meth:`_forest` decide it, the verdicts kept where nothing new bears
        on them: :meth:`_kept_verdict`)."""
        root, members, rel, adjacency = kept.root, kept.members, kept.rel, kept.adjacency
        kept.unlooked.update(grown)
        for e in kept.apart:
            ra, rb = root[e.a], root[e.b]
            regrown = ra != rb and (ra in touched or rb in touched)
            if regrown and e.valid and not e.link and self._join_accepted(e, members[ra], members[rb], rel, adjacency):
                return False
        for r in sorted(touched):
            group = set(members[r])
            joins = [t for t in kept.tree if not t.link and t.a in group]
            if not joins:
                continue
            if not self._kept_joins_hold(kept, r, joins, grown):
                return False
            # new loops only add support, and a new leaf is on no cycle: the vote can find a culprit
            # only where the last one had a candidate that its accusers' groups did not bear out
            accusers = [e for e in kept.conflicts if e.a in group and e.b in group] if kept.contested else []
            if accusers:
                loops = [e for e in kept.loops if e.a in group]
                if self._culprit(joins, loops, accusers, adjacency, kept.forest) is not None:
                    return False
        return True

    def _kept_joins_hold(self, kept: KeptForest, r: str, joins: list[Edge], grown: set[str]) -> bool:
        """Whether the joins of group ``r``'s tree still hold now that the ``grown`` submaps (new,
        or with a new version) are in it. As a join's verdict is kept while its two groups stay
        the same (:meth:`_join_holds`), the group's joins are looked at again when a new submap
        joins it, and then only the pairs that its submaps new or grown since the last look make
        across a join are new evidence. Each is looked at (:meth:`_look`) where the tree puts it;
        a pair that puts ``VALID_REFUTE_VIOLATION`` of wall in the other's seen free space is
        weighed in (:meth:`holds_with`), and where that cannot say, the join is judged again
        whole (:meth:`_failed_join`). Which side of a join a submap is on is read off the rooted
        forest (:attr:`~fleetmap.merger.forest.RootedForest.joins_above`), so a step costs what
        its fresh submaps meet, not what the group holds."""
        root, looked = kept.root, kept.looked
        if not any(k not in kept.versions and root[k] == r for k in grown):
            return True  # the same group: its joins' verdicts stand
        # new submaps, and those grown by as many versions as a pair's verdict is kept for
        # (:meth:`_pair_verdict`: what an active submap's walls bore out they still bear out)
        fresh = [
            k
            for k in sorted(kept.unlooked)
            if root[k] == r and (k not in looked or self._nodes[k].version - looked[k] >= VERDICT_VERSIONS)
        ]
        for k in fresh:
            looked[k] = self._nodes[k].version
        kept.unlooked.difference_update(fresh)
        forest, group = kept.forest, kept.members[r]
        above, at = forest.joins_above, forest.at
        centres, radii = self.discs_at(group, at)
        index = {k: i for i, k in enumerate(group)}
        rows = [index[k] for k in fresh]
        gap = np.hypot(centres[rows, None, 0] - centres[None, :, 0], centres[rows, None, 1] - centres[None, :, 1])
        meet = gap <= radii[rows, None] + radii[None, :]
        pairs = {
            (f, g) if f < g else (g, f)
            for f, row in zip(fresh, meet, strict=True)
            for g in (group[j] for j in np.flatnonzero(row).tolist())
            if g != f
        }
        # a pair whose chains can have drifted farther than registration reaches says nothing
        # either way (:meth:`_join_pairs`)
        reach_t, reach_r = MAX_CORRESPONDENCE, REACH_ROTATION
        drifts = {(f, g): forest.drift(f, g) for f, g in sorted(pairs) if above[f] != above[g]}  # across a join
        within = [p for p, (_, drift_t, drift_r) in drifts.items() if drift_t <= reach_t and drift_r <= reach_r]
        refute = VALID_REFUTE_VIOLATION
        for e in joins:
            key = e.key()
            a_far = key in above[e.a]  # whether e.a is on the far side of e from the root
            suspicious = []
            for f, g in within:
                if (key in above[f]) == (key in above[g]):
                    continue  # both on one side
                a, b = (f, g) if (key in above[f]) == a_far else (g, f)
                implied = at[a].inverse().compose(at[b])
                if self._look(a, b, implied)[1] >= refute:
                    suspicious.append((a, b, implied))
            if not suspicious:
                continue
            holds = self.holds_with(e, suspicious, at, forest.drift)
            if holds is None:
                holds = self._failed_join([e], kept.adjacency, kept.rel) is None
            if not holds:
                return False
        return True

    def _kept_component(self, kept: KeptForest, r: str, cycles_changed: bool) -> bool:
        """Group ``r``'s component after this step: its kept poses, the new leaves' from their
        links, or, where its cycles changed, refined again from them; False where the refined
        poses now disagree with an integration taken or agree with one left out."""
        group = kept.members[r]
        anchor = self._pick_anchor(group)
        held = kept.components.get(r)
        if held is not None and held.anchor == anchor and not cycles_changed and len(held.members) == len(group):
            return True  # new versions of its submaps only: the same poses (the tree spans the group)
        order = _bfs_order(kept.adjacency, anchor)
        if held is not None and held.anchor == anchor and not cycles_changed:
            poses = dict(held.poses)
            for k in order:  # the leaves hung from the chain since: breadth first, parents first
                if k not in poses:
                    parent = kept.forest.parent[k]
                    assert parent is not None
                    poses[k] = poses[parent.a].compose(parent.transform)
        else:
            in_group = set(group)
            tree = [e for e in kept.tree if e.a in in_group]
            cycle_edges = [e for e in kept.loops if e.a in in_group]
            poses, off = self._refined(anchor, order, kept.adjacency, tree + cycle_edges, bool(cycle_edges))
            if off:
                return False
            tol_t, tol_r = self._tolerance(1)
            for e in kept.aside.values():
                if e.a in in_group and e.b in in_group and self._agrees(e, poses, tol_t, tol_r):
                    return False
        kept.components[r] = Component(anchor, tuple(order), poses, np.zeros((0, 4)))
        return True

    def _kept_result(self, kept: KeptForest) -> tuple[list[Component], list[Edge], list[Edge], list[Edge]]:
        # copies: the kept lists grow with the next steps, and a result once given stays as it was
        components = self._global_first(list(kept.components.values()))
        return components, list(kept.tree), list(kept.loops), list(kept.rejected)

    def _whole_solve(
        self, links: list[Edge], valid: list[Edge], priors: Sequence[Edge] = ()
    ) -> tuple[list[Component], list[Edge], list[Edge], list[Edge]]:
        """The forest from every edge, the components refined, and an integration the refined
        poses disagree with left out and all found again (see the module); kept for the next
        solve (:class:`~fleetmap.merger.forest.KeptForest`)."""
        order = {k: n.order for k, n in self._nodes.items()}
        valid = sorted(valid, key=lambda e: (-e.value, order[e.a], order[e.b]))
        disagreeing: set[tuple[str, str]] = set()
        self._begin_refinement()
        for n in range(MAX_REJECTION_ROUNDS):
            built = self._forest(links, [e for e in valid if e.key() not in disagreeing], priors)
            components, off = self._refined_components(built.tree, built.loops)
            components = self._global_first(components)
            if not off:
                break
            if n < MAX_REJECTION_ROUNDS - 1:
                off = self._grossest(components, off)
            for e in off:
                log.debug("rejecting edge %s-%s: the refined poses disagree with it", e.a, e.b)
            disagreeing.update(e.key() for e in off)
        rejected = built.rejected + [e for e in valid if e.key() in disagreeing and e.valid]
        taken = {e.key(): e for e in (*links, *priors)}
        taken.update((e.key(), e) for e in valid if e.key() not in disagreeing)
        built.aside = {e.key(): e for e in valid if e.key() in disagreeing or e.key() in built.excluded}
        for key in built.aside:
            taken.pop(key, None)
        built.edges = taken
        built.versions = {k: n.version for k, n in self._nodes.items()}
        built.rejected = rejected
        built.components = {built.root[c.anchor]: c for c in components}
        self._kept = built
        return components, list(built.tree), list(built.loops), list(rejected)

    def _global_first(self, components: list[Component]) -> list[Component]:
        """The components, the global map first: the component of the most robots, then of the
        most robots' epochs, then of the most submaps (one robot's many epochs, a flood of its own
        key, never outweigh the fleet's map)."""
        held, self._ranks = self._ranks, {}
        for c in components:  # kept by component: most are as the last solve left them
            rank = held.get(id(c))
            if rank is None or rank[0] is not c:
                robots, chains = {_robot_of(k) for k in c.members}, {_chain_of(k) for k in c.members}
                rank = (c, (-len(robots), -len(chains), -len(c.members)))
            self._ranks[id(c)] = rank
        ranks = Counter(rank for _, rank in self._ranks.values())

        def key(c: Component) -> tuple[int, int, int, float]:
            rank = self._ranks[id(c)][1]
            # the walls' length (their submaps' versions change it) only where the rest ties
            return (*rank, -sum(self._nodes[k].map.total_length for k in c.members) if ranks[rank] > 1 else 0.0)

        return sorted(components, key=key)

    def _fused(self, c: Component, edges: list[Edge]) -> Component:
        """A component with its walls (:meth:`_walls`; ``edges``: its tree and loops): the last
        solve's same object where neither its submaps and poses nor its walls changed."""
        walls = self._walls(c, edges)
        held = self._with_walls.get(id(c))
        if held is None or held[0] is not c or held[1].segments is not walls:
            held = (c, replace(c, segments=walls))
        self._with_walls_now[id(c)] = held
        return held[1]

    def _walls(self, c: Component, edges: list[Edge]) -> Array:
        """The component's walls: every member's at its pose, one segment per stretch of wall; the
        last solve's where the component is the same (the same maps in the same order at poses
        equal to the bit: a component no step touched).

        ``wall_fusion`` weighted: where several submaps see one wall, each copy weighs by the
        information on its offset (Ballesta et al. 2009, Section 4, eqs. 6-8, as
        :func:`~fleetmap.shared.core.kalman_fusion.offset_information` gives it to the wall's line
        fit): from its submap's pose covariance in the solved graph (:meth:`pose_covariances`) and
        its segment's fit, a submap's segment carrying none of its own: ``RESIDUAL_SIGMA`` off the
        wall every ``SAMPLE_SPACING`` along it, as the tracking registers scans on it."""
        order, poses = list(c.members), c.poses
        maps = tuple(self._nodes[k].map for k in order)
        key = tuple((k, id(m), poses[k].x, poses[k].y, poses[k].theta) for k, m in zip(order, maps, strict=True))
        held = self._last_walls.get(key)
        if held is None or not all(a is b for a, b in zip(held[0], maps, strict=True)):
            walls = WallMap(SIMPLIFY_TOLERANCE)
            weighted = self.merge.wall_fusion == "weighted" and len(order) > 1
            covariances = self.pose_covariances(c.anchor, poses, edges) if weighted else None
            sigma, spacing = RESIDUAL_SIGMA, SAMPLE_SPACING
            for k, m in zip(order, maps, strict=True):
                weights = (
                    None
                    if covariances is None
                    else offset_information(m.segments, poses[k], covariances[k], sigma, spacing)
                )
                walls.add(poses[k].apply(m.segments), weights)
            held = (maps, walls.segments)
        self._walls_now[key] = held
        return held[1]


def _new_edges(kept: KeptForest, taken: dict[tuple[str, str], Edge]) -> list[Edge] | None:
    """The edges ``taken`` (the step's links and integrations, by key) that the kept forest must
    take as new: those it has not seen, and those done again as their submaps grew where their last
    version closed a loop, was a join refused between groups still apart, or said nothing (removed
    from the forest's lists: the join is refused again, the cycle closes, or the whole solve
    decides). None where an edge left, or a link, an ambiguous integration or one the forest
    decided by (:func:`_deciding`) changed: only the whole solve can take those."""
    new: list[Edge] = []
    redone: set[tuple[str, str]] = set()
    fixed: set[tuple[str, str]] | None = None
    for key, e in taken.items():
        held = kept.edges.get(key)
        if held is None:
            new.append(e)
        elif held is not e and held != e:
            fixed = _deciding(kept) if fixed is None else fixed
            if e.link or not e.valid or key in fixed:
                return None
            redone.add(key)
    if len(taken) - len(new) != len(kept.edges):
        return None
    if redone:
        for name in ("loops", "conflicts", "apart", "rejected"):
            setattr(kept, name, [e for e in getattr(kept, name) if e.key() not in redone])
    return new + [taken[key] for key in sorted(redone)]


def _deciding(kept: KeptForest) -> set[tuple[str, str]]:
    """The integrations whose new version only the whole solve can take: the forest's tree edges,
    the cycles that did not close within a tree (the culprit rule counts them), and joins refused
    between two groups that have since become one. The others (loops that closed, joins refused
    between groups still apart, integrations that said nothing) the kept forest takes again as new
    edges (:meth:`PoseGraph._kept_solve`)."""
    root = kept.root
    apart = {e.key() for e in kept.apart if root[e.a] != root[e.b]}
    refused = {e.key() for e in (*kept.conflicts, *kept.rejected, *kept.apart)} - apart
    return {e.key() for e in kept.tree} | refused


def _edges_by_component(components: list[Component], edges: list[Edge]) -> list[list[Edge]]:
    """The edges within each component, in the components' order."""
    where = {k: i for i, c in enumerate(components) for k in c.members}
    out: list[list[Edge]] = [[] for _ in components]
    for e in edges:
        i = where.get(e.a)
        if i is not None and where.get(e.b) == i:
            out[i].append(e)
    return out
