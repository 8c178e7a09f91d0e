"""The merger's pair schedule: which pairs of submaps to integrate, and in what order.

**Bounded work per submap.** A submap is integrated when it is final (it never changes again),
and, while its robot's current epoch is not placed and has no final submap yet (a robot that
just joined, or lost its place), as its active submap grows (each time its version doubles,
:data:`SEARCH_GROWTH`). A final submap that no solve has seen yet, nor its predecessor (a flood
of one robot's submaps in one step), searches once the next solve has placed its chain
(:meth:`PairSchedule.placed`), as if it had come alone. Which pairs:

- *near* (a submap whose predecessor is in the graph): the submaps of its component, its own
  robot's earlier ones included (a loop), whose refined poses lie within reach of where its links
  put the new one (not its neighbours on its own chain), at most
  :data:`NEAR_CANDIDATES`, registered near that prediction
  (:meth:`~fleetmap.merger.posegraph.PoseGraph.align_pair`), as Cartographer's constraint builder
  searches near a trajectory;
- *far*: the submaps of the other components that can share most wall with it, at most
  :data:`FAR_CANDIDATES`, by the paper's pose-free integration: the cheap descriptor (the cosine
  of pairwise geometric histograms of the walls) shortlists, the integration's coarse grid score
  orders the shortlist, which widens with every try (:mod:`fleetmap.merger.farrank`); every
  :data:`LOOP_SWEEP_EVERY`-th final submap also tries the most similar submap of its own
  component beyond its reach (a loop its drift hides from the near search);
- *joined*: when a solve joins groups of epochs that were apart, the final submaps of the groups
  whose walls now meet, registered near where the join puts them (at most :data:`NEAR_CANDIDATES`
  a submap): the near search of a submap that arrived before the join only saw its own group;
  where the forest's path between the two can have drifted beyond registration's reach and the
  registration fails, the pair is integrated again by the paper's search, within the window where
  an integration can close its cycle with the forest (:meth:`PairSchedule.registered`);
- *idle*: with nothing else due, one more pose-free try for a submap of each component apart from
  the global map, up to :data:`FAR_BUDGET` tries a submap.

Robots that known start poses alone hold in one component (:mod:`fleetmap.merger.startposes`)
count as apart here until an integration ties them: they search each other *far* and *idle*, and
their pairs are not registered near where the start poses put them.

So integrating n submaps costs O(n) integrations, not n^2
(:attr:`~fleetmap.merger.stats.MergerStats.integrations`).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable

import numpy as np
from fleetmap.merger.executor import Executor, PairJob
from fleetmap.merger.farrank import FarRanking
from fleetmap.merger.outputs import Placement, epoch_of
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.searchwindow import placed_as, predicted_pose, search_window, window_in
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.descriptor import similarity
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Window
from fleetmap.shared.core.tracking import MAX_CORRESPONDENCE, REACH_ROTATION
from fleetmap.shared.io.keys import parse_submap_key
from fleetmap.shared.io.messages import LocalMap

NEAR_CANDIDATES = 3
"""A placed robot's submap is registered on at most this many submaps near where the graph puts it,
nearest first ..."""
FAR_CANDIDATES = 3
"""... and integrated (pose-free) with at most this many of the other components' submaps most like
it (the descriptor ranks a submap's first overlapping candidate in the top 3 for 67-70 % of submaps;
docs/decisions/002-pose-graph.md) ..."""
FAR_BUDGET = 12
"""... and, while nobody has placed its robot, with at most this many of them in all (the top 12:
88-91 %; 002): n submaps cost O(n) integrations."""
LOOP_SWEEP_EVERY = 4
"""Every this-many-th final submap of a placed robot also tries the most similar submap of its own
component beyond its reach (a loop its drift hides; 0 changes no figure on the three logs, 002)."""
SEARCH_GROWTH = 2
"""An unplaced robot's active submap is searched again once its version is this many times the
version last searched: a submap of v versions costs about log(v) searches (1 or 2: the same times;
docs/decisions/010-a-back-end-that-costs-what-is-new.md)."""
MAX_QUEUED_PAIRS = 20_000
"""Pairs of submaps waiting to be integrated, at most; more are dropped, logged and counted (a bound
on a flooded merger's memory; docs/decisions/003-a-fleet-that-lets-in-only-its-own.md)."""

Pair = tuple[str, str]


def ordered(a: str, b: str) -> Pair:
    """A pose-free pair, always one way (INTEGRATE(a, b) is not exactly the inverse of INTEGRATE(b,
    a): whatever order the submaps arrived in, the same edge)."""
    return (a, b) if a < b else (b, a)


class PairSchedule:
    """The queue of pairs to integrate and what decides it (see the module docstring), over one
    pose graph and the submaps in it; each call reads where the last solve placed them."""

    def __init__(
        self,
        graph: PoseGraph,
        submaps: dict[str, LocalMap],
        config: FleetmapConfig,
        stats: MergerStats,
        refuse: Callable[[str, int, str], None],
        executor: Executor | None = None,
    ) -> None:
        """``refuse(limit, value, what)`` counts and logs a pair :data:`MAX_QUEUED_PAIRS` refused."""
        self.graph, self.submaps, self.config, self.stats, self._refuse = graph, submaps, config, stats, refuse
        self.queue: dict[Pair, Transform2D | None] = {}
        """Pairs to integrate, oldest first: (a, b) with b's predicted pose in a (near), or None
        (pose-free)."""
        self.scheduled: dict[str, int] = {}
        """The version of each submap its integrations were last scheduled for."""
        self.finals = 0
        """Final submaps of placed robots scheduled so far (every loop_sweep_every-th sweeps)."""
        self.far_tries: dict[str, int] = {}
        """Pose-free integrations queued for each submap with other components' submaps."""
        self.far_rank = FarRanking(graph, stats, submaps, executor)
        """The far search's order (:mod:`fleetmap.merger.farrank`; its scores run on ``executor``)."""
        self.behind = False
        """Whether the last step left pairs queued (live, at its time budget): no far scores then (:meth:`_far`)."""
        self.finished_epochs: set[str] = set()
        """Epochs (``robot/epoch``) with a final submap: from then on their final submaps search."""
        self.idle: set[Pair] = set()
        """Queued pairs that :meth:`idle_pairs` chose."""
        self.joined: set[Pair] = set()
        """Pairs :meth:`queue_joined` queued (each once: a pair that did not register stays so)."""
        self.wide: dict[Pair, Transform2D] = {}
        """Joined pairs registered near the join (their prediction) where the drift of the forest's
        path between them may have carried them beyond registration's reach
        (:meth:`_tie_within_reach`): searched again if the registration is not valid (:meth:`registered`)."""
        self.retry: set[Pair] = set()
        """Pairs queued pose-free again after their registration near a prediction failed."""
        self.windows: dict[Pair, Window] = {}
        """Where a queued pose-free pair of one component searches (:mod:`~fleetmap.merger.searchwindow`)."""
        self.unplaced: set[str] = set()
        """Final submaps scheduled before any solve saw them or their chain: their searches wait for
        one (:meth:`placed`)."""
        self.owner: dict[Pair, str] = {}
        """The robot whose submap queued each pair (whose turn takes it: :meth:`next_pair`)."""
        self._owner = ""
        self._served = ""
        """The robot whose pair was taken last."""

    def enqueue(self, pair: Pair, predicted: Transform2D | None) -> bool:
        """Queue a pair to integrate (once); False if it was queued already or the queue is full."""
        if pair in self.queue:
            return False
        if len(self.queue) >= MAX_QUEUED_PAIRS:
            self._refuse("max_queued_pairs", MAX_QUEUED_PAIRS, f"pair {pair[0]} {pair[1]}, {len(self.queue)} queued")
            return False
        self.owner[pair] = self._owner
        self.queue[pair] = predicted
        return True

    def next_pair(self) -> tuple[Pair, Transform2D | None]:
        """The next queued pair to integrate: the oldest of the robot whose turn it is. Robots take
        turns (round-robin over the robots with pairs queued, each pair the robot's whose submap
        queued it), so one robot's flood of submaps or epochs delays its own integrations, not the
        others'. The queue must not be empty."""
        first: dict[str, Pair] = {}
        for pair in self.queue:
            first.setdefault(self.owner.get(pair, ""), pair)
        robots = sorted(first)
        pair = first[next((r for r in robots if r > self._served), robots[0])]
        return pair, self.queue[pair]

    def take(self, pair: Pair) -> None:
        """A pair off the queue (being integrated): its robot had its turn."""
        del self.queue[pair]
        self._served = self.owner.pop(pair, "")

    def searching(self, p: Placement) -> bool:
        """Whether robots apart from the global map have submaps with candidates left to try."""
        if p.result is None or len(p.groups) < 2:
            return False
        budget = FAR_BUDGET
        return any(self.far_tries.get(k, 0) < budget for k in self.idle_candidates(p))

    def job(self, pair: Pair, predicted: Transform2D | None) -> PairJob | None:
        """The integration a queued pair is due: near its prediction, or pose-free (once per
        pair of versions); None if a map has gone or the pair's edge is current."""
        a, b = pair
        if a not in self.graph or b not in self.graph:
            return None
        if pair in self.idle:
            self.idle.discard(pair)
            self.stats.idle += 1
        if predicted is not None:
            self.stats.near += 1
            return self.graph.pair_job(a, b, predicted)
        window = self.windows.pop(pair, None)
        if pair in self.retry:  # (its edge is current: the registration's, which failed)
            self.retry.discard(pair)
            self.stats.retried += 1
            return self.graph.pair_job(a, b, window=window)
        return self.graph.job_once(a, b, window)

    def registered(self, pair: Pair, edge_valid: bool) -> None:
        """A pair integrated: one of :attr:`wide` whose registration near the join is not valid is
        queued again for the paper's integration (infinite-corridor-c cut in 2 had its one wrong
        relation where two robots' submaps, 2.2 m from where the join put them, were registered
        there and slid; docs/decisions/028), searched around the join's prediction
        (:func:`~fleetmap.merger.searchwindow.search_window`)."""
        near = self.wide.pop(pair, None)
        if near is not None and not edge_valid and self.enqueue(pair, None):
            self.retry.add(pair)
            window = search_window(self.graph, *pair, near, *pair)
            if window is not None:
                self.windows[pair] = window

    def submap(self, m: LocalMap, current: bool, p: Placement) -> None:
        """Queue the integrations a submap version is due (see the module docstring); ``current``:
        it is of its robot's current epoch."""
        key = m.submap_key
        self._owner = m.robot
        placed = p.placed_epoch(f"{m.robot}/{m.epoch}")
        last = self.scheduled.get(key)
        final = m.final and (last is None or last < m.version)
        searching = (
            current
            and not placed
            and f"{m.robot}/{m.epoch}" not in self.finished_epochs
            and (last is None or m.version >= SEARCH_GROWTH * max(last, 1))
        )
        if not (final or searching):
            return
        self.scheduled[key] = m.version
        if final and placed_as(self.graph, key, p) not in p.where:
            self.unplaced.add(key)  # no solve has seen it or its chain yet: it searches after one
            return
        if final:
            self._near_search(key, p)
        self._far_search(key, p)

    def _far_search(self, key: str, p: Placement) -> None:
        """Queue a submap's *far* search, unless it is in the global map (whose submaps are not
        searched for the others: each of theirs searches it, and one direction is enough)."""
        if not self._in_global_map(key, p):
            group = self._group_members(key, p)
            for other in self._far(key, group, p, within=False)[:FAR_CANDIDATES]:
                self._queue_far(key, other)

    def _near_search(self, key: str, p: Placement) -> None:
        """Queue a final submap's near search (the module docstring's *near*) and, every
        :data:`LOOP_SWEEP_EVERY`-th, its sweep for a loop beyond reach."""
        mine = self._component_members(key, p)
        beyond = []
        for other, predicted in self._near(key, mine, p)[:NEAR_CANDIDATES]:
            if (key, other) in self.queue:
                continue  # (a flood's submaps search each other: one way is enough, one edge a pair)
            # registered near the prediction where the robot's own drift between the two
            # cannot have carried it out of registration's reach; else by the paper's search (a
            # loop after a long way round: the search window as wide as the uncertainty), the
            # most similar such submap only: the paper's integration costs ten registrations
            if self._within_reach(other, key, p):
                self.enqueue((other, key), predicted)
            else:
                beyond.append(other)
        if beyond:
            h = self.graph.descriptor(key)
            best = max(beyond, key=lambda k: (similarity(self.graph.descriptor(k), h), k))
            self._queue_loop(best, key, p)
        self.finals += 1
        if LOOP_SWEEP_EVERY > 0 and self.finals % LOOP_SWEEP_EVERY == 0:
            for other in self._far(key, mine, p, within=True)[:1]:
                self._queue_loop(other, key, p)

    def _queue_loop(self, x: str, y: str, p: Placement) -> None:
        """Queue a pose-free pair of one component, searched around where the last solve puts
        them (:mod:`~fleetmap.merger.searchwindow`)."""
        pair = ordered(x, y)
        if self.enqueue(pair, None):
            window = window_in(self.graph, *pair, p)
            if window is not None:
                self.windows[pair] = window

    def placed(self, p: Placement) -> None:
        """After a solve: the searches of each final submap that no solve had seen, nor its chain,
        when it was scheduled (:attr:`unplaced`), now that one has. A robot whose
        submaps reach the merger in a flood, before any solve (one that joins late, a merger that
        fell behind), would otherwise have no near search, and search pose-free its own chain as if
        it were another robot's: infinite-corridor-c cut in 4 had its one wrong relation at such a
        robot's end (docs/decisions/029)."""
        for key in sorted(self.unplaced):
            if key not in self.graph:  # (its robot was forgotten)
                self.unplaced.discard(key)
            elif key in p.where:
                self.unplaced.discard(key)
                self._owner = parse_submap_key(key)[0]
                self._near_search(key, p)
                self._far_search(key, p)

    def queue_joined(self, p: Placement, apart: dict[str, frozenset[str]]) -> None:
        """After a solve that joined groups of epochs (``apart``: each epoch's component's epochs
        before it): queue near registrations between the final submaps of the groups now joined
        whose walls meet at their refined poses and that no valid integration relates yet (a pair
        tried pose-free while apart, ambiguous then, may register near the join), each pair once,
        at most :data:`NEAR_CANDIDATES` a submap, nearest first.

        A final submap searches near its prediction once, when it arrives, among the submaps of its
        component then: two robots' submaps that meet only once a later join puts them in one frame
        would never be registered on each other, and the join would rest on its few integrations
        while the chains around it bend. These are the join's own loop closures, as Cartographer's
        constraint builder finds them for a trajectory it has just placed; bounded by the pairs
        that meet, so the work stays O(n)."""
        if p.result is None:
            return
        if all(
            apart.get(epoch, frozenset({epoch})) == epochs for epochs in map(frozenset, p.epochs_in) for epoch in epochs
        ):
            return  # every component holds the epochs it held: nothing joined (a step costs what it adds)
        limit = NEAR_CANDIDATES
        at = {k: pose for k, pose in p.result.poses.items() if pose is not None}
        queued = 0
        for component in p.result.components:
            groups: dict[frozenset[str], list[str]] = {}
            for key in sorted(component.members):
                if self.submaps[key].final and key in at:
                    epoch = epoch_of(key)
                    groups.setdefault(apart.get(epoch, frozenset({epoch})), []).append(key)
            if len(groups) < 2:
                continue
            found: list[tuple[float, str, str]] = []
            groups_in_order = sorted(groups.values())
            for n, group_a in enumerate(groups_in_order):
                for group_b in groups_in_order[n + 1 :]:
                    meets = self.graph.meeting(group_a, at, group_b, at)
                    for ia, ib in np.argwhere(meets):
                        a, b = ordered(group_a[ia], group_b[ib])
                        known = self.graph.edge(a, b)
                        if (a, b) in self.joined or (known is not None and known.valid) or not p.tied(a, b):
                            continue  # (robots together by their start poses alone: the near search's)
                        found.append((math.hypot(at[a].x - at[b].x, at[a].y - at[b].y), a, b))
            count: Counter[str] = Counter()
            for _, a, b in sorted(found):
                if count[a] >= limit or count[b] >= limit:
                    continue
                self._owner = parse_submap_key(b)[0]
                predicted = at[a].inverse().compose(at[b])
                if self.enqueue((a, b), predicted):
                    if not self._tie_within_reach(a, b, p):
                        self.wide[(a, b)] = predicted
                    self.joined.add((a, b))
                    count[a] += 1
                    count[b] += 1
                    queued += 1
        self.stats.join_pairs += queued

    def idle_pairs(self, p: Placement) -> int:
        """With nothing else to do: one more pose-free pair for a submap of each component apart
        from the global map (:meth:`idle_candidates`: robots not in it yet), its next submap of
        another component not tried yet in the far search's order (:meth:`_far`), up to
        :data:`FAR_BUDGET` tries a submap; how many were queued. Every submap's candidates are tried
        in turn: in a building where most views look alike (racks), the descriptor ranks the right
        partner anywhere."""
        if p.result is None or len(p.groups) < 2:
            return 0
        budget = FAR_BUDGET
        queued = 0
        by_group: dict[str, list[str]] = {}
        for key in self.idle_candidates(p):
            by_group.setdefault(p.ties.get(epoch_of(key), epoch_of(key)), []).append(key)
        for group, candidates in by_group.items():
            mine = set(p.groups[group])
            for key in sorted(candidates, key=lambda k: (self.far_tries.get(k, 0), k)):
                if self.far_tries.get(key, 0) >= budget:
                    continue
                others = self._far(key, mine, p, within=False)
                if others:
                    self._owner = parse_submap_key(key)[0]
                    self._queue_far(key, others[0])
                    self.idle.add(ordered(others[0], key))
                    queued += 1
                    break
                self.far_tries[key] = budget  # none left
        return queued

    def idle_candidates(self, p: Placement) -> list[str]:
        """The submaps the idle search tries (:meth:`idle_pairs`), whose tries :meth:`searching`
        counts (they must be the same, or a step with nothing to queue would have work for ever):
        of each group of submaps the integrations place together (a component, or each part of
        one that known start poses alone hold together: :attr:`Placement.groups`) but the global
        map's, its final submaps, or all of them if none is final yet. Robots placed among
        themselves and not in the global map search on: two robots that joined each other are
        still apart from the fleet."""
        if p.result is None:
            return []
        out: list[str] = []
        for members in p.groups.values():
            if members[0] in p.global_group:
                continue
            finals = [k for k in members if self.submaps[k].final]
            out += finals or list(members)
        return out

    def _in_global_map(self, key: str, p: Placement) -> bool:
        """Whether a submap (or its predecessor, for a new one) is in the global map, placed there
        with another epoch by integrations (:attr:`Placement.global_group`; not by a known start
        pose alone, :mod:`fleetmap.merger.startposes`)."""
        return placed_as(self.graph, key, p) in p.global_group

    def _group_members(self, key: str, p: Placement) -> set[str]:
        """The submaps the last solve's integrations place with ``key`` (:meth:`Placement.group_of`)."""
        return {key, *(p.group_of(placed_as(self.graph, key, p)) or ())}

    def _queue_far(self, key: str, other: str) -> None:
        if self.enqueue(ordered(other, key), None):
            self.far_tries[key] = self.far_tries.get(key, 0) + 1

    def _component_members(self, key: str, p: Placement) -> set[str]:
        """The submaps in ``key``'s component, by the last solve and its links."""
        members = {key}
        link = self.graph.link_to(key)
        anchor = link.a if link is not None else key
        component = p.component_of(anchor)
        if component is not None:
            members.update(component.members)
        return members

    def _near(self, key: str, mine: set[str], p: Placement) -> list[tuple[str, Transform2D]]:
        """Submaps of ``key``'s component within reach of where the graph puts it, nearest first,
        with the predicted pose of ``key`` in each; not its neighbours on its own chain."""
        here = predicted_pose(self.graph, key, p)
        if here is None or p.result is None:
            return []
        radius = _radius(self.graph, key)
        out = []
        for other in sorted(mine):
            if other == key or _neighbours(key, other):
                continue
            there = p.result.poses.get(other)
            if there is None:
                continue
            distance = math.hypot(here.x - there.x, here.y - there.y)
            if distance <= radius + _radius(self.graph, other):
                out.append((distance, other, there.inverse().compose(here)))
        out.sort(key=lambda x: (x[0], x[1]))
        return [(other, predicted) for _, other, predicted in out]

    def _within_reach(self, a: str, b: str, p: Placement) -> bool:
        """Whether registration from the predicted pose can find b on a: the drift the links
        between two submaps of one robot's chain allow (three standard deviations of their
        covariances, :meth:`~fleetmap.merger.chains.ChainGraph.chain_drift`) is within the
        tracking's correspondence distance and 5 degrees; for two robots' submaps, when their
        prediction comes through integrations (:meth:`Placement.tied`), not through their start
        poses alone (metres off: :mod:`fleetmap.merger.startposes`)."""
        drift = self.graph.chain_drift(a, b)
        if drift is None:
            return p.tied(a, b)
        return _reaches(drift)

    def _tie_within_reach(self, a: str, b: str, p: Placement) -> bool:
        """Whether registration near where the last solve's forest puts b on a can find it: the
        drift of the links on the forest's path between them
        (:meth:`~fleetmap.merger.posegraph.PoseGraph.tree_drift`) is within the tracking's
        correspondence distance and 5 degrees, as :meth:`_within_reach` for one robot's chain."""
        drift = self.graph.tree_drift(placed_as(self.graph, a, p), placed_as(self.graph, b, p))
        return drift is not None and _reaches(drift)

    def _far(self, key: str, mine: set[str], p: Placement, within: bool) -> list[str]:
        """Submaps most like ``key`` (pairwise geometric histograms), of its own component beyond its
        reach (``within``), most similar first; or of the other components, in the far search's order
        for its next try (:class:`~fleetmap.merger.farrank.FarRanking`; :attr:`behind`: the descriptor's)."""
        h = self.graph.descriptor(key)
        here = predicted_pose(self.graph, key, p)
        radius = _radius(self.graph, key) if within else 0.0
        candidates = []
        for other in self.graph.keys:
            if other == key or (other in mine) != within or _neighbours(key, other):
                continue
            if within and here is not None and p.result is not None:
                there = p.result.poses.get(other)
                gap = math.inf if there is None else math.hypot(here.x - there.x, here.y - there.y)
                if gap <= radius + _radius(self.graph, other):
                    continue  # within reach: the near search's
            if not self.graph.seen_enough(key, other) or self.graph.is_current(*ordered(other, key)):
                continue
            candidates.append((-similarity(self.graph.descriptor(other), h), other))
        candidates.sort()
        partners = [other for _, other in candidates]
        if within or self.behind:
            return partners
        return self.far_rank.order(key, partners, self.far_tries.get(key, 0) + FAR_CANDIDATES)


def _radius(graph: PoseGraph, key: str) -> float:
    """How far a submap's walls reach from its frame (m)."""
    seg = graph.map_of(key).segments
    if len(seg) == 0:
        return 0.0
    return float(np.hypot(seg[:, 0::2], seg[:, 1::2]).max())


def _reaches(drift: tuple[float, float]) -> bool:
    """Whether registration from a prediction this far off (three standard deviations, m and rad)
    finds the same minimum: within the tracking's correspondence distance and 5 degrees."""
    return drift[0] <= MAX_CORRESPONDENCE and drift[1] <= REACH_ROTATION


def _neighbours(a: str, b: str) -> bool:
    """Whether two submaps are within two of each other on one robot's chain (they share
    scans, or their links already say how they lie)."""
    ra, ea, sa = parse_submap_key(a)
    rb, eb, sb = parse_submap_key(b)
    return ra == rb and ea == eb and sa is not None and sb is not None and abs(sa - sb) <= 2
