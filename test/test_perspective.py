from __future__ import annotations

import math

import numpy as np

from pothole_detector.stages.perspective import band, round_up_levels, shift_rows
from pothole_detector.stages.road_model import RoadModel


def test_shift_rows_moves_each_row_right_and_zero_fills():
    image = np.arange(1, 13, dtype=np.uint8).reshape(3, 4)
    kappa = np.array([0, 1, 3], dtype=np.int32)
    np.testing.assert_array_equal(shift_rows(np, image, kappa),
                                  [[1, 2, 3, 4], [0, 5, 6, 7], [0, 0, 0, 9]])
    colour = np.dstack([image, image])
    assert shift_rows(np, colour, kappa)[2, 3, 1] == 9


def test_row_shifts_are_the_floored_row_minimum_less_the_margin():
    model = RoadModel(30.0, 0.5, math.radians(2.0))
    kappa, _ = band(np, model, 40, 100, 5.0, 16.0, 384)
    expected = np.maximum(np.floor(model.disparity(np, 40, 100, np.float64).min(axis=1) - 5), 0)
    np.testing.assert_array_equal(kappa, expected)


def test_band_covers_the_road_and_margins():
    model = RoadModel(100.0, 0.2, math.radians(3.0))
    kappa, levels = band(np, model, 200, 400, 40.0, 16.0, 384)
    road = model.disparity(np, 200, 400, np.float64)
    assert levels % 16 == 0
    assert (road - kappa[:, None]).max() + 16 <= levels < (road - kappa[:, None]).max() + 32
    assert band(np, model, 200, 400, 40.0, 16.0, 48)[1] == 48
    assert round_up_levels(1) == 16 and round_up_levels(17) == 32


def test_matching_the_shifted_pair_recovers_disparity():
    rng = np.random.default_rng(3)
    right = rng.integers(0, 255, (6, 64), dtype=np.uint8)
    true_d = np.array([20, 21, 22, 23, 24, 25])
    left = np.stack([np.roll(row, d) for row, d in zip(right, true_d)])
    kappa = true_d - 2
    shifted = shift_rows(np, right, kappa.astype(np.int32))
    for v in range(6):
        u = 40
        d0 = [k for k in range(8) if shifted[v, u - k] == left[v, u]][0]
        assert d0 + kappa[v] == true_d[v]
