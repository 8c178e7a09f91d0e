"""A robot's first steps down a corridor whose doors repeat: where the scan pair's integration is
ambiguous, its best transformation is a start of the window's search, and the pair's fit stays in
the race against a turned start (docs/decisions/069)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.logs import read_carmen
from fleetmap.shared.io.sources import CarmenSource

from tests.helpers import steps_off, tracked

OREBRO = Path("corrected") / "orebro-corrected.log.gz"


def orebro_piece(datasets: Path, start: int, stop: int) -> tuple[int, dict[int, tuple[float, float]]]:
    """orebro-corrected's scans ``start:stop`` as one robot (the log has no wheel readings there),
    as ``fleetmap map --split 8`` cuts it: its epochs, and its steps 0.3 m or 5 degrees off the
    corrected poses' (m, deg), by the later scan."""
    path = datasets / OREBRO
    agent, poses = tracked(itertools.islice(CarmenSource(path, range_max=math.inf), start, stop))
    truth = [Transform2D(*s.odometry) for s in itertools.islice(read_carmen(path), stop)]
    missing = [i for i in range(start, stop) if i not in poses]
    assert not missing, f"scans not placed: {missing}"
    return agent.counts.epochs, steps_off(truth, poses, range(start + 1, stop))


@pytest.mark.slow  # tracks 30 scans of a real log (about 5 s)
def test_a_robots_second_scan_down_a_corridor_whose_doors_repeat_is_placed_where_the_pair_fits_best(
    datasets: Path,
) -> None:
    # Robot 6 of orebro-corrected cut in 8 (scans 150-179): scan 151 is 1.2 m on from 150. Nothing
    # measured the motion yet (standing still, 3 m wide) and the scan pair's integration is
    # ambiguous (its best 0.09 m off, a rival 2.5 m back at 0.9 of its value). The window's
    # best-supported positions all lay behind the robot (a scan placed short overlaps more of the
    # one wall seen), and the fit 1.8 m back was taken: 3 m off, and every relation of scan 150
    # with that robot's own and another's wrong (5 wrong relations, the log's only ones cut in 8).
    # Registered from the pair's best, the scan fits the submap better (7.0 against 5.9), its
    # beams through none of the walls
    epochs, off = orebro_piece(datasets, 150, 180)
    assert epochs == 1
    assert not off, f"steps off (scan: metres, degrees): {off}"


@pytest.mark.slow  # tracks 30 scans of a real log (about 5 s)
def test_a_turned_fit_that_barely_outscores_the_step_the_scan_pair_measured_does_not_replace_it(
    datasets: Path,
) -> None:
    # Robot 2 of orebro-corrected cut in 8 (scans 30-59): the pair 35 -> 36 integrates valid and
    # right (2.9 m on, 12 degrees round), its fit on the submap weak (4.29, the robot's floor
    # 5.00). A start turned round fitted at 5.33, typical, and was taken: scan 36 placed
    # 180 degrees round, and its submap's link turned with it. A later start must outscore the
    # pair's fit twice over, turned or not
    _epochs, off = orebro_piece(datasets, 30, 60)
    assert 36 not in off, f"steps off (scan: metres, degrees): {off}"
    # (scan 31, 2 m on, fits the corridor as well standing still as where it was: 9.99 against
    # 10.00, no beam through a wall either way; nothing measured the motion yet)
    assert set(off) <= {31}, f"steps off (scan: metres, degrees): {off}"
