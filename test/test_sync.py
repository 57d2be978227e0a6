"""Stamp pairing and the newest-wins hand-off used by the nodes."""

from __future__ import annotations

import threading

from pcc_ros.runtime.pairing import LatestSlot, StampPairer

MS = 1_000_000


def test_pairs_within_slop_in_either_order():
    p = StampPairer(slop_ns=50 * MS)
    assert p.add_left(1000 * MS, "cloud1") is None
    assert p.add_right(1030 * MS, "det1") == ("cloud1", "det1")
    assert p.add_right(2000 * MS, "det2") is None
    assert p.add_left(1990 * MS, "cloud2") == ("cloud2", "det2")
    assert p.stats.paired == 2 and p.stats.dropped_clouds == 0


def test_no_pair_outside_slop_and_queue_is_bounded():
    p = StampPairer(slop_ns=10 * MS, queue_size=3)
    for i in range(6):
        assert p.add_left(i * 100 * MS, i) is None
    assert p.stats.dropped_clouds == 3
    assert p.add_right(205 * MS, "late") is None  # cloud 2 was dropped: no partner


def test_closest_stamp_wins_and_older_are_dropped():
    p = StampPairer(slop_ns=50 * MS)
    p.add_left(100 * MS, "a")
    p.add_left(140 * MS, "b")
    assert p.add_right(145 * MS, "d") == ("b", "d")
    assert p.stats.dropped_clouds == 1  # "a" is older than the matched cloud


def test_latest_slot_newest_wins_and_counts_drops():
    slot = LatestSlot()
    slot.put(1)
    slot.put(2)
    slot.put(3)
    assert slot.take(timeout=0) == 3
    assert slot.stats.dropped_pairs == 2
    assert slot.take(timeout=0.01) is None


def test_latest_slot_wakes_a_waiting_worker():
    slot = LatestSlot()
    got = []
    worker = threading.Thread(target=lambda: got.append(slot.take(timeout=5)))
    worker.start()
    slot.put("frame")
    worker.join(timeout=5)
    assert got == ["frame"]
