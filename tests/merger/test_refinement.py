"""The refinement of a component's poses (``merger/refinement.py``)."""

from __future__ import annotations

import numpy as np
from fleetmap.merger.graph import Edge
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.segmap import SegmentMap

BOX = np.array([[1.0, -0.3, 1.0, 0.3], [1.0, 0.3, 1.4, 0.3], [1.4, 0.3, 1.4, -0.3], [1.4, -0.3, 1.0, -0.3]])


def test_a_ring_the_last_solve_left_wound_twice_round_is_refined_to_its_links() -> None:
    # A robot drives an octagon (2 m, then 45 degrees, eight times) and its last submap integrates
    # with its first. Where the last solve left the ring wound twice round (each step turned 90
    # degrees: a fold a wrong loop left behind), every link is 45 degrees (9 sigma) off and the
    # descent from there stays wound: freiburg-campus cut in 2 kept links 116-163 degrees off that
    # way, its map 70 m off (docs/decisions/039). The refinement must end where its links put the
    # ring, as a descent from the spanning tree does.
    graph = PoseGraph()
    cov = np.diag([0.1**2, 0.1**2, np.radians(5.0) ** 2])
    step = Transform2D(2.0, 0.0, np.radians(45.0))
    keys = [f"r1/0/{n}" for n in range(8)]
    for n, key in enumerate(keys):
        graph.put_map(key, SegmentMap(BOX, ordered=False, oriented=True), 1)
        if n:
            graph.put_link(keys[n - 1], key, step, cov)
    graph.add_edge(Edge(keys[7], keys[0], step, 30.0, True))
    ring = graph.solve().components[0]
    assert ring.anchor == keys[0] and len(ring.members) == 8
    wound, pose = Transform2D(2.0, 0.0, np.radians(90.0)), Transform2D.identity()
    for key in keys:  # the same anchor, the same tree above each submap: the last solve's poses are its start
        anchor, path, _ = graph._solution[key]
        graph._solution[key] = (anchor, path, pose)
        pose = pose.compose(wound)
    graph._refined_now, graph._kept = {}, None  # nothing kept: the component is refined again
    again = graph.solve().components[0]
    for key in keys:
        dt, dr = again.poses[key].distance(ring.poses[key])
        assert dt < 0.01 and np.degrees(dr) < 0.1, f"{key}: {dt:.2f} m, {np.degrees(dr):.0f} deg off its links' ring"
