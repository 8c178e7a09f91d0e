"""What the merger makes of the robots' clocks.

A robot's stamps label its messages; they do not order them (its own counts do: epoch, submap
and version, scan index). The one judgement made of a stamp is against the receiver's clock: a
stamp more than :data:`CLOCK_SKEW` ahead of it is refused, dropped and counted, as Kerberos refuses
a ticket from further than its allowed skew. Without it, one message stamped in the year 2260 was
the newest thing a robot had said for the rest of the session.
"""

from __future__ import annotations

CLOCK_SKEW = 300.0
"""How far ahead of the merger's clock (s) a robot's stamp may be: five minutes, Kerberos's
default allowed skew; a robot without NTP that is further ahead has its messages refused, and the
merger's log says so."""


def from_the_future(stamp: float, now: float | None) -> bool:
    """Whether ``stamp`` is further ahead of ``now`` (the receiver's clock, s since 1970; None: no
    clock, as in a replay) than :data:`CLOCK_SKEW`."""
    return now is not None and stamp > now + CLOCK_SKEW
