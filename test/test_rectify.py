"""stages/rectify.py: the fixed-point bilinear remap with a known answer, pixels outside the
raw image, the unseen mask and the disparities it drops (the GPU's twin: test_gpu.py)."""

from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages import rectify
from pothole_detector.stages.census_sgm import BORDER_X, BORDER_Y


def test_a_sample_between_four_pixels_has_the_fixed_point_answer():
    image = (np.arange(64).reshape(8, 8) * 4 % 256).astype(np.uint8)
    pixel = image.astype(int)
    table = rectify.remap_table(np.full((1, 1), 2.3, np.float32),
                                np.full((1, 1), 3.7, np.float32), (8, 8))
    # 2.3 and 3.7 px round to 74/32 and 118/32: x0 2, fx 10, y0 3, fy 22
    assert table.index[0, 0] == 3 * 8 + 2 and table.fraction[0, 0] == 10 | 22 << 8
    top = 22 * pixel[3, 2] + 10 * pixel[3, 3]
    bottom = 22 * pixel[4, 2] + 10 * pixel[4, 3]
    expected = (10 * top + 22 * bottom + 512) >> 10
    assert rectify.remap(CPU, image, table)[0, 0] == expected == 127


def test_whole_pixels_are_copied_and_the_last_row_and_column_reached():
    image = np.random.default_rng(0).integers(0, 256, (6, 9), dtype=np.uint8)
    rows, cols = np.mgrid[0:6, 0:9].astype(np.float32)
    table = rectify.remap_table(cols, rows, (6, 9))
    np.testing.assert_array_equal(rectify.remap(CPU, image, table), image)


def test_outside_the_raw_image_is_black_and_unseen_with_its_window():
    height, width = 40, 60
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    table = rectify.remap_table(cols - 5.0, rows, (height, width))  # 5 columns off the left
    image = np.full((height, width), 200, np.uint8)
    out = rectify.remap(CPU, image, table)
    assert (out[:, :5] == 0).all() and (out[:, 5:] == 200).all()
    assert table.unseen[:, :5 + BORDER_X].all() and not table.unseen[:, 5 + BORDER_X:].any()
    assert BORDER_Y > 0  # the window reaches rows as well


def test_disparities_of_unseen_pixels_or_partners_are_dropped():
    height, width = 20, 40
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    seen = rectify.remap_table(cols, rows, (height, width))
    blind_left = rectify.remap_table(cols + 30.0, rows, (height, width))  # right part unseen
    tables = rectify.Rectification(seen, blind_left, (cols, rows))
    disparity = np.full((height, width), 4.0, np.float32)
    disparity[0, 0] = np.nan
    out = rectify.invalidate_unseen(CPU, disparity, tables)
    partner_unseen = blind_left.unseen[:, np.clip(np.arange(width) - 4, 0, width - 1)]
    np.testing.assert_array_equal(np.isnan(out), partner_unseen | np.isnan(disparity))
    assert np.isnan(out).any() and not np.isnan(out).all()
