"""The ``--executor/--workers/--ray-address`` flags of the commands that integrate submaps
(``fleetmap merger`` and ``fleetmap map``): where the integrations run
(:mod:`fleetmap.merger.executor`). Every choice gives the same map."""

from __future__ import annotations

import argparse

from fleetmap.merger.executor import EXECUTORS, Executor, make_executor


def add_executor_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("integration workers")
    g.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="local",
        help="where integrations run: inline (in this process), local (a process pool, the default) or ray "
        "(Ray tasks; pip install 'fleetmap[ray]'). The map is the same whichever runs them",
    )
    g.add_argument(
        "--workers",
        type=_workers,
        default=None,
        metavar="N",
        help="local: processes in the pool; ray: CPUs of the local cluster it starts (default: this machine's CPUs)",
    )
    g.add_argument(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="ray: the cluster to join (host:port of its head, or 'auto'; default: start a local one)",
    )


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of workers, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"needs at least one worker, got {n}")
    return n


def executor_from_args(args: argparse.Namespace, niceness: int = 0) -> Executor:
    """``niceness``: a local pool's workers' (:data:`~fleetmap.merger.executor.WORKER_NICENESS`)."""
    if args.ray_address is not None and args.executor != "ray":
        raise SystemExit(f"fleetmap: --ray-address needs --executor ray (got --executor {args.executor})")
    return make_executor(args.executor, args.workers, args.ray_address, niceness)
