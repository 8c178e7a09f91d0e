"""Subcommands of the fleetmap CLI: each module has ``register(subparsers)`` setting ``func``."""

from __future__ import annotations

import argparse
import math


def add_no_return_reading(group: argparse._ActionsContainer) -> None:
    """``--no-return-reading R`` (``args.no_return_reading``): a CARMEN log's reading that means no
    return. Named apart from ``--max-range``, extraction's cut-off (a parameter); its old name
    ``--range-max`` is still accepted, not shown."""
    group.add_argument(
        "--no-return-reading",
        type=float,
        default=math.inf,
        metavar="R",
        help="CARMEN FLASER/RLASER logs: the reading that means no return; readings at or above it are "
        "no return (e.g. 81.91; not --max-range, extraction's cut-off)",
    )
    group.add_argument(
        "--range-max", dest="no_return_reading", type=float, default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
