from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from pothole_detector.backend import CPU
from pothole_detector.stages.matching import matched_columns
from pothole_detector.stages.photometric import (BRIGHTNESS_WINDOW_PX, GAIN_ROUNDS, GAIN_TRIM,
                                                 disagreement, host_sum, inconsistent)


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


def disagreement_reference(left, right, disparity):
    """The array form of the host's disagreement (scipy's box means, NumPy's sums)."""
    valid = np.isfinite(disparity)
    left_mean = scipy.ndimage.uniform_filter(left.astype(np.float32), BRIGHTNESS_WINDOW_PX,
                                             mode="nearest")
    right_mean = np.take_along_axis(
        scipy.ndimage.uniform_filter(right.astype(np.float32), BRIGHTNESS_WINDOW_PX,
                                     mode="nearest"), matched_columns(np, disparity), axis=1)

    def gain(where):
        return (np.sum(np.where(where, left_mean, 0), dtype=np.float64) / np.maximum(
            np.sum(np.where(where, right_mean, 0), dtype=np.float64), 1.0)).astype(np.float32)

    agreeing = valid
    for _ in range(GAIN_ROUNDS):
        difference = np.abs(left_mean - gain(agreeing) * right_mean)
        typical = np.sum(np.where(agreeing, difference, 0), dtype=np.float64) / np.maximum(
            np.count_nonzero(agreeing), 1)
        agreeing = valid & (difference <= GAIN_TRIM * typical)
    difference = np.abs(left_mean - gain(agreeing) * right_mean)
    return np.where(valid, difference, np.float32(np.nan)).astype(np.float32)


@pytest.mark.parametrize("shape", [(3, 5), (40, 80), (130, 150), (300, 410)])
def test_the_host_rounds_are_the_array_forms(shape):
    rng = np.random.default_rng(shape[1])
    left = rng.integers(0, 256, shape, dtype=np.uint8)
    right = np.clip(left.astype(int) * 0.8 + rng.normal(0, 6, shape), 0, 255).astype(np.uint8)
    right[: shape[0] // 3, : shape[1] // 3] = 255
    disparity = rng.uniform(0, 8, shape).astype(np.float32)
    disparity[rng.random(shape) < 0.2] = np.nan
    np.testing.assert_array_equal(disagreement(CPU, left, right, disparity),
                                  disagreement_reference(left, right, disparity))


def test_the_host_sum_is_numpys_to_the_bit():
    rng = np.random.default_rng(3)
    for count in (0, 5, 100, 8191, 9000, 20000, 100000):
        values = rng.random(count).astype(np.float32)
        if count:
            values[0], values[count // 3] = 3e7, 1.5e7  # rounding shows any other order
        assert host_sum(values, np.getbufsize()) == np.sum(values, dtype=np.float64)
