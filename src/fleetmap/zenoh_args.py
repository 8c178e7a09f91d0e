"""What the zenoh services' commands share: their flags, opening the bus, stopping on a signal.

Every service (``fleetmap record``, ``fleetmap router``, the agent and the merger) takes the same
``--mode/--connect/--listen/--zenoh-config/--fleet`` flags (see
:mod:`fleetmap.shared.io.zenoh_config` for what they default to) and stops cleanly on SIGINT or
SIGTERM alike, so ``kill PID`` and Ctrl-C both leave finished files behind.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

from fleetmap.shared.io.zenoh_config import ZenohOptions, add_zenoh_arguments, zenoh_options_from_args

__all__ = ["ZenohOptions", "add_zenoh_arguments", "stop_on_signals", "zenoh_options_from_args"]

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs (main thread only).

    The service waits on it (``while not stop.wait(0.1): ...``) and shuts down cleanly when it
    is set; the previous handlers are restored afterwards.
    """
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
