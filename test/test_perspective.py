from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.stages import perspective
from pothole_detector.stages.perspective import (SHIFT_FIRST, SHIFT_ONE, add_shifts, band,
                                                 no_shifts, round_up_levels, row_shifts,
                                                 shift_at, shift_range, shifts_table,
                                                 source_columns, transform_right)
from pothole_detector.stages.road_model import RoadModel

CURVED = RoadModel(120.0, 0.25, math.radians(-3.0), (2.0, -4.0, 3.0, 9.0, -2.0, 1.5),
                   kind="quadratic")


def test_row_shifts_move_each_row_right_and_zero_fill():
    image = np.arange(1, 13, dtype=np.uint8).reshape(3, 4)
    shifts = row_shifts(np.array([0, 1, 3]))
    np.testing.assert_array_equal(transform_right(np, image, shifts),
                                  [[1, 2, 3, 4], [0, 5, 6, 7], [0, 0, 0, 9]])
    np.testing.assert_array_equal(shifts[SHIFT_FIRST], [0, 1, 3])
    colour = np.dstack([image, image])
    assert transform_right(np, colour, shifts)[2, 3, 1] == 9


@pytest.mark.parametrize("dtype", [np.uint8, np.uint32])
def test_the_host_kernel_shifts_rows_as_the_gather_does(dtype):
    """An HxW image on the host goes through the Numba kernel; an HxWx1 one through the gather
    of source_columns, the device's form: the same pixels, for row and pixel shifts whose
    lines rise, fall and reach zero within the row."""
    rng = np.random.default_rng(3)
    image = rng.integers(1, np.iinfo(dtype).max, (40, 97), dtype=dtype)
    base = rng.integers(-20 * SHIFT_ONE, 30 * SHIFT_ONE, 40)
    step = rng.integers(-SHIFT_ONE // 2, SHIFT_ONE // 2, 40)
    for shifts in (shifts_table(base, step), row_shifts(rng.integers(0, 99, 40))):
        expected = transform_right(np, image[:, :, None], shifts)[:, :, 0]
        actual = transform_right(np, image, shifts)
        assert actual.dtype == dtype
        np.testing.assert_array_equal(actual, expected)
        assert (actual == 0).any() and (actual != 0).any()


def test_kappa_is_the_floored_line_clipped_at_zero():
    # row 0: 2.5 + 0.25 x; row 1: 1.75 - 0.5 x (reaches 0 at x = 3.5)
    shifts = shifts_table(np.array([5 * SHIFT_ONE // 2, 7 * SHIFT_ONE // 4]),
                          np.array([SHIFT_ONE // 4, -SHIFT_ONE // 2]))
    np.testing.assert_array_equal(shift_at(np, shifts, np.arange(8)[None, :]),
                                  [[2, 2, 3, 3, 3, 3, 4, 4], [1, 1, 0, 0, 0, 0, 0, 0]])
    # a column shows x - kappa: the rising row repeats a right column, the falling one skips
    np.testing.assert_array_equal(source_columns(np, shifts, 8),
                                  [[-2, -1, -1, 0, 1, 2, 2, 3], [-1, 0, 2, 3, 4, 5, 6, 7]])


@pytest.mark.parametrize("seed", range(4))
def test_first_column_is_the_first_that_shows_a_right_pixel(seed):
    rng = np.random.default_rng(seed)
    base = rng.integers(-40 * SHIFT_ONE, 300 * SHIFT_ONE, 200)
    step = rng.integers(-perspective.MAX_STEP, perspective.MAX_STEP + 1, 200)
    shifts = shifts_table(base, step)
    source = source_columns(np, shifts, 1000)
    # x - kappa(x) never falls along a row, so the columns that show a pixel are a suffix
    assert (np.diff(source, axis=1) >= 0).all()
    shown = source >= 0
    first = np.where(shown.any(axis=1), shown.argmax(axis=1), 1000)
    np.testing.assert_array_equal(np.minimum(shifts[SHIFT_FIRST], 1000), first)


def test_steps_of_a_pixel_per_column_are_refused():
    with pytest.raises(ValueError):
        shifts_table(np.zeros(2), np.array([0, SHIFT_ONE]))


def test_row_mode_shifts_are_the_floored_row_minimum_less_the_margin():
    model = RoadModel(30.0, 0.5, math.radians(2.0))
    shifts, _ = band(np, model, 40, 100, 5.0, 16.0, 384, "row")
    expected = np.maximum(np.floor(model.disparity(np, 40, 100, np.float64).min(axis=1) - 5), 0)
    np.testing.assert_array_equal(shift_at(np, shifts, np.arange(100)[None, :]),
                                  np.broadcast_to(expected[:, None], (40, 100)))
    np.testing.assert_array_equal(shifts[SHIFT_FIRST], expected)


@pytest.mark.parametrize("model", [RoadModel(100.0, 0.2, math.radians(3.0)),
                                   RoadModel(100.0, 0.2, math.radians(-4.0)), CURVED])
@pytest.mark.parametrize("mode", ["row", "pixel"])
def test_band_holds_the_road_between_its_margins(model, mode):
    height, width = 200, 400
    shifts, levels = band(np, model, height, width, 40.0, 16.0, 384, mode)
    road = model.disparity(np, height, width, np.float64)
    kappa = shift_at(np, shifts, np.arange(width)[None, :])
    above = road - kappa
    assert levels % 16 == 0
    assert above.min() >= 40.0 - 1e-9  # the margin below the road everywhere
    assert above.max() + 16 <= levels < above.max() + 16 + 17
    assert band(np, model, height, width, 40.0, 16.0, 48, mode)[1] == 48
    assert round_up_levels(1) == 16 and round_up_levels(17) == 32


def test_pixel_shifts_follow_the_roll_so_the_band_is_narrower():
    # 3 degrees of roll over 2000 columns: the road falls 0.2 x 105 = 21 px along a row
    model = RoadModel(150.0, 0.2, math.radians(3.0))
    _, row_levels = band(np, model, 1000, 2000, 40.0, 16.0, 384, "row")
    shifts, pixel_levels = band(np, model, 1000, 2000, 40.0, 16.0, 384, "pixel")
    assert (row_levels, pixel_levels) == (80, 64)
    road = model.disparity(np, 1000, 2000, np.float64)
    kappa = shift_at(np, shifts, np.arange(2000)[None, :])
    assert np.abs(road - kappa - 40.5).max() < 1.0
    assert shift_range(shifts, 2000) == (int(kappa.min()), int(kappa.max()))


def _add_shifts_array_form(d0, shifts):
    """add_shifts as array code (the form of kernels/sgm.cu's sgm_finish, step by step)."""
    column = np.arange(d0.shape[1], dtype=np.float32)[None, :] - d0
    column = np.where(np.isfinite(column), column, np.float32(0))
    left_column = np.floor(column)
    fraction = column - left_column
    left_column = left_column.astype(np.int64)
    lower = shift_at(np, shifts, left_column)
    upper = shift_at(np, shifts, left_column + 1)
    shift = lower.astype(np.float32) + fraction * (upper - lower).astype(np.float32)
    return (d0 + shift).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_add_shifts_gives_the_array_form_s_bits(seed):
    rng = np.random.default_rng(seed)
    height, width = 37, 251
    base = rng.integers(-5 * SHIFT_ONE, 60 * SHIFT_ONE, height)
    step = rng.integers(-SHIFT_ONE // 4, SHIFT_ONE // 4, height)
    shifts = np.stack([np.zeros(height, np.int64), base, step]).astype(np.int32)
    d0 = rng.uniform(-2, 80, (height, width)).astype(np.float32)
    d0[rng.random(d0.shape) < 0.1] = np.nan
    d0[0, :5] = np.float32(3.0)
    expected = _add_shifts_array_form(d0, shifts)
    np.testing.assert_array_equal(add_shifts(d0, shifts), expected)


def test_add_shifts_interpolates_kappa_between_the_columns_beside_the_match():
    shifts = shifts_table(np.array([5 * SHIFT_ONE // 2]), np.array([SHIFT_ONE // 4]))
    # kappa(x) = 2, 2, 3, 3, 3, 3, 4, 4 for x = 0..7
    d0 = np.array([[np.nan, 0.0, 0.0, 1.0, 2.5, 0.25, 0.5, 1.25]], dtype=np.float32)
    d1 = add_shifts(d0, shifts)
    # u - d0 = 1, 2, 2, 1.5 (kappa 2 -> 3: 2.5), 4.75, 5.5 (3 -> 4: 3.5), 5.75 (3.75)
    np.testing.assert_array_equal(d1, np.array(
        [[np.nan, 2.0, 3.0, 4.0, 5.0, 3.25, 4.0, 5.0]], dtype=np.float32))
    assert d1.dtype == np.float32


def test_matching_the_transformed_pair_recovers_disparity():
    """A right image whose true disparity rises along each row (a rolled road): at some level
    the transformed right image shows the left pixel, and add_shifts gives the true disparity.
    (Where the disparity falls along a row, the transformed image skips a right column now and
    then: a pixel whose match lies there is matched one column off.)"""
    rng = np.random.default_rng(3)
    height, width = 6, 300
    right = rng.integers(0, 1 << 30, (height, width), dtype=np.int32)  # no repeated values
    columns = np.arange(width)
    true_d = np.floor(20 + 0.06 * columns[None, :] + 1.3 * np.arange(height)[:, None])
    left = np.take_along_axis(right, columns[None, :] - true_d.astype(int), axis=1)
    model = RoadModel(20.0, math.hypot(1.3, 0.06), math.atan2(-0.06, 1.3))
    shifts, levels = band(np, model, height, width, 2.0, 2.0, 64, "pixel")
    assert levels == 16 and shifts[perspective.SHIFT_STEP].min() > 0
    transformed = transform_right(np, right, shifts)
    for v in range(height):
        for u in (60, 151, 298):
            d0 = [k for k in range(levels) if transformed[v, u - k] == left[v, u]][0]
            d1 = add_shifts(np.full((1, width), d0, np.float32), shifts[:, v:v + 1])[0, u]
            assert d1 == true_d[v, u]


def test_no_shifts_leave_the_pair_as_it_is():
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    np.testing.assert_array_equal(transform_right(np, image, no_shifts(3)), image)
    d0 = np.array([[0.5, 1.25, 2.0, 3.0]] * 3, dtype=np.float32)
    np.testing.assert_array_equal(add_shifts(d0, no_shifts(3)), d0)
