"""The order in which the far search tries the other components' submaps for one of its own.

The descriptor's order (:func:`~fleetmap.shared.core.descriptor.similarity`) is cheap and whole-map:
a partner that shares only a part of a submap's walls ranks low, often beyond the far search's
budget (:data:`~fleetmap.merger.schedule.FAR_BUDGET`). The coarse grid score of the paper's
candidates (:func:`~fleetmap.shared.core.overlap.overlap_score`) ranks such partners first, but
costs about a seventh of a pose-free integration, so each try pays for :data:`FAR_SCORED` of them:
a submap's n-th try ranks by that score the first ``FAR_SCORED * n`` partners in the descriptor's
order (the window widens with every try and reaches past what the descriptor ranks high), then the
rest in the descriptor's order. Only final submaps are scored: a growing one keeps the descriptor's
order. A merger behind its robots (its last step stopped at its time budget with pairs still
queued: :attr:`~fleetmap.merger.schedule.PairSchedule.behind`) takes the descriptor's order too:
live, scoring every final submap on arrival in the merger's step kept it behind (16 robots, inline:
latency 8.6-10.2 s against 1.7-1.9 s without the scores, docs/decisions/032); offline, each step
integrates all it queued, and every final submap's search is ranked. The order is a function of the
graph, the submaps' finality, the tries and whether the merger is behind (the scores are kept only
so that each pair is scored once), so a merger restored from its state, or a replay, orders
alike. A try's scores run side by side as jobs on the merger's executor
(:class:`~fleetmap.merger.executor.ScoreJob`), as its integrations do: the same scores wherever
they run.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

from fleetmap.merger.executor import Executor, InlineExecutor, ScoreJob, score_result
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.merger.stats import MergerStats
from fleetmap.shared.io.messages import LocalMap

log = logging.getLogger(__name__)

FAR_SCORED = 4
"""Partners a far try ranks by their overlap score: they cost about half a pose-free integration
(21 ms each against 0.15 s, docs/decisions/031), so ranking adds at most half to what the far
search costs a submap, however many submaps the other components hold. 2 and 8 make the same joins
on the rows the ranking changed (edmonton-c K = 4, belgioioso-c K = 8); a wider window spends fewer
integrations (docs/decisions/031, "FAR_SCORED at 2, 4 and 8")."""


class FarRanking:
    """Overlap scores of pairs of submaps (each pair of versions once), and the far search's order."""

    def __init__(
        self,
        graph: PoseGraph,
        stats: MergerStats,
        submaps: Mapping[str, LocalMap],
        executor: Executor | None = None,
    ) -> None:
        self.graph = graph
        self.stats = stats
        self.submaps = submaps
        """The submaps as received: which are final."""
        self.executor: Executor = executor or InlineExecutor()
        """Where the scores run (the merger's executor)."""
        self._scores: dict[tuple[str, str], tuple[int, int, float]] = {}

    def order(self, key: str, partners: list[str], turns: int) -> list[str]:
        """``partners`` (the descriptor's order) for ``key``'s ``turns``-th try (the first is 1): the
        first ``FAR_SCORED * turns`` final ones by their overlap score, best first (ties: the
        descriptor's order), then the rest in the descriptor's order. A submap still growing is
        neither scored nor scores: its next version, a few scans on, would need its scores again
        (live, scoring every version of a 16-robot fleet's growing submaps fell twenty seconds
        behind the robots, docs/decisions/031)."""
        if not self._final(key):
            return partners
        window = [other for other in partners if self._final(other)][: FAR_SCORED * max(turns, 0)]
        self._score_all([(key, other) for other in window])
        ranked = sorted(window, key=lambda other: -self.score(key, other))
        chosen = set(ranked)
        return ranked + [other for other in partners if other not in chosen]

    def _final(self, key: str) -> bool:
        m = self.submaps.get(key)
        return m is not None and m.final

    def score(self, a: str, b: str) -> float:
        """The overlap score of two submaps at their current versions (one way: the first key in
        sorted order is searched on, as the pair is integrated)."""
        a, b = (a, b) if a < b else (b, a)
        self._score_all([(a, b)])
        return self._scores[(a, b)][2]

    def _score_all(self, pairs: list[tuple[str, str]]) -> None:
        """Score the pairs not scored at their current versions, all at once on the executor. A
        job that fails where it ran scores 0 (logged and counted): it only ranks the pair last."""
        jobs = []
        for x, y in pairs:
            a, b = (x, y) if x < y else (y, x)
            known = self._scores.get((a, b))
            if known is None or known[:2] != (self.graph.version_of(a), self.graph.version_of(b)):
                pair = self.graph.pair_job(a, b)
                given = {name: index for name, index in pair.given.items() if name.startswith("index_")}
                jobs.append(ScoreJob(a, b, pair.versions, pair.work_a, pair.work_b, pair.integration, given))
        running = [(job, self.executor.submit(job, self.graph.indexes)) for job in jobs]
        for job, handle in running:
            try:
                result = score_result(handle)
            except Exception as exc:  # a job that failed where it ran: ranked last
                self.stats.failed += 1
                log.error("scoring %s and %s failed (%s: %s); ranked last", job.a, job.b, type(exc).__name__, exc)
                value = 0.0
            else:
                self.graph.keep_built(job.a, job.b, job.versions, result.built)
                value = result.value
            self._scores[(job.a, job.b)] = (*job.versions, value)
            self.stats.far_scored += 1

    def forget(self, key: str) -> None:
        """Drop the scores of a submap that left the graph."""
        for pair in [pair for pair in self._scores if key in pair]:
            del self._scores[pair]
