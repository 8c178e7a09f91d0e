"""What an agent has done so far (both front ends report it)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class AgentCounts:
    """What an agent has done so far."""

    scans: int
    placed: int
    """Scans placed in their epoch (each epoch's first scan included)."""
    epochs: int
    """Epochs started (0 until the first scan with segments)."""
    local_maps: int
    """LocalMap versions emitted (republished ones not counted)."""
