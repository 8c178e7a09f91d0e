"""The agents of ``fleetmap map`` in processes of their own, so that the merger cannot starve them.

Live, every robot's agent is a process of its own and the merger another. Offline, all of them
once shared one process: the agents' tracking and the merger's solving took turns on one
interpreter lock, and the merger's work on a large map slowed every robot's tracking (issue 49: a
45-minute log tracked at 58 ms a scan beside the merger, 3-5 ms alone). :class:`AgentProcesses`
runs the agents in worker processes instead: each worker holds whole robots (an agent's state never
leaves its process), tracks their scans in the fleet's timeline order, and sends what each scan
gave back in batches. Read in the timeline's order, they are the same messages in the same order
as agents run in line give, so the map is the same.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import queue
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from fleetmap.agents.agent import Agent
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.io.messages import Message

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess

    from fleetmap.mapping import Piece

BATCH_SCANS = 32
"""Scans a worker tracks before it sends what they gave (or fewer, once ``BATCH_SECONDS`` passed)."""
BATCH_SECONDS = 0.2
"""The longest a worker keeps what it tracked before sending it."""
POLL_SECONDS = 1.0
"""How often a reader waiting on a worker checks that the worker is still alive."""


@dataclass(frozen=True)
class Finished:
    """What one robot's agent says at its end."""

    messages: list[Message]
    """The final version of every map it was still building (:meth:`Agent.finish`)."""
    epochs: int
    clock: dict[str, Any] | None
    """What it made of its stamps (:func:`clock_summary`)."""


def clock_summary(agent: Agent) -> dict[str, Any] | None:
    """What the tracker made of a robot's stamps (``stamps_trusted`` false: not every stamp was its
    scan's time; ``untimed_scans`` whose stamps repeated, went back or came in a burst, from scan
    ``first_untimed`` on, had the intervals they bound timed by their sequence at ``mean_period``,
    and every interval from scan ``distrusted_at`` on, where the motion showed the stamps wrong;
    ``bursts`` of scans stamped together, whose ``odometry_spread`` readings were placed between the
    bursts' own)."""
    clock, bursts = agent.clock, agent.bursts
    if clock is None or bursts is None:
        return None
    return {
        "bursts": bursts.bursts,
        "odometry_spread": bursts.spread,
        "stamps_trusted": clock.trusted and clock.untimed == 0,
        "untimed_scans": clock.untimed,
        "first_untimed": clock.first_untimed,
        "distrusted_at": clock.distrusted_at,
        "mean_period": clock.period,
        "repeated": clock.repeated,
        "backwards": clock.backwards,
        "too_fast": clock.too_fast,
    }


Order = Sequence[tuple[int, int]]
"""The scans to track, in the fleet's timeline order: (the piece's number, the scan's in it)."""


def _tracking(
    pieces: dict[int, Piece], order: Order, config: FleetmapConfig, finished: dict[int, Finished]
) -> Iterator[tuple[int, int, list[Message], float]]:
    """The agents of ``pieces``, each scan of ``order`` tracked in turn: ``(n, i, messages,
    seconds)``; at the end, each agent's :class:`Finished` put in ``finished``."""
    agents = {n: Agent(p.robot, config, odometry=p.has_odometry) for n, p in pieces.items()}
    for n, i in order:
        s = pieces[n].scans[i]
        t0 = time.perf_counter()
        messages = agents[n].add_scan(s.index, s.stamp, s.scan, s.odometry)
        yield n, i, messages, time.perf_counter() - t0
    finished.update({n: Finished(a.finish(), a.counts.epochs, clock_summary(a)) for n, a in agents.items()})


def _track(pieces: dict[int, Piece], order: Order, config: FleetmapConfig, out: Any) -> None:
    """A worker: :func:`_tracking`, what each scan gave put on ``out`` in batches (``("scans",
    [(n, i, messages, seconds), ...])``), then ``("done", {n: Finished})``; or ``("error",
    exception)`` and nothing more."""
    try:
        finished: dict[int, Finished] = {}
        batch: list[tuple[int, int, list[Message], float]] = []
        sent = time.monotonic()
        for tracked in _tracking(pieces, order, config, finished):
            batch.append(tracked)
            if len(batch) >= BATCH_SCANS or time.monotonic() - sent >= BATCH_SECONDS:
                out.put(("scans", batch))
                batch, sent = [], time.monotonic()
        if batch:
            out.put(("scans", batch))
        out.put(("done", finished))
    except Exception as exc:  # raised again by the reader, as it was where it can be pickled
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:
            exc = RuntimeError(f"tracking failed: {type(exc).__name__}: {exc}")
        out.put(("error", exc))


class AgentProcesses:
    """Every piece's agent, in ``processes`` worker processes (0: in this process, in line).

    Iterated, it yields ``(n, i, messages)`` for every scan of ``order`` in that order: what the
    agent of piece ``n`` gave for its scan ``i``. Then :attr:`finished` holds each piece's
    :class:`Finished` and :attr:`seconds` the agents' tracking time summed. A worker that fails
    raises its error in the reader; one that dies raises a RuntimeError. :meth:`close` (or the
    ``with`` block's end) stops the workers."""

    def __init__(self, pieces: Sequence[Piece], order: Order, config: FleetmapConfig, processes: int) -> None:
        self.pieces = list(pieces)
        self.order = list(order)
        self.config = config
        self.finished: dict[int, Finished] = {}
        self.seconds = 0.0
        self._workers: list[tuple[BaseProcess, Any]] = []
        self._worker_of: dict[int, int] = {}
        self._pending: list[deque[tuple[int, int, list[Message], float]]] = []
        self._done: list[bool] = []
        if processes > 0:
            self._start(min(processes, len(self.pieces)))

    @staticmethod
    def default_processes(pieces: int) -> int:
        """One worker per robot, up to one fewer than this machine's CPUs (the merger has one), at least one."""
        return max(1, min(pieces, (os.cpu_count() or 1) - 1))

    def _start(self, processes: int) -> None:
        # whole robots to each worker, the most scans first onto the least loaded
        load = [0] * processes
        for n in sorted(range(len(self.pieces)), key=lambda n: -len(self.pieces[n].scans)):
            w = load.index(min(load))
            self._worker_of[n] = w
            load[w] += len(self.pieces[n].scans)
        context = multiprocessing.get_context("forkserver")
        for w in range(processes):  # no fewer pieces than workers: none goes without
            mine = {n: p for n, p in enumerate(self.pieces) if self._worker_of[n] == w}
            out = context.Queue(maxsize=256)
            order = [(n, i) for n, i in self.order if n in mine]
            process = context.Process(
                target=_track, args=(mine, order, self.config, out), name=f"fleetmap-agents-{w}", daemon=True
            )
            process.start()
            self._workers.append((process, out))
        self._pending = [deque() for _ in self._workers]
        self._done = [False] * len(self._workers)

    def __iter__(self) -> Iterator[tuple[int, int, list[Message]]]:
        if not self._workers:
            yield from self._in_line()
            return
        for n, i in self.order:
            w = self._worker_of[n]
            while not self._pending[w]:
                self._receive(w)
            m, j, messages, seconds = self._pending[w].popleft()
            if (m, j) != (n, i):  # the worker tracks its robots in this same order
                raise RuntimeError(f"tracking worker {w} sent scan {j} of piece {m} for scan {i} of piece {n}")
            self.seconds += seconds
            yield n, i, messages
        for w in range(len(self._workers)):
            while not self._done[w]:
                self._receive(w)

    def _in_line(self) -> Iterator[tuple[int, int, list[Message]]]:
        for n, i, messages, seconds in _tracking(dict(enumerate(self.pieces)), self.order, self.config, self.finished):
            self.seconds += seconds
            yield n, i, messages

    def _receive(self, w: int) -> None:
        process, out = self._workers[w]
        while True:
            try:
                kind, body = out.get(timeout=POLL_SECONDS)
                break
            except queue.Empty:
                if not process.is_alive():
                    raise RuntimeError(
                        f"tracking worker {process.name} ended (exit code {process.exitcode}) before it sent every scan"
                    ) from None
        if kind == "error":
            raise body
        if kind == "done":
            self.finished.update(body)
            self._done[w] = True
        else:
            self._pending[w].extend(body)

    def close(self) -> None:
        """Stop every worker (those still tracking too: the reader is failing)."""
        for process, out in self._workers:
            if process.is_alive():
                process.terminate()
            process.join(timeout=5.0)
            out.close()
            out.cancel_join_thread()
        self._workers = []

    def __enter__(self) -> AgentProcesses:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
