"""The result as output messages (outputs.py): what needs no ROS."""

import numpy as np

from pothole_detector.ros.outputs import relabel


def test_relabel_renames_labels():
    labels = np.array([[0, 1, 1], [2, 2, 0]], np.int32)
    renamed = relabel(labels, [type("P", (), {"label": 1}), type("P", (), {"label": 2})], [7, 3])
    np.testing.assert_array_equal(renamed, [[0, 7, 7], [3, 3, 0]])
    assert renamed.dtype == labels.dtype
