from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import CPU
from pothole_detector.params import Config
from pothole_detector.stages.matching import Matcher, downsample, to_gray8
from pothole_detector.stages.perspective import no_shifts, row_shifts


def match(backend, left, right, levels, config):
    return Matcher(backend)(left, right, no_shifts(left.shape[0]), levels, config)


@pytest.mark.parametrize("matcher", ["census", "opencv"])
def test_sgm_on_a_rendered_road_is_subpixel_accurate(flat_sample, matcher):
    disparity = match(CPU, flat_sample.left, flat_sample.right, 128,
                      Config({"matcher": matcher}))
    error = np.abs(disparity - flat_sample.disparity)
    assert np.isfinite(disparity[:, 128:]).mean() > 0.8
    assert np.nanmedian(error) < 0.3
    assert np.nanmean(error > 1.0) < 0.02


@pytest.mark.parametrize("matcher", ["census", "opencv"])
def test_invalid_pixels_are_nan_never_zero(flat_sample, matcher):
    disparity = match(CPU, flat_sample.left, flat_sample.right, 128,
                      Config({"matcher": matcher}))
    assert np.isnan(disparity[:, :60]).all()
    assert not (disparity == 0).any()


def test_opencv_left_right_check_can_be_turned_off(flat_sample):
    with_check = match(CPU, flat_sample.left, flat_sample.right, 128,
                       Config({"matcher": "opencv"}))
    without = match(CPU, flat_sample.left, flat_sample.right, 128,
                    Config({"matcher": "opencv", "lr_max_diff_px": -1, "speckle_window_px": 0}))
    assert np.isfinite(without).sum() > np.isfinite(with_check).sum()


@pytest.mark.parametrize("image", [
    np.full((4, 5), 4095, np.uint16),
    np.dstack([np.full((4, 5), 255, np.uint8)] * 3),
    np.dstack([np.full((4, 5), 255, np.uint8)] * 4),
])
def test_to_gray8_accepts_mono16_rgb_rgba(image):
    gray = to_gray8(image)
    assert gray.dtype == np.uint8 and gray.shape == (4, 5) and gray.max() == 255


@pytest.mark.parametrize("channels,dtype", [(0, np.uint8), (0, np.uint16), (3, np.uint8),
                                            (4, np.uint8), (3, np.uint16)])
def test_to_gray8_into_a_given_array_gives_the_same_grey(channels, dtype):
    rng = np.random.default_rng(channels)
    shape = (7, 9, channels) if channels else (7, 9)
    image = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    out = np.full((7, 9), 3, np.uint8)
    assert to_gray8(image, out=out) is out
    np.testing.assert_array_equal(out, to_gray8(image))
    assert len(np.unique(out)) > 10


def test_downsample_averages_blocks():
    image = np.arange(16, dtype=np.uint8).reshape(4, 4) * 10
    np.testing.assert_array_equal(downsample(np, image, 2), [[25, 45], [105, 125]])


def test_census_on_the_cpu_matches_a_rendered_road(flat_sample):
    left = to_gray8(flat_sample.left)[100:164, 200:456]
    right = to_gray8(flat_sample.right)[100:164, 200:456]
    truth = flat_sample.disparity[100:164, 200:456]
    shifts = row_shifts(np.floor(np.nanmin(truth, axis=1) - 8).astype(int))
    disparity = Matcher(CPU)(left, right, shifts, 32, Config({"matcher": "census"}))
    error = np.abs(disparity - truth)
    assert np.isfinite(disparity[:, 80:]).mean() > 0.8
    assert np.nanmedian(error) < 0.3 and np.nanmean(error > 1.0) < 0.03


def test_a_pair_of_the_same_image_is_refused_as_no_stereo_pair(demo_sample):
    from pothole_detector.errors import NoTextureError
    from pothole_detector.stages.matching import check_pair
    check_pair(demo_sample.left, demo_sample.right)
    with pytest.raises(NoTextureError, match="not a stereo pair"):
        check_pair(demo_sample.left, demo_sample.left.copy())
    differs = demo_sample.left.copy()
    differs[5, 7] ^= 1  # equal in every 16th row, not elsewhere
    check_pair(demo_sample.left, differs)
