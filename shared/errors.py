"""One exception hierarchy for the whole library; the CLI turns it into exit codes."""

from __future__ import annotations


class FleetmapError(Exception):
    """Base class of every error fleetmap raises on purpose."""


class BadInput(FleetmapError):
    """Input that cannot be used: a file, a message or a value, named in the message.

    ``source`` names the input (a path, a message key, a config field) and ``reason`` says
    what is wrong with it; ``str()`` gives the one line the CLI prints.
    """

    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = reason
        super().__init__(f"{source}: {reason}")

    def __reduce__(self) -> tuple[type, tuple[str, str]]:
        # pickled by what it was made from, not by its one-line message (Exception's default), so
        # that it crosses a process pool: unpickling it by the message alone fails in the pool's
        # result thread, and the pool then waits for the result for ever
        return type(self), (self.source, self.reason)


class ConfigError(BadInput):
    """A configuration file or override that names an unknown field or a bad value."""
