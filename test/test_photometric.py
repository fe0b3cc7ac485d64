from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages.photometric import disagreement, inconsistent


def textured_pair(shift=4, gain=0.9):
    """A random texture the right camera sees ``shift`` px to the left, through a gain."""
    rng = np.random.default_rng(2)
    wide = rng.integers(30, 200, (40, 80 + shift)).astype(np.float64)
    left = wide[:, :80].astype(np.uint8)
    right = np.clip(np.rint(wide[:, shift:] * gain), 0, 255).astype(np.uint8)
    disparity = np.full((40, 80), float(shift), dtype=np.float32)
    disparity[:, :shift] = np.nan
    return left, right, disparity


def test_a_surface_seen_alike_agrees_up_to_the_gain():
    left, right, disparity = textured_pair()
    found = disagreement(CPU, left, right, disparity)
    assert found.dtype == np.float32 and np.isnan(found[:, :4]).all()
    assert np.nanmedian(found[3:-3, 8:-3]) < 1.0


def test_a_highlight_one_camera_sees_disagrees():
    left, right, disparity = textured_pair()
    right[10:30, 30:50] = np.clip(right[10:30, 30:50].astype(int) + 80, 0, 255)
    found = disagreement(CPU, left, right, disparity)
    assert np.nanmedian(found[15:25, 38:42]) > 50  # left columns 34-54 match right 30-50
    assert np.nanmedian(found[3:8, 8:-3]) < 1.5


def test_superpixels_far_above_the_roads_disagreement_are_flagged():
    means = np.array([1.0, 1.2, 0.8, 3.5, 2.9, np.nan], dtype=np.float32)
    road = np.array([True, True, True, False, False, False])
    np.testing.assert_array_equal(inconsistent(CPU, means, road, 3.0),
                                  [False, False, False, True, False, False])
