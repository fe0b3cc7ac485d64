from __future__ import annotations

import math

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages.road_model import RoadModel
from pothole_detector.stages.transform import transform_disparity


def test_road_becomes_delta_dt_and_a_pothole_stays_below():
    model = RoadModel(40.0, 0.25, math.radians(-3.0))
    disparity = model.disparity(np, 60, 90)
    disparity[20:30, 40:50] -= 6.0
    disparity[0, 0] = np.nan
    transformed = transform_disparity(CPU, disparity, model, 32.0)
    assert transformed.dtype == np.float32
    assert np.isnan(transformed[0, 0])
    np.testing.assert_allclose(transformed[40:, :], 32.0, atol=1e-4)
    np.testing.assert_allclose(transformed[20:30, 40:50], 26.0, atol=1e-4)
