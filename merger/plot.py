"""Drawing merged maps (matplotlib, no screen needed)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from fleetmap.shared.geometry import Array, Transform2D
from matplotlib.collections import LineCollection


def plot_merged(
    path: str | Path,
    maps: Mapping[str, Array],
    poses: Mapping[str, Transform2D | None],
    *,
    truth: Array | None = None,
    fused: Array | None = None,
    notes: Sequence[str] = (),
    title: str = "fleetmap: merged map",
    colors: Mapping[str, int] | None = None,
) -> None:
    """Each placed map in its own colour (or its group's, ``colors``: e.g. one per robot) over the
    true walls when known; unplaced maps and ``notes`` (e.g. rejected edges) listed under the plot."""
    fig, ax = plt.subplots(figsize=(9, 8))
    if truth is not None and len(truth):
        ax.add_collection(
            LineCollection(list(truth.reshape(-1, 2, 2)), colors="0.8", linewidths=3.0, label="true walls")
        )
    if fused is not None and len(fused):
        ax.add_collection(
            LineCollection(list(fused.reshape(-1, 2, 2)), colors="0.3", linewidths=0.6, label="fused map")
        )
    cmap = plt.get_cmap("tab10" if len(maps) <= 10 else "tab20")
    unplaced = []
    for i, (name, segments) in enumerate(maps.items()):
        pose = poses.get(name)
        if pose is None:
            unplaced.append(name)
            continue
        moved = pose.apply(segments)
        colour = cmap((colors[name] if colors is not None and name in colors else i) % cmap.N)
        ax.add_collection(LineCollection(list(moved.reshape(-1, 2, 2)), colors=[colour], linewidths=1.2, label=name))
        ax.plot([pose.x], [pose.y], marker="o", color=colour, markersize=4)
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=7, framealpha=0.8)
    lines = list(notes)
    if unplaced:
        lines.append("not placed: " + ", ".join(unplaced))
    if lines:
        fig.text(0.01, 0.01, "\n".join(lines[:12]), fontsize=7, va="bottom", family="monospace")
    fig.tight_layout(rect=(0, 0.03 + 0.012 * min(len(lines), 12), 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
