"""The pivot front end's read-only view of its epochs (:attr:`PivotFrontEnd.epochs`): which scans it
placed in each local map and where, as its messages say (``benchmarks/merge.py`` reads it)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fleetmap.agents.pivot import KIDNAP_REASON, ONE_SCAN_REASON, PivotFrontEnd
from fleetmap.scenarios import SimulatedScan
from fleetmap.shared.io.messages import FleetEvent, LocalMap, Message, Scan

from tests.agents.conftest import blocked, kidnap_index


def _drive(scans: list[SimulatedScan]) -> tuple[PivotFrontEnd, list[Message], dict[int, tuple[int, object]]]:
    """The front end after ``scans``, its messages, and per scan placed as the last one of its
    ``add_scan`` (the robot's epoch and pose right after it)."""
    front = PivotFrontEnd("r1")
    messages: list[Message] = []
    now: dict[int, tuple[int, object]] = {}
    for s in scans:
        messages += front.add_scan(s.index, s.stamp, s.scan)
        if front.epoch_pose is not None:
            now[s.index] = (front.epoch, front.epoch_pose)
    return front, messages + front.finish(), now


def _check_consistent(front: PivotFrontEnd, messages: list[Message], now: dict[int, tuple[int, object]]) -> None:
    epochs = front.epochs
    said = {m.index: m.epoch for m in messages if isinstance(m, Scan)}
    events = [json.loads(m.detail) for m in messages if isinstance(m, FleetEvent) and m.kind == "epoch"]
    first = {0: min(i for e in epochs for i, _ in e.scans)} | {e["epoch"]: e["first_scan"] for e in events}
    # one record per epoch, numbered as the messages number them
    assert [e.number for e in epochs] == sorted(first) == list(range(max(said.values()) + 1))
    placed = [i for e in epochs for i, _ in e.scans]
    assert placed == sorted(set(placed)), "each scan placed once, in order"
    assert len(placed) == front.counts.placed
    for e in epochs:
        indices = [i for i, _ in e.scans]
        # the epoch's frame is its first scan (the event's first_scan), placed at the identity
        assert indices[0] == first[e.number]
        assert max(e.scans[0][1].distance(e.scans[0][1].identity())) < 1e-12
        # a scan is published in the epoch it went into, or in an earlier one when it was placed
        # later, as a seed of a new epoch (unplaced when it was published)
        assert all(said[i] <= e.number for i in indices)
        # a scan placed when published is in its Scan's epoch, at the pose the robot had then
        for i, (epoch, pose) in now.items():
            if epoch == e.number and said[i] == e.number:
                assert (i, pose) in e.scans
        # the epoch's last local map message says as much
        final = [m for m in messages if isinstance(m, LocalMap) and m.epoch == e.number][-1]
        assert final.scans == len(e.scans)
        kept = np.asarray(final.segments)
        assert kept.shape[0] <= len(e.map) and np.isin(kept, e.map.segments).all()


@pytest.mark.slow  # a kidnapped robot's whole stream through the pivot front end
def test_a_kidnap_puts_the_scans_after_it_in_the_next_epoch(kidnapped_stream):
    front, messages, now = _drive(kidnapped_stream)
    _check_consistent(front, messages, now)
    kidnap = kidnap_index(kidnapped_stream)
    old, new = front.epochs
    assert max(i for i, _ in old.scans) < kidnap == new.scans[0][0]
    link = next(m.previous_epoch_link for m in messages if isinstance(m, LocalMap) and m.epoch == 1)
    assert (link.epoch, link.reason) == (0, KIDNAP_REASON.format(n=2))


def test_scans_placed_while_seeding_a_new_epoch_are_recorded_in_it(sparse_r2_stream):
    # Two blocked scans in a row (boards in front of the laser, 0.5 m and 1.5 m away) start epoch 1
    # from the first; the second does not integrate with it (a map of one scan), so epoch 2 starts
    # from the second while epoch 1 is seeded; the next clear scan does not integrate with epoch 2's
    # board either: epoch 3, which the clear scans after it go on.
    s = sparse_r2_stream
    front, messages, now = _drive([*s[:3], blocked(s[3]), blocked(s[4], 1.5, 20.0), *s[5:8]])
    _check_consistent(front, messages, now)
    reasons = [json.loads(m.detail)["reason"] for m in messages if isinstance(m, FleetEvent)]
    assert reasons == [KIDNAP_REASON.format(n=2), ONE_SCAN_REASON, ONE_SCAN_REASON]
    by_epoch = {e.number: [i for i, _ in e.scans] for e in front.epochs}
    assert by_epoch == {0: [x.index for x in s[:3]], 1: [s[3].index], 2: [s[4].index], 3: [x.index for x in s[5:8]]}
    # scan 3 was published in epoch 0 (unplaced then), and placed in epoch 1 while seeding it;
    # no Scan message says epoch 1
    said = {m.index: m.epoch for m in messages if isinstance(m, Scan)}
    assert (said[s[3].index], said[s[4].index]) == (0, 2)


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_the_epochs_are_read_only_and_change_no_message(sparse_r2_stream):
    scans = sparse_r2_stream[:5]
    quiet = PivotFrontEnd("r1")
    looked = PivotFrontEnd("r1")
    first: list[bytes] = []
    second: list[bytes] = []
    for x in scans:
        first += [m.to_msgpack() for m in quiet.add_scan(x.index, x.stamp, x.scan)]
        looked.epochs  # noqa: B018 - reading it must change nothing
        second += [m.to_msgpack() for m in looked.add_scan(x.index, x.stamp, x.scan)]
        assert [len(e.scans) for e in looked.epochs] == [looked.counts.placed]
    assert first + [m.to_msgpack() for m in quiet.finish()] == second + [m.to_msgpack() for m in looked.finish()]
    with pytest.raises(AttributeError):
        looked.epochs = []  # type: ignore[misc]
