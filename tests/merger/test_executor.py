"""Where integrations run: a local process pool and a local Ray cluster give the inline merge's
poses exactly, also when a worker is killed in the middle of the merge."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from fleetmap.merger.executor import Executor, LocalExecutor, make_executor
from fleetmap.shared.errors import BadInput

from fleetmap.cli import main
from fleetmap.config_args import preset
from fleetmap.mapping import MapResult, Piece, map_logs

WAIT = 120.0
"""Seconds a killer thread waits for a worker to kill (a bound, never reached when it works)."""


@pytest.fixture(scope="module")
def pieces(csail_pieces: list[Piece]) -> list[Piece]:
    """360 real scans (mit-csail) as two robots: a merge of a dozen submaps and their integrations."""
    return csail_pieces


Poses = list[tuple[str, float, int, float, float, float]]


def _poses(result: MapResult) -> Poses:
    return [(robot, stamp, c, p.x, p.y, p.theta) for robot, stamp, c, p in result.poses]


def _merge(pieces: list[Piece], executor: Executor, out: Path) -> Poses:
    return _poses(map_logs(pieces, out, preset("offline"), None, executor))


@pytest.fixture(scope="module")
def inline_poses(csail_in_line: tuple[MapResult, Path]) -> Poses:
    poses = _poses(csail_in_line[0])
    assert len(poses) == len({(r, s) for r, s, *_ in poses}) > 300 and {c for _, _, c, *_ in poses} == {0}
    return poses


def _kill_one(find: Callable[[], list[int]], done: threading.Event, killed: list[int]) -> threading.Thread:
    """A thread that kills the first worker ``find`` names (SIGKILL: no goodbye) while the merge runs."""

    def run() -> None:
        while not done.wait(0.01):
            pids = find()
            if pids:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
                return

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


@pytest.mark.slow  # maps 360 real scans on a pool (about 15 s; an undisturbed pool: tests/test_map.py)
def test_a_process_pool_merges_to_the_inline_poses_even_when_a_worker_dies(
    pieces: list[Piece], inline_poses: Poses, tmp_path: Path
) -> None:
    killed: list[int] = []
    done = threading.Event()
    doomed = LocalExecutor(2)
    # once a few jobs went out, one worker dies under the ones in flight
    thread = _kill_one(lambda: doomed.pids if doomed.submitted >= 3 else [], done, killed)
    try:
        poses = _merge(pieces, doomed, tmp_path / "killed")
    finally:
        done.set()
        thread.join(WAIT)
        doomed.close()
    assert killed, "no worker was killed"
    assert doomed.restarts >= 1
    assert poses == inline_poses


def _ray_workers_running_a_job() -> list[int]:
    """Ray names a worker process after the task it runs (``ray::run_job``)."""
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as fh:
                    if fh.read().startswith(b"ray::run_job"):
                        out.append(int(pid))
            except OSError:
                continue
    return out


@pytest.mark.slow  # starts a local Ray cluster of 2 CPUs and maps 360 real scans on it (about 35 s)
def test_a_local_ray_cluster_merges_to_the_inline_poses_even_when_a_worker_dies(
    pieces: list[Piece], inline_poses: Poses, tmp_path: Path
) -> None:
    pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'fleetmap[ray]'")
    on_ray = make_executor("ray", workers=2)
    try:
        assert on_ray.capacity == 2  # one job in flight per CPU
        killed: list[int] = []
        done = threading.Event()
        thread = _kill_one(_ray_workers_running_a_job, done, killed)
        try:
            poses = _merge(pieces, on_ray, tmp_path / "killed")
        finally:
            done.set()
            thread.join(WAIT)
    finally:
        on_ray.close()
    assert killed, "no Ray worker was seen running an integration"
    assert poses == inline_poses


def test_an_unknown_executor_or_no_workers_is_refused_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(BadInput, match="--executor"):
        make_executor("threads")
    with pytest.raises(BadInput, match="--workers"):
        LocalExecutor(0)
    with pytest.raises(SystemExit) as exc:
        main(["merger", "--workers", "0"])
    assert exc.value.code == 2
    assert "--workers" in capsys.readouterr().err


OWNER = """
import sys
import numpy as np
from fleetmap.merger.executor import LocalExecutor, PairJob
from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
from fleetmap.shared.core.segmap import SegmentMap

if __name__ == "__main__":
    walls = SegmentMap(np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [0.0, 3.0, 0.0, 0.0]]), oriented=True)
    params = IntegrationParams(), TrackingParams(), MergeParams()
    job = PairJob("a", "b", (0, 0), walls, walls, walls, walls, None, *params)
    pool = LocalExecutor(2)
    pool.submit(job).result()
    print(" ".join(str(p) for p in pool.pids), flush=True)
    sys.stdin.read()  # until killed
"""


@pytest.mark.slow  # starts a process with a pool of two workers and kills it
def test_the_workers_of_a_killed_merger_end_with_it(tmp_path: Path) -> None:
    import subprocess
    import sys
    import time

    script = tmp_path / "owner.py"
    script.write_text(OWNER)
    owner = subprocess.Popen([sys.executable, str(script)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout is not None
        workers = [int(p) for p in owner.stdout.readline().split()]
        assert workers and all(_alive(p) for p in workers)
    finally:
        owner.kill()
        owner.wait(30)
    deadline = time.monotonic() + WAIT
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        threading.Event().wait(0.1)
    assert not any(_alive(p) for p in workers), "a worker outlived the process that owned its pool"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow  # starts a pool, kills its idle worker
def test_a_worker_that_died_while_idle_is_replaced_at_the_next_job() -> None:
    import numpy as np
    from fleetmap.merger.executor import PairJob
    from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
    from fleetmap.shared.core.segmap import SegmentMap

    walls = SegmentMap(np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [0.0, 3.0, 0.0, 0.0]]), oriented=True)
    params = IntegrationParams(), TrackingParams(), MergeParams()
    job = PairJob("a", "b", (0, 0), walls, walls, walls, walls, None, *params)
    pool = LocalExecutor(1)
    try:
        first = pool.submit(job).result()
        (worker,) = pool.pids
        os.kill(worker, signal.SIGKILL)
        pause = threading.Event()
        for _ in range(600):  # the pool notices its dead worker within moments
            if getattr(pool._pool, "_broken", False):
                break
            pause.wait(0.05)
        again = pool.submit(job).result()
    finally:
        pool.close()
    assert pool.restarts >= 1 and again.transform == first.transform


@pytest.mark.slow  # starts two process pools
def test_fleetmap_maps_pool_workers_yield_the_cpu_to_its_agents_and_a_live_mergers_do_not() -> None:
    # fleetmap map's agents track in processes beside the pool: on a busy machine the scheduler
    # must give them the CPU first (aces cut in 8: the agents' tracking 76-85 s beside a pool at
    # the same priority, 62-66 s beside one that yields); a live merger's robots track elsewhere
    import argparse

    import numpy as np
    from fleetmap.merger.executor import WORKER_NICENESS, PairJob
    from fleetmap.shared.config import IntegrationParams, MergeParams, TrackingParams
    from fleetmap.shared.core.segmap import SegmentMap

    from fleetmap.executor_args import executor_from_args

    walls = SegmentMap(np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [0.0, 3.0, 0.0, 0.0]]), oriented=True)
    job = PairJob(
        "a", "b", (0, 0), walls, walls, walls, walls, None, IntegrationParams(), TrackingParams(), MergeParams()
    )
    mine = os.getpriority(os.PRIO_PROCESS, 0)
    args = argparse.Namespace(executor="local", workers=1, ray_address=None)
    for niceness, expected in ((WORKER_NICENESS, min(19, mine + WORKER_NICENESS)), (0, mine)):
        pool = executor_from_args(args, niceness)
        assert isinstance(pool, LocalExecutor)
        try:
            assert pool.submit(job).result().integration.valid
            workers = [os.getpriority(os.PRIO_PROCESS, pid) for pid in pool.pids]
        finally:
            pool.close()
        assert workers and all(n == expected for n in workers), f"ours {mine}, workers {workers}, expected {expected}"
