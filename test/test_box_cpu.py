"""stages/box_cpu.py: scipy.ndimage.uniform_filter's means and np.take_along_axis's gather,
known answers on tiny maps and the reference on random ones."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from pothole_detector.stages import box_cpu


def test_a_square_of_ones_in_zeros_spreads_by_a_ninth():
    image = np.zeros((5, 6), np.float32)
    image[2, 2] = 9.0
    out = box_cpu.box_mean(image, 3, "constant")
    np.testing.assert_allclose(out[1:4, 1:4], 1.0, rtol=1e-6)
    assert out[0].sum() == 0 and out[:, 4:].sum() == 0


def test_the_border_pixel_repeats_or_gives_zeros():
    image = np.full((4, 4), 6.0, np.float32)
    np.testing.assert_allclose(box_cpu.box_mean(image, 3, "nearest"), 6.0)
    constant = box_cpu.box_mean(image, 3, "constant")
    assert constant[0, 0] == pytest.approx(6.0 * 4 / 9)
    assert constant[0, 1] == pytest.approx(6.0 * 6 / 9)
    assert constant[1, 1] == pytest.approx(6.0)


@pytest.mark.parametrize("mode", box_cpu.MODES)
@pytest.mark.parametrize("size", (3, 4, 5, 7))
def test_the_means_are_scipys(mode, size):
    rng = np.random.default_rng(size)
    for image in (rng.integers(0, 256, (37, 150)).astype(np.uint8),
                  (rng.normal(20.0, 5.0, (150, 37)) * (rng.random((150, 37)) < 0.8)
                   ).astype(np.float32),
                  rng.random((3, 2)) < 0.5):
        want = scipy.ndimage.uniform_filter(image.astype(np.float32), size, mode=mode)
        np.testing.assert_array_equal(box_cpu.box_mean(image, size, mode), want)


def test_an_unknown_mode_is_refused():
    with pytest.raises(ValueError, match="mode"):
        box_cpu.box_mean(np.zeros((2, 2), np.float32), 3, "reflect")


def test_the_gather_is_take_along_axis():
    rng = np.random.default_rng(3)
    image = rng.random((20, 30)).astype(np.float32)
    columns = rng.integers(0, 30, (20, 30)).astype(np.int32)
    np.testing.assert_array_equal(box_cpu.gather_columns(image, columns),
                                  np.take_along_axis(image, columns, axis=1))


@pytest.mark.parametrize("size", (1, 3, 5, 33))
def test_the_square_maximum_is_scipys(size):
    rng = np.random.default_rng(size)
    depths = rng.normal(0.0, 2.0, (41, 67)).astype(np.float32)
    depths[rng.random(depths.shape) < 0.2] = -np.inf
    cells = (rng.random((23, 9)) < 0.1).astype(np.uint8)
    labels = (rng.integers(1, 4000, (30, 50)) * (rng.random((30, 50)) < 0.05)).astype(np.int32)
    np.testing.assert_array_equal(box_cpu.square_maximum(depths, size),
                                  scipy.ndimage.maximum_filter(depths, size, mode="nearest"))
    np.testing.assert_array_equal(box_cpu.square_maximum(cells, size),
                                  scipy.ndimage.maximum_filter(cells, size, mode="reflect"))
    np.testing.assert_array_equal(
        box_cpu.square_maximum(labels.astype(np.float32), size).astype(np.int32),
        scipy.ndimage.maximum_filter(labels, size, mode="constant"))
