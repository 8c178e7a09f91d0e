"""Numba loops compiled on their first call, so a process that never needs one never pays for it.

The core's compiled loops (the grid score's lookups, the beam test, the occupancy grid's beam
march, the registration's nearest cell, a transformation's matched pairs) are each built by a
function that imports Numba and defines the loop with ``cache=True``: compiled once, then loaded
from the cache beside its module (1-2 s to compile, a few milliseconds to load). Each is one
function that calls no other jitted function defined beside it: one that does is compiled again in
every process, its cache never matching (the matched pairs' loop did, 1.4 s a process).
:class:`Compiled` calls the building function the first time the loop is needed, once, whichever
thread asks first.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any


class Compiled:
    """A compiled loop, built by ``build`` on the first call and called with the same arguments."""

    def __init__(self, build: Callable[[], Callable[..., Any]]) -> None:
        self._build = build
        self._loop: Callable[..., Any] | None = None
        self._building = threading.Lock()

    def __call__(self, *args: Any) -> Any:
        loop = self._loop
        if loop is None:
            with self._building:  # two threads may ask at once (the grid score's two directions)
                if self._loop is None:
                    self._loop = self._build()
                loop = self._loop
        return loop(*args)
