"""A live merger's budget per robot: how fast a robot's new submaps enter the pose graph.

A robot within the motion model starts a submap at most every half ``tracking.submap_length`` of
its path (the next starts halfway), and moves at most ``integration.motion.max_speed``: it starts
at most ``max_speed / (submap_length / 2)`` new submaps a second (0.6 with the defaults), its
new epochs' first submaps included. A live merger takes each robot's new submaps at that rate
over a window of :data:`WINDOW` seconds (a token bucket: a window's worth at once, then as time
gives more); a robot's new submaps beyond it wait, in arrival order, up to another window's worth,
and more are refused and counted (``refused["submap_budget"]``). New versions of a submap the
merger holds, or holds back, are never held back themselves; one robot's flood delays only itself.

What it bounds: how much of the graph (and so of the merger's memory and integration time) one
robot can take in a window, whatever its key lets it send. Offline (``fleetmap map``, a replay)
there is no budget: a log's submaps arrive as fast as they are read, and a replay takes what the
live merger's steps took. A merger restarted without its state file is sent every robot's
submaps again at once: past a window's worth they wait, past two they are refused (``--state``
keeps them).
"""

from __future__ import annotations

from fleetmap.shared.config import FleetmapConfig

WINDOW = 60.0
"""The budget's window (s): a robot may start a window's worth of new submaps at once."""


class SubmapBudget:
    """Per robot, the new submaps it may put into the graph now (a token bucket on the merger's clock)."""

    def __init__(self, rate: float, window: float = WINDOW) -> None:
        self.rate = rate
        """New submaps a second, per robot."""
        self.burst = max(1.0, rate * window)
        """... and at once; as many again may wait."""
        self._buckets: dict[str, tuple[float, float]] = {}
        """Per robot: the new submaps it may still start, and when that was worked out (s)."""

    @classmethod
    def of(cls, config: FleetmapConfig) -> SubmapBudget:
        """The budget of a robot within ``config``'s motion model and submap length."""
        return cls(config.integration.motion.max_speed / (config.tracking.submap_length / 2))

    def admit(self, robot: str, now: float) -> bool:
        """Whether ``robot`` may put one more new submap into the graph at ``now`` (taken if so)."""
        tokens, since = self._buckets.get(robot, (self.burst, now))
        tokens = min(self.burst, tokens + max(now - since, 0.0) * self.rate)
        admitted = tokens >= 1.0
        self._buckets[robot] = (tokens - 1.0 if admitted else tokens, now)
        return admitted

    def forget(self, robot: str) -> None:
        self._buckets.pop(robot, None)
