"""Drawing merged maps (matplotlib, no screen needed).

What a person reads first is the global map, so the fused walls are drawn on top, dark; each
robot's own walls lie under them in the robot's colour, pale, with its path where it is known; the
true walls, when a scenario has them, are the wide grey band beneath everything. One legend row per
robot (or per map where maps have no robot), outside the axes so it never covers the map.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D
from matplotlib.collections import LineCollection
from matplotlib.lines import Line2D

LEGEND_ROWS = 24
"""Legend rows in one column; more robots take more columns."""


def plot_merged(
    path: str | Path,
    maps: Mapping[str, Array],
    poses: Mapping[str, Transform2D | None],
    *,
    truth: Array | None = None,
    fused: Array | None = None,
    notes: Sequence[str] = (),
    title: str = "fleetmap: merged map",
    groups: Mapping[str, str] | None = None,
    paths: Mapping[str, Array] | None = None,
) -> list[str]:
    """Each placed map at its pose under the ``fused`` walls, over the ``truth`` walls when known.
    ``groups`` names each map's robot (one colour and one legend row each; default: each map its
    own); ``paths`` holds each robot's placed laser positions ``(n, 2)`` in order, drawn as its
    path. Unplaced maps and ``notes`` (e.g. other components) are listed under the plot. Returns
    the legend's rows."""
    group = {name: (groups or {}).get(name, name) for name in maps}
    names = sorted(set(group.values()) | set(paths or {}))
    cmap = plt.get_cmap("tab10" if len(names) <= 10 else "tab20")
    colour = {g: cmap(i % cmap.N) for i, g in enumerate(names)}
    fig, ax = plt.subplots(figsize=(10, 8))
    handles: list[Line2D] = []
    if truth is not None and len(truth):
        ax.add_collection(LineCollection(list(truth.reshape(-1, 2, 2)), colors="0.85", linewidths=4.0, zorder=1))
        handles.append(Line2D([], [], color="0.85", linewidth=4.0, label="true walls"))
    unplaced: list[str] = []
    counts: dict[str, int] = dict.fromkeys(names, 0)
    drawn: dict[str, list[Array]] = {}
    for name, segments in maps.items():
        pose = poses.get(name)
        if pose is None:
            unplaced.append(name)
            continue
        counts[group[name]] += 1
        drawn.setdefault(group[name], []).append(pose.apply(np.asarray(segments)).reshape(-1, 2, 2))
    for g, parts in drawn.items():  # one collection per robot: a thousand submaps draw as fast as ten
        ax.add_collection(
            LineCollection(list(np.concatenate(parts)), colors=[colour[g]], linewidths=1.6, alpha=0.45, zorder=2)
        )
    for g, xy in (paths or {}).items():
        xy = np.asarray(xy).reshape(-1, 2)
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], color=colour[g], linewidth=0.9, zorder=3)
            ax.plot(xy[:1, 0], xy[:1, 1], color=colour[g], marker="o", markersize=5, zorder=3)
    if fused is not None and len(fused):
        ax.add_collection(LineCollection(list(fused.reshape(-1, 2, 2)), colors="black", linewidths=0.7, zorder=4))
        handles.append(Line2D([], [], color="black", linewidth=0.7, label="global map (fused walls)"))
    for g in names:
        what = f"{counts[g]} map{'s' if counts[g] != 1 else ''} placed" if groups else "placed"
        if paths and g in paths:
            what += ", path from the dot"
        handles.append(
            Line2D([], [], color=colour[g], linewidth=2.0, label=f"{g}: {what}" if counts[g] else f"{g}: not placed")
        )
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    columns = max(1, -(-len(handles) // LEGEND_ROWS))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, ncols=columns, frameon=False)
    text = list(notes)
    if unplaced:
        shown = ", ".join(unplaced[:12]) + (f" and {len(unplaced) - 12} more" if len(unplaced) > 12 else "")
        text.append(f"not placed: {shown}")
    if text:
        fig.text(0.01, 0.01, "\n".join(text[:12]), fontsize=7, va="bottom", family="monospace", wrap=True)
    fig.tight_layout(rect=(0, 0.03 + 0.015 * min(len(text), 12), 1, 1))
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return [str(h.get_label()) for h in handles]
