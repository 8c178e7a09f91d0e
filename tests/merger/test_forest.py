"""The rooted forest answers what a search along the forest answered: the same paths, the same drift."""

from __future__ import annotations

import itertools
import math
import random

import numpy as np
import pytest
from fleetmap.merger.forest import RootedForest
from fleetmap.merger.graph import Edge, _tree_path
from fleetmap.merger.posegraph import PoseGraph
from fleetmap.shared.core.geometry import Transform2D


def _fleet_forest(seed: int) -> tuple[list[str], dict[str, list[Edge]], dict[tuple[str, str], np.ndarray]]:
    """Robots' chains of submaps (links with covariances), some chains joined by integrations, as a
    forest: each robot's chain, then joins between chains that are not joined yet."""
    rng = random.Random(seed)
    keys: list[str] = []
    adjacency: dict[str, list[Edge]] = {}
    covariances: dict[tuple[str, str], np.ndarray] = {}
    root: dict[str, str] = {}

    def add(e: Edge) -> None:
        adjacency[e.a].append(e)
        adjacency[e.b].append(e.reversed())

    for r in range(6):
        chain = [f"r{r}/0/{n}" for n in range(rng.randint(1, 30))]
        for k in chain:
            keys.append(k)
            adjacency[k] = []
            root[k] = chain[0]
        for a, b in itertools.pairwise(chain):
            t = Transform2D(rng.uniform(0.5, 3.0), rng.uniform(-0.5, 0.5), rng.uniform(-0.6, 0.6))
            cov = np.diag([rng.uniform(1e-4, 1e-2), rng.uniform(1e-4, 1e-2), rng.uniform(1e-5, 1e-3)])
            covariances[(a, b)] = covariances[(b, a)] = cov
            add(Edge(a, b, t, math.inf, True, link=True))
    for _ in range(8):
        a, b = rng.sample(keys, 2)
        if root[a] == root[b]:
            continue
        add(Edge(a, b, Transform2D(rng.uniform(-9, 9), rng.uniform(-9, 9), rng.uniform(-3, 3)), 20.0, True))
        old = root[b]
        for k in keys:
            if root[k] == old:
                root[k] = root[a]
    return keys, adjacency, covariances


@pytest.mark.parametrize("seed", range(5))
def test_paths_and_drift_are_those_of_a_search_along_the_forest(seed: int) -> None:
    keys, adjacency, covariances = _fleet_forest(seed)
    forest = RootedForest(keys, adjacency, covariances)
    graph = PoseGraph()
    graph._link_covariances = covariances
    rng = random.Random(seed + 100)
    connected = 0
    for _ in range(200):
        a, b = rng.sample(keys, 2)
        searched = _tree_path(adjacency, a, b)
        assert sorted(forest.path_keys(a, b)) == sorted(e.key() for e in searched)
        if not searched:
            assert forest.lowest_common(a, b) is None
            continue
        connected += 1
        expected = graph._cycle_tolerance(searched)
        got = graph._tolerance_between(forest, a, b)
        assert got == pytest.approx(expected, rel=1e-9, abs=1e-12)
    assert connected > 20


@pytest.mark.parametrize("seed", range(3))
def test_a_forest_grown_leaf_by_leaf_finds_the_ancestors_a_climb_finds(seed: int) -> None:
    # the kept solve hangs each new submap from its parent as a leaf (add_leaf); the lowest common
    # ancestor is found by jumps of 1, 2, 4, ... levels, so the chains are made long and bushy
    rng = random.Random(seed)
    forest = RootedForest([], {}, {})
    parent: dict[str, str | None] = {}
    for t in range(3):
        forest.add_root(f"t{t}")
        parent[f"t{t}"] = None
    for n in range(400):
        # mostly the newest node (a robot's chain), now and then any (a branch)
        up = f"n{n - 1}" if n > 0 and rng.random() < 0.8 else rng.choice(sorted(parent))
        key = f"n{n}"
        forest.add_leaf(Edge(up, key, Transform2D(1.0, 0.0, 0.0), math.inf, True, link=True), {})
        parent[key] = up

    def ancestors(k: str) -> list[str]:
        out = [k]
        while parent[out[-1]] is not None:
            out.append(parent[out[-1]])  # type: ignore[arg-type]
        return out

    for _ in range(500):
        a, b = rng.sample(sorted(parent), 2)
        above_b = set(ancestors(b))
        expected = next((k for k in ancestors(a) if k in above_b), None)
        assert forest.lowest_common(a, b) == expected
