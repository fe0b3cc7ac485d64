"""Stable pothole ids (tracking.py)."""

from __future__ import annotations

import numpy as np

from pothole_detector.stages.measure import Pothole
from pothole_detector.tracking import MAX_ID, StableIds, relabel


def _pothole(label: int, x: float, z: float, area: float = 0.03) -> Pothole:
    return Pothole(label=label, pixels=100, area_m2=area, max_depth_m=0.05, mean_depth_m=0.03,
                   volume_m3=area * 0.03, centroid_cam_m=(x, 0.5, z), bbox_px=(0, 0, 1, 1))


def test_a_pothole_keeps_its_id_while_its_footprint_overlaps_last_frames():
    ids = StableIds()
    assert ids.assign([_pothole(1, 0.0, 2.0), _pothole(2, 1.0, 3.0)]) == [1, 2]
    # the rig moved 5 cm; the potholes come in the other order, and a new one appears
    assert ids.assign([_pothole(1, 1.0, 2.95), _pothole(2, -1.0, 2.0),
                       _pothole(3, 0.0, 1.95)]) == [2, 3, 1]
    # the first one left the view; the others stay; a far one is new
    assert ids.assign([_pothole(1, 0.0, 1.9), _pothole(2, 1.0, 2.9),
                       _pothole(3, 0.0, 6.0)]) == [1, 2, 4]
    ids.reset()
    assert ids.assign([_pothole(1, 0.0, 1.9)]) == [5]
    assert ids.assign([]) == [] and ids.assign([_pothole(1, 0.0, 1.9)]) == [6]


def test_ids_wrap_after_the_label_images_largest():
    ids = StableIds()
    ids._next = MAX_ID
    assert ids.assign([_pothole(1, 0.0, 2.0), _pothole(2, 5.0, 9.0)]) == [MAX_ID, 1]


def test_relabel_renames_labels():
    labels = np.array([[0, 1, 1], [2, 2, 0]], np.int32)
    renamed = relabel(labels, [_pothole(1, 0, 2), _pothole(2, 1, 3)], [7, 3])
    np.testing.assert_array_equal(renamed, [[0, 7, 7], [3, 3, 0]])
    assert renamed.dtype == labels.dtype
