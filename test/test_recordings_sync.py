from __future__ import annotations

import pytest

from pothole_detector.recordings.sync import StereoSynchronizer

MS = 1_000_000


def test_exact_pairs_identical_stamps_in_either_order():
    sync = StereoSynchronizer(queue_size=5)
    assert sync.add("left", 100, "L1").pairs == []
    assert sync.add("right", 100, "R1").pairs == [(100, "L1", "R1")]
    assert sync.add("right", 200, "R2").pairs == []
    assert sync.add("left", 200, "L2").pairs == [(200, "L2", "R2")]


def test_exact_refuses_jittered_stamps_and_drops_the_unpaired():
    sync = StereoSynchronizer(queue_size=5)
    sync.add("left", 100 * MS, "L1")
    assert sync.add("right", 103 * MS, "R1").pairs == []
    sync.add("left", 200 * MS, "L2")
    outcome = sync.add("right", 200 * MS, "R2")
    assert outcome.pairs == [(200 * MS, "L2", "R2")]
    assert outcome.dropped == 2  # L1 and R1 can never be paired now


def test_approximate_pairs_nearest_within_tolerance():
    sync = StereoSynchronizer(queue_size=5, approximate=True, tolerance_ns=10 * MS)
    sync.add("left", 100 * MS, "L1")
    sync.add("left", 130 * MS, "L2")
    outcome = sync.add("right", 128 * MS, "R1")
    assert outcome.pairs == [(130 * MS, "L2", "R1")]
    assert outcome.dropped == 1
    assert sync.add("right", 160 * MS, "R2").pairs == []
    assert sync.add("left", 175 * MS, "L3").pairs == []  # 15 ms apart: beyond tolerance


def test_queue_size_bounds_waiting_items():
    sync = StereoSynchronizer(queue_size=3)
    dropped = sum(sync.add("left", stamp, stamp).dropped for stamp in range(10))
    assert dropped == 7
    assert sync.add("right", 9, "R").pairs == [(9, 9, "R")]


def test_stamps_going_backwards_reset_and_keep_the_new_item():
    sync = StereoSynchronizer(queue_size=5)
    sync.add("left", 500, "L1")
    sync.add("left", 600, "L2")
    outcome = sync.add("left", 100, "L0")
    assert "backwards" in outcome.backwards
    assert outcome.dropped == 2
    assert sync.add("right", 100, "R0").pairs == [(100, "L0", "R0")]


def test_bad_arguments():
    with pytest.raises(ValueError):
        StereoSynchronizer(queue_size=0)
    with pytest.raises(ValueError):
        StereoSynchronizer().add("middle", 0, None)


def test_waiting_counts_items_per_side():
    sync = StereoSynchronizer(queue_size=5)
    sync.add("left", 1, "L")
    sync.add("left", 2, "L")
    assert (sync.waiting("left"), sync.waiting("right")) == (2, 0)


def test_a_repeated_stamp_is_dropped_counted_and_said_not_paired_twice():
    sync = StereoSynchronizer()
    assert sync.add("left", 100, "L1").pairs == []
    paired = sync.add("right", 100, "R1")
    assert paired.pairs == [(100, "L1", "R1")]
    again = sync.add("left", 100, "L1 again")
    assert again.pairs == [] and again.dropped == 1 and "two left images" in again.duplicate
    assert sync.waiting("left") == 0
    assert sync.add("left", 200, "L2").duplicate is None
