"""Where the merger's integrations run: in its own process, in a local process pool, or on Ray.

An integration (Algorithm 1, steps 1-2, or a registration near a prediction, valued the same way)
needs two submaps and the parameters, nothing else of the graph: :class:`PairJob` holds that,
:func:`run_pair` computes it anywhere, and :class:`~fleetmap.merger.graph.MapGraph` turns the
:class:`PairResult` into an edge. Jobs are independent, so a step hands several to an
:class:`Executor` at once and takes the results back in the order it queued the pairs: the graph
is the same whichever executor ran them, bit for bit (the same numpy code on the same inputs).

- :class:`InlineExecutor` runs each job in the calling process when its result is asked for (the
  library default: no processes).
- :class:`LocalExecutor` is a ``concurrent.futures`` process pool (``forkserver``: the merger's
  zenoh threads are never forked); a worker that dies mid-job breaks the pool, which is started
  again and the lost jobs run again (``MAX_ATTEMPTS`` times at most).
- :class:`RayExecutor` submits jobs as Ray tasks to a local or remote cluster (``pip install
  'fleetmap[ray]'``); Ray runs a task again when its worker dies (``max_retries``).

A job carries the search indexes the graph built already, and a worker sends back the ones it
built (the graph keeps them); a worker also keeps those it saw (by key, version and the map's
fingerprint), so each submap is indexed once.

The far search's overlap scores (:class:`ScoreJob`, :mod:`fleetmap.merger.farrank`) run on the
same executors (:func:`run_job` takes either kind): they too need two maps and nothing else.
"""

from __future__ import annotations

import hashlib
import logging
import multiprocessing
import os
import select
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, cast

import numpy as np
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Integration, Window, index_for, integrate, takes_large_path
from fleetmap.shared.core.near import align_near
from fleetmap.shared.core.overlap import overlap_score
from fleetmap.shared.core.pivotmap import WITNESS_ROTATION, WITNESS_TRANSLATION
from fleetmap.shared.core.refine import fit_information, refine_transform
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.tracking import VOXEL_SIZE, ReferenceMap, sample_segments
from fleetmap.shared.core.transformation_value import prepare
from fleetmap.shared.core.work import Work, WorkExhausted
from fleetmap.shared.errors import BadInput

log = logging.getLogger(__name__)

EXECUTORS: tuple[str, ...] = ("inline", "local", "ray")

POLISH_ITERATIONS = 30
"""A polished edge's Gauss-Newton steps, at most (``polish_edges``)."""
EDGE_INFORMATION = True
"""An edge weighs as firmly as its walls fix each direction of its transform (the normal matrix of its
least-squares fit), not by its value alone in every direction (orebro's pieces 0-3 of 8: maps 0.26 and
0.22 m off by value alone, all within 0.2 m with it; docs/decisions/008-pivot-local-maps.md)."""


MAX_ATTEMPTS = 3
"""How often a local job runs when its worker dies under it (a job that kills every worker it
runs on is a bug to report, not to retry for ever)."""

CACHE_SIZE = 64
"""Submaps' indexes a worker keeps (by key and version)."""

WORKER_NICENESS = 10
"""``fleetmap map``'s pool workers yield the CPU to its agents' tracking (``nice``; a tenth of an
agent's share where they contend): the merger's work must not starve the agents (aces cut in 8:
tracking 76-85 s beside workers at the agents' priority, 62-66 s beside ones that yield). A live
merger's workers keep its priority: its robots track elsewhere, and a fleet simulated on the
merger's machine (benchmarks/live.py) took its pool's share (16 robots: latency 5.7 -> 13.6 s)."""


@dataclass(frozen=True)
class PairJob:
    """One integration: submap ``b`` on submap ``a`` at their versions, near ``predicted`` (b's
    frame in a's) or pose-free (None). ``work_*`` are the maps integrated (simplified for a
    MapGraph's large maps; the same objects as ``map_*`` for submaps); ``map_*`` are the ones the
    edge is fitted on."""

    a: str
    b: str
    versions: tuple[int, int]
    map_a: SegmentMap
    map_b: SegmentMap
    work_a: SegmentMap
    work_b: SegmentMap
    predicted: Transform2D | None
    integration: IntegrationParams
    tracking: TrackingParams
    merge: MergeParams
    given: dict[str, Any] = field(default_factory=dict)
    """Indexes the caller built already (``index_a``, ``index_b``, ``reference_a``): a worker takes
    them rather than build them again (unpickling one costs a hundredth of building it)."""
    window: Window | None = None
    """A pose-free integration's search window (None: the whole map)."""


@dataclass(frozen=True)
class PairResult:
    """What :func:`run_pair` found: the integration, and a valid edge's fitted transform and how
    firmly the walls fix it (:func:`~fleetmap.shared.core.integration.fit_information`)."""

    integration: Integration
    transform: Transform2D
    information: tuple[float, ...] | None
    built: dict[str, Any] = field(default_factory=dict)
    """Indexes a worker built that the job did not give (the caller keeps them: each is built once)."""


@dataclass(frozen=True)
class ScoreJob:
    """The far search's overlap score of b's walls on a's (:func:`~fleetmap.shared.core.overlap.overlap_score`),
    on the maps a pose-free integration searches (``work_*``), at their versions."""

    a: str
    b: str
    versions: tuple[int, int]
    work_a: SegmentMap
    work_b: SegmentMap
    integration: IntegrationParams
    given: dict[str, Any] = field(default_factory=dict)
    """The grid indexes the caller built already (``index_a``, ``index_b``)."""


@dataclass(frozen=True)
class ScoreResult:
    value: float
    built: dict[str, Any] = field(default_factory=dict)
    """Indexes a worker built that the job did not give (the caller keeps them)."""


Job = PairJob | ScoreJob
Outcome = PairResult | ScoreResult


class Indexes:
    """Search indexes and registration grids of submaps, by key, version and what they are built
    from (``content``: the map's fingerprint and the parameters), the newest ``size`` kept."""

    def __init__(self, size: int = CACHE_SIZE) -> None:
        self.size = size
        self._held: OrderedDict[tuple[object, ...], Any] = OrderedDict()

    def get(self, key: str, version: int, kind: str, build: Any, content: object = None) -> Any:
        k = (key, version, kind, content)
        if k in self._held:
            self._held.move_to_end(k)
            return self._held[k]
        value = self._held[k] = build()
        while len(self._held) > self.size:
            self._held.popitem(last=False)
        return value


_WORKER_INDEXES = Indexes()
"""A worker process's own indexes (jobs give maps, not indexes: those stay where they are built)."""


def fingerprint(m: SegmentMap) -> bytes:
    """A digest of a map's walls and the arrays it carries (viewpoints): what its indexes are
    built from, whatever its key and version say."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(m.segments, dtype=np.float64).tobytes())
    for name in sorted(m.extras):
        value = m.extras[name]
        if isinstance(value, np.ndarray):
            h.update(name.encode())
            h.update(np.ascontiguousarray(value).tobytes())
    return h.digest()


def reference_of(m: SegmentMap) -> ReferenceMap:
    """The registration grid of a map's walls."""
    reference = ReferenceMap(VOXEL_SIZE)
    reference.insert(sample_segments(m.segments, VOXEL_SIZE))
    return reference


def run_pair(job: PairJob, indexes: Indexes | None = None) -> PairResult:
    """Integrate one pair (pure but for ``indexes``, a cache): near the prediction by registration
    (:func:`~fleetmap.shared.core.near.align_near`), else by the paper's INTEGRATE, the large-map
    path where a map is large; a valid result fitted on the full maps (:func:`fitted`). The whole
    of it within ``merge.max_integration_work`` (:mod:`fleetmap.shared.core.work`): past it, the
    result is not valid and ``exhausted``."""
    a, b, (va, vb) = job.a, job.b, job.versions
    p = job.integration
    need = _Needs(job.given, indexes, p)
    built = need.built
    work = Work(job.merge.max_integration_work)

    if job.predicted is not None:
        r = align_near(
            job.map_a,
            job.map_b,
            job.predicted,
            p,
            job.tracking,
            need("reference_a", a, va, "reference", lambda: reference_of(job.map_a), job.map_a),
            need("index_a", a, va, "index", lambda: index_for(job.work_a, p), job.work_a),
            need("index_b", b, vb, "index", lambda: index_for(job.work_b, p), job.work_b),
            work,
        )
    else:
        large = takes_large_path(job.work_a, job.work_b, p)
        r = integrate(
            job.work_a,
            job.work_b,
            p,
            index1=need("index_a", a, va, "index", lambda: index_for(job.work_a, p), job.work_a) if large else None,
            index2=need("index_b", b, vb, "index", lambda: index_for(job.work_b, p), job.work_b) if large else None,
            window=job.window,
            work=work,
        )
    if not r.valid:
        return PairResult(r, r.transform, None, built)
    try:
        transform, information = fitted(job, r.transform, work)
    except WorkExhausted:
        return PairResult(replace(r, valid=False, work=work.spent, exhausted=True), r.transform, None, built)
    return PairResult(replace(r, work=work.spent), transform, information, built)


def run_score(job: ScoreJob, indexes: Indexes | None = None) -> ScoreResult:
    """The overlap score of a pair (pure but for ``indexes``, a cache, as :func:`run_pair`)."""
    p = job.integration
    need = _Needs(job.given, indexes, p)
    index_a = need("index_a", job.a, job.versions[0], "index", lambda: index_for(job.work_a, p), job.work_a)
    index_b = need("index_b", job.b, job.versions[1], "index", lambda: index_for(job.work_b, p), job.work_b)
    return ScoreResult(overlap_score(job.work_a, job.work_b, index_a, index_b, p), need.built)


def run_job(job: Job, indexes: Indexes | None = None) -> Outcome:
    """:func:`run_pair` or :func:`run_score`, by the job's kind (what every executor runs)."""
    return run_score(job, indexes) if isinstance(job, ScoreJob) else run_pair(job, indexes)


class _Needs:
    """A job's indexes: the ones it was given, else from ``indexes`` (the caller's, in its
    process), else built or kept by this worker (:data:`_WORKER_INDEXES`) and noted in
    :attr:`built` for the caller to keep."""

    def __init__(self, given: dict[str, Any], indexes: Indexes | None, p: IntegrationParams) -> None:
        self.given, self.indexes, self.p = given, indexes, p
        self.built: dict[str, Any] = {}

    def __call__(self, name: str, key: str, version: int, kind: str, build: Callable[[], Any], m: SegmentMap) -> Any:
        value = self.given.get(name)
        if value is None:
            if self.indexes is None:
                params = VOXEL_SIZE if kind == "reference" else self.p
                value = _WORKER_INDEXES.get(key, version, kind, build, (fingerprint(m), params))
                self.built[name] = value  # a worker's: the caller keeps it
            else:
                value = self.indexes.get(key, version, kind, build, None)
        return value


def fitted(job: PairJob, t: Transform2D, work: Work | None = None) -> tuple[Transform2D, tuple[float, ...] | None]:
    """A valid edge's transform and how firmly the walls fix it, on the two maps as they are:
    where either was integrated simplified, ``t`` fitted again by least squares
    (``polish_edges``), unless the fit moves it farther than the witness
    tolerances."""
    p, merge = job.integration, job.merge
    polish = merge.polish_edges and not (job.work_a is job.map_a and job.work_b is job.map_b)
    if not (polish or EDGE_INFORMATION):
        return t, None
    prep = prepare(job.map_a.segments, job.map_b.segments, job.map_a.oriented and job.map_b.oriented, p, work=work)
    if polish:
        candidate = refine_transform(prep, t, p, iterations=POLISH_ITERATIONS)
        dt, dr = candidate.distance(t)
        if dt <= WITNESS_TRANSLATION and dr <= WITNESS_ROTATION:
            t = candidate
    h = fit_information(prep, t, p) if EDGE_INFORMATION else None
    return t, None if h is None else tuple(np.asarray(h).ravel().tolist())


class Handle(Protocol):
    def result(self) -> Outcome: ...


def pair_result(handle: Handle) -> PairResult:
    """A :class:`PairJob`'s handle's result (:func:`run_job` gives a job's own kind)."""
    return cast(PairResult, handle.result())


def score_result(handle: Handle) -> ScoreResult:
    """A :class:`ScoreJob`'s handle's result."""
    return cast(ScoreResult, handle.result())


class Executor(Protocol):
    """Runs jobs (:func:`run_job`); :attr:`capacity` jobs in flight keep every worker busy (one
    each: a step past its time waits for those in flight, so no more; a step with no time keeps
    two each, :meth:`~fleetmap.merger.engine.Merger._integrate`)."""

    name: str

    @property
    def capacity(self) -> int: ...

    def submit(self, job: Job, here: Indexes | None = None) -> Handle:
        """Start a job; ``here`` is the caller's cache of indexes, for a job run in its process."""
        ...

    def close(self) -> None: ...


class _Deferred:
    def __init__(self, job: Job, indexes: Indexes) -> None:
        self._job, self._indexes = job, indexes
        self._result: Outcome | None = None

    def result(self) -> Outcome:
        if self._result is None:
            self._result = run_job(self._job, self._indexes)
        return self._result


class InlineExecutor:
    """Each job in this process, when its result is asked for (one at a time)."""

    name = "inline"

    def __init__(self, indexes: Indexes | None = None) -> None:
        self.indexes = indexes or Indexes()

    @property
    def capacity(self) -> int:
        return 1

    def submit(self, job: Job, here: Indexes | None = None) -> Handle:
        return _Deferred(job, here if here is not None else self.indexes)

    def close(self) -> None:
        pass


class _Pooled:
    def __init__(self, owner: LocalExecutor, job: Job) -> None:
        self._owner, self._job = owner, job
        try:
            self._future: Future[Outcome] = owner._pool_submit(job)
        except BrokenProcessPool as exc:  # said by result(), where the step takes failures
            self._future = Future()
            self._future.set_exception(exc)
        self._attempts = 1

    def result(self) -> Outcome:
        while True:
            try:
                return self._future.result()
            except BrokenProcessPool:
                if self._attempts >= MAX_ATTEMPTS:
                    raise
                self._attempts += 1
                log.warning(
                    "an integration worker died during %s-%s: running it again (attempt %d of %d)",
                    self._job.a,
                    self._job.b,
                    self._attempts,
                    MAX_ATTEMPTS,
                )
                self._future = self._owner._pool_submit(self._job)


def _start_worker(owner: int, niceness: int) -> None:
    """A pool worker's start: it ends with its owner (:func:`_end_with`), ``niceness`` below it."""
    _end_with(owner)
    os.nice(niceness)


def _end_with(owner: int) -> None:
    """In a pool worker: end when the process that owns the pool ends, however it ended. A worker
    of a killed merger would otherwise wait on its queue for ever (and keep the forkserver alive:
    each worker holds the pipe whose end tells the forkserver its owner is gone)."""

    def watch() -> None:
        try:
            fd = os.pidfd_open(owner)
        except (AttributeError, OSError):
            fd = None
        if fd is not None:
            select.select([fd], [], [])  # readable when the owner has ended
            os._exit(0)
        while True:  # no pidfd (old kernel): look once a second
            time.sleep(1.0)
            try:
                os.kill(owner, 0)
            except ProcessLookupError:
                os._exit(0)
            except PermissionError:
                pass

    threading.Thread(target=watch, name="fleetmap-end-with-owner", daemon=True).start()


class LocalExecutor:
    """A pool of ``workers`` local processes (default: one per CPU)."""

    name = "local"

    def __init__(self, workers: int | None = None, niceness: int = 0) -> None:
        """``niceness``: how far below this process its workers run (:data:`WORKER_NICENESS`)."""
        n = workers if workers is not None else (os.cpu_count() or 1)
        if n < 1:
            raise BadInput("--workers", f"needs at least one worker, got {n}")
        self.workers = n
        self.niceness = niceness
        self._pool: ProcessPoolExecutor | None = None
        self.restarts = 0
        """How often a dead worker broke the pool and it was started again."""
        self.submitted = 0
        """Jobs handed to the pool (again, after a restart) so far."""

    @property
    def capacity(self) -> int:
        return self.workers

    def _pool_submit(self, job: Job) -> Future[Outcome]:
        """Hand a job to the pool, starting it (again, if a dead worker broke it) as needed."""
        for _ in range(MAX_ATTEMPTS):
            if self._pool is not None and getattr(self._pool, "_broken", False):
                self._restart()
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    self.workers,
                    mp_context=multiprocessing.get_context("forkserver"),
                    initializer=_start_worker,
                    initargs=(os.getpid(), self.niceness),
                )
            try:
                future = self._pool.submit(run_job, job)
            except BrokenProcessPool:  # a worker died since the last look (idle between steps)
                self._restart()
                continue
            self.submitted += 1
            return future
        raise BrokenProcessPool(f"the integration pool broke {MAX_ATTEMPTS} times in a row")

    def _restart(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        self.restarts += 1

    @property
    def pids(self) -> list[int]:
        """The pool's worker processes now (none before the first job)."""
        processes = getattr(self._pool, "_processes", None) or {}
        return sorted(processes)

    def submit(self, job: Job, here: Indexes | None = None) -> Handle:
        return _Pooled(self, job)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class _RayHandle:
    def __init__(self, ref: Any) -> None:
        self._ref = ref

    def result(self) -> Outcome:
        import ray

        value: Outcome = ray.get(self._ref)
        return value


class RayExecutor:
    """Ray tasks on the cluster at ``address`` (None: a local one of ``workers`` CPUs, or the one
    ``ray.init`` finds by itself with ``address="auto"``). A task whose worker dies is run again
    (``max_retries``), so a lost worker loses no integration."""

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise BadInput(
                "--executor ray", "Ray is not installed: pip install 'fleetmap[ray]' (or choose --executor local)"
            ) from None
        self._ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "logging_level": "WARNING"}
            if address is None:
                kwargs["num_cpus"] = workers if workers is not None else (os.cpu_count() or 1)
            what = "--ray-address " + address if address is not None else "--executor ray"
            try:
                ray.init(address=address, **kwargs)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                where = "join the Ray cluster" if address is not None else "start a local Ray cluster"
                raise BadInput(what, f"cannot {where}: {exc}") from exc
        try:
            self._task = ray.remote(max_retries=MAX_ATTEMPTS, retry_exceptions=False)(run_job)
            self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        except Exception:
            self.close()  # the cluster this started goes with it
            raise

    @property
    def capacity(self) -> int:
        return self.workers

    def submit(self, job: Job, here: Indexes | None = None) -> Handle:
        return _RayHandle(self._task.remote(job))

    def close(self) -> None:
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()


def make_executor(
    kind: str = "inline", workers: int | None = None, address: str | None = None, niceness: int = 0
) -> Executor:
    """The executor a command line asks for (``--executor``, ``--workers``, ``--ray-address``);
    ``niceness``: a local pool's workers' (:data:`WORKER_NICENESS`)."""
    if kind == "inline":
        return InlineExecutor()
    if kind == "local":
        return LocalExecutor(workers, niceness)
    if kind == "ray":
        return RayExecutor(address, workers)
    raise BadInput("--executor", f"expected one of {', '.join(EXECUTORS)}, got {kind!r}")
