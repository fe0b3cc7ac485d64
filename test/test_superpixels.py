from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import CPU
from pothole_detector.stages.superpixels import (_block_mean, grid_count, region_size, slic,
                                                 superpixel_grid, superpixel_means, superpixels,
                                                 upsample_labels)

from slic_reference import slic_reference


def disc_image(height=96, width=128):
    v, u = np.mgrid[0:height, 0:width]
    disc = (u - 60) ** 2 + (v - 50) ** 2 < 22 ** 2
    image = np.where(disc, 20.0, 32.0).astype(np.float32)
    image += np.random.default_rng(0).normal(0, 0.3, image.shape).astype(np.float32)
    return image, disc


def test_superpixels_follow_a_disparity_edge():
    image, disc = disc_image()
    labels, n = slic(CPU, image, np.ones(image.shape, bool), 12, 2.0, 8)
    assert labels.shape == image.shape and labels.max() < n
    inside = np.bincount(labels.ravel(), disc.ravel(), minlength=n)
    total = np.bincount(labels.ravel(), minlength=n)
    used = total > 0
    purity = np.maximum(inside[used], total[used] - inside[used]) / total[used]
    assert (purity * total[used]).sum() / total.sum() > 0.97


def test_superpixels_are_compact_on_a_flat_map():
    image = np.full((64, 64), 32.0, np.float32)
    labels, n = slic(CPU, image, np.ones(image.shape, bool), 16, 2.0, 5)
    sizes = np.bincount(labels.ravel(), minlength=n)
    assert n == 16 and sizes.min() > 0.5 * 256 and sizes.max() < 1.5 * 256


@pytest.mark.parametrize("shape", [(1, 50), (37, 53), (5, 3)])
def test_odd_sizes_and_nan(shape):
    image = np.random.default_rng(1).normal(30, 1, shape).astype(np.float32)
    image[0, 0] = np.nan
    found = superpixels(CPU, image, 8, 2.0, 3, downsample=1)
    labels, n = found.labels, found.count
    assert labels.shape == shape and labels.min() >= 0 and labels.max() < n


@pytest.mark.parametrize("shape,step,compactness,iterations",
                         [((61, 97), 8, 2.0, 6), ((120, 200), 10, 0.5, 4),
                          ((33, 40), 16, 10.0, 3), ((13, 7), 8, 2.0, 2)])
def test_the_compiled_iterations_give_the_array_form_s_labels(shape, step, compactness,
                                                              iterations):
    rng = np.random.default_rng(step)
    ramp = np.cumsum(rng.normal(0, 0.3, shape), axis=1)
    image = (32 - 0.1 * ramp + rng.normal(0, 0.5, shape)).astype(np.float32)
    valid = rng.random(shape) < 0.85
    labels, count = slic(CPU, image, valid, step, compactness, iterations)
    expected, expected_count = slic_reference(image, valid, step, compactness, iterations)
    assert count == expected_count and labels.dtype == np.int32
    np.testing.assert_array_equal(labels, expected)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_compiled_means_give_the_bincount_form_s_bits(dtype):
    rng = np.random.default_rng(5)
    values = rng.normal(30, 3, (53, 71)).astype(dtype)
    values[rng.random(values.shape) < 0.2] = np.nan
    labels = rng.integers(0, 40, values.shape).astype(np.int32)
    labels[labels == 7] = 8
    values[labels == 9] = np.nan
    mean, fraction = superpixel_means(CPU, values, labels, 41)
    valid = np.isfinite(values).ravel()
    count = np.bincount(labels.ravel(), minlength=41).astype(np.float64)
    count_valid = np.bincount(labels.ravel(), weights=valid.astype(np.float64), minlength=41)
    total = np.bincount(labels.ravel(), minlength=41,
                        weights=np.where(valid, values.ravel(), 0).astype(np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        expected = np.where(count_valid > 0, total / np.maximum(count_valid, 1), np.nan)
    np.testing.assert_array_equal(mean, expected.astype(np.float32))
    np.testing.assert_array_equal(fraction,
                                  (count_valid / np.maximum(count, 1)).astype(np.float32))
    assert np.isnan(mean[[7, 9, 40]]).all() and fraction[7] == 0 and fraction[9] == 0


def test_downsampled_labels_cover_the_full_image():
    image, disc = disc_image(97, 131)
    found = superpixels(CPU, image, 16, 2.0, 6, downsample=2)
    labels, n = found.labels, found.count
    assert labels.shape == image.shape
    means, valid = superpixel_means(CPU, image, labels, n)
    np.testing.assert_array_equal(means, found.means)
    inside = means[np.unique(labels[40:60, 50:70])]
    assert np.all(inside < 26)


def test_means_ignore_invalid_pixels():
    image = np.array([[1.0, np.nan], [3.0, 5.0]], np.float32)
    labels = np.array([[0, 0], [1, 1]])
    means, valid = superpixel_means(CPU, image, labels, 3)
    np.testing.assert_allclose(means[:2], [1.0, 4.0])
    assert np.isnan(means[2])
    np.testing.assert_allclose(valid, [0.5, 1.0, 0.0])


@pytest.mark.parametrize("shape,region,downsample", [((61, 203), 32, 2), ((40, 41), 8, 1),
                                                     ((1040, 2079), 32, 2), ((33, 17), 5, 3)])
def test_grid_count_is_the_count_superpixel_grid_returns(shape, region, downsample):
    image = np.random.default_rng(0).normal(30, 2, shape).astype(np.float32)
    _, n = superpixel_grid(CPU, image, region, 2.0, 1, downsample)
    assert grid_count(shape, region, downsample) == n


@pytest.mark.parametrize(("given", "width", "axis_sine", "step"), [
    (0, 2079, 1.0, 32), (0, 2079, 0.71, 32), (0, 2079, 0.5, 32), (0, 2079, 0.4, 26),
    (0, 2079, 0.26, 17), (0, 2079, 0.03, 16), (0, 1280, 0.1, 10), (0, 640, 0.1, 8),
    (0, 320, 1.0, 8), (24, 2079, 0.1, 24)])
def test_region_size_shares_the_width_and_shrinks_on_a_grazing_road(given, width, axis_sine,
                                                                    step):
    """width / 64, times the axis's sine over sin(30 deg) below it, at most halved, at least
    8 px; a step that is given stays."""
    assert region_size(given, width, axis_sine) == step


@pytest.mark.parametrize("dtype", (np.int32, np.bool_, np.uint8))
def test_upsampling_on_the_host_is_fancy_indexing(dtype):
    rng = np.random.default_rng(9)
    small = rng.integers(0, 7, (13, 21)).astype(dtype)
    for factor, shape in ((2, (26, 42)), (2, (27, 45)), (3, (38, 60))):
        rows = np.minimum(np.arange(shape[0]) // factor, small.shape[0] - 1)
        cols = np.minimum(np.arange(shape[1]) // factor, small.shape[1] - 1)
        got = upsample_labels(CPU, small, factor, shape)
        assert got.dtype == small.dtype
        np.testing.assert_array_equal(got, small[rows[:, None], cols[None, :]])


def block_mean_reference(image, valid, factor):
    """The array form superpixels._block_mean's kernel replaces."""
    height, width = image.shape[0] // factor, image.shape[1] // factor
    crop = (slice(0, height * factor), slice(0, width * factor))
    values = np.where(valid, image, 0)[crop].reshape(height, factor, width, factor)
    counts = valid[crop].reshape(height, factor, width, factor).sum(axis=(1, 3))
    means = values.sum(axis=(1, 3)) / np.maximum(counts, 1)
    return means.astype(np.float32), counts * 2 >= factor * factor


@pytest.mark.parametrize("factor", (1, 2, 3, 4))
def test_block_means_are_the_array_forms(factor):
    rng = np.random.default_rng(factor)
    image = rng.normal(30.0, 5.0, (61, 83)).astype(np.float32)
    valid = rng.random(image.shape) < 0.7
    means, enough = _block_mean(image, valid, factor)
    want_means, want_enough = block_mean_reference(image, valid, factor)
    np.testing.assert_array_equal(means, want_means)
    np.testing.assert_array_equal(enough, want_enough)
