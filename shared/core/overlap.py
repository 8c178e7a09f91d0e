"""How much wall two partial maps can share, before integrating them: the far search's ranking.

The descriptor (:mod:`fleetmap.shared.core.descriptor`) compares the pairwise geometric histograms
of two maps' whole walls: maps of one place score alike. Two maps that share only a part score
unlike, the more so the more their sizes differ, and that is how a tour cut into robots meets
itself: at each cut, the last short submap of one robot and the first of the next. On edmonton-c
cut in 4 the descriptor ranked those partners 40th of 47 and 43rd of 45, beyond the far search's
budget, and the robots stayed apart (docs/decisions/031).

The integration's own first stage ranks them first, by wide margins: the paper's candidate
transformations (Algorithms 2 and 3, on each map's longest walls), ranked by the coarse grid score
(:mod:`fleetmap.shared.core.mapgrid`: wall length that lands on a wall of the other facing the same
way, less wall in the other's seen free space). :func:`overlap_score` is the best such score, the
wall length, roughly, that the two maps can share at best, over one candidate of each of the most
supported cells of candidates (the cells of
:func:`~fleetmap.shared.core.distinct.distinct_candidates`' support): the right transformation is
found from many pairs of walls, an alias along parallel walls from few. The support alone (a
generalised Hough transform) does not rank them: the grid score is the evidence.
"""

from __future__ import annotations

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.distinct import SUPPORT_CELL, cell_keys, gather_candidates
from fleetmap.shared.core.integration import GRID_FINE, MAX_SEARCH_SEGMENTS, _longest
from fleetmap.shared.core.mapgrid import MapIndex, ranking_scores
from fleetmap.shared.core.segmap import SegmentMap

SCORED_CELLS = GRID_FINE
"""The most supported cells of candidates scored, one candidate each (as many candidates as the
integration scores finely)."""


def overlap_score(
    m1: SegmentMap, m2: SegmentMap, index1: MapIndex, index2: MapIndex, params: IntegrationParams
) -> float:
    """The best coarse grid score of m2 on m1 over the paper's candidate transformations (0 if
    there are none); ``index1`` and ``index2`` are the maps' grid indexes
    (:func:`~fleetmap.shared.core.integration.index_for`)."""
    search1, search2 = _longest(m1, MAX_SEARCH_SEGMENTS), _longest(m2, MAX_SEARCH_SEGMENTS)
    candidates, _ = gather_candidates(search1, search2, params.heuristic, params)
    if len(candidates) == 0:
        return 0.0
    _, first, support = np.unique(cell_keys(candidates, *SUPPORT_CELL), return_index=True, return_counts=True)
    best = first[np.argsort(-support, kind="stable")[:SCORED_CELLS]]
    return float(ranking_scores(index1, index2, candidates[best], fine=False).max())
