"""Where the last solve puts a submap, and where the paper's integration searches a pair of one
component: around where the last solve puts the two, no farther than an integration may lie and
still close its cycle.

The merger's cycle check takes an integration of two submaps of one component as a loop when it
lies within the tolerance of the forest's path between them
(:meth:`~fleetmap.merger.spanning.ForestBuilder.tree_tolerance`: the base tolerance of each
integration on the path and of the new one, and the drift its links allow); beyond it, the
integration is a conflict. Searching farther finds nothing the map can use, only aliases: a
corridor's walls match all along it. Cartographer searches a trajectory's own loop closures in a
window around where the trajectory puts them, and the whole map only between trajectories nothing
connects yet; the same here, with the window the graph's own uncertainty. On fr079, mit-csail and
aces whole, every valid loop the whole map's search found within the window was found in it,
for half to a third of the CPU (docs/decisions/037).
"""

from __future__ import annotations

import math

from fleetmap.merger.outputs import Placement
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Window


def search_window(
    graph: PoseGraph, a: str, b: str, predicted: Transform2D, stand_a: str, stand_b: str
) -> Window | None:
    """The window to integrate b on a in: centred on ``predicted`` (b's frame in a's, where the last
    solve puts them), as wide as the forest's tolerance between the submaps whose places stand for
    theirs (``stand_*``: a submap itself, or a new one's predecessor on its chain), widened for a
    new submap by its link's drift: a new b's link carried by the forest's rotation, a new a's
    heading turning all of b about a (first order, added: an upper bound). None if the two are not
    in one tree: the whole map."""
    tolerance = graph.tree_tolerance(stand_a, stand_b)
    if tolerance is None:
        return None
    radius, rotation = tolerance
    for key, stand in ((b, stand_b), (a, stand_a)):
        if key != stand:
            link, drift = graph.link_to(key), graph.chain_drift(stand, key)
            if link is None or drift is None:
                return None
            lever = math.hypot(link.transform.x, link.transform.y) if key == b else math.hypot(predicted.x, predicted.y)
            radius += drift[0] + (rotation if key == b else drift[1]) * lever
            rotation += drift[1]
    return Window(predicted, radius, rotation)


def window_in(graph: PoseGraph, a: str, b: str, p: Placement) -> Window | None:
    """:func:`search_window` for b on a around where the placement ``p`` puts them (None: either
    has no place, they are not in one tree, or only known start poses hold them together, metres
    off: :mod:`fleetmap.merger.startposes`)."""
    at_a, at_b = predicted_pose(graph, a, p), predicted_pose(graph, b, p)
    if at_a is None or at_b is None or not p.tied(a, b):
        return None
    return search_window(graph, a, b, at_a.inverse().compose(at_b), placed_as(graph, a, p), placed_as(graph, b, p))


def predicted_pose(graph: PoseGraph, key: str, p: Placement) -> Transform2D | None:
    """Where the graph puts a submap in its component's frame: its refined pose, or its
    predecessor's composed with its link."""
    if p.result is None:
        return None
    pose = p.result.poses.get(key)
    if pose is not None:
        return pose
    link = graph.link_to(key)
    if link is not None and p.result.poses.get(link.a) is not None:
        before = p.result.poses[link.a]
        return before.compose(link.transform) if before is not None else None
    return None


def placed_as(graph: PoseGraph, key: str, p: Placement) -> str:
    """The submap whose place stands for ``key``'s: itself, or for a new one its predecessor on
    its robot's chain."""
    link = graph.link_to(key)
    if key in p.where or link is None or link.a.split("/", 1)[0] != key.split("/", 1)[0]:
        return key
    return link.a
