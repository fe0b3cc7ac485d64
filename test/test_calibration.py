from __future__ import annotations

import math

import pytest

from pothole_detector.calibration import (StereoCalibration, camera_info_yaml,
                                          load_stereo_camera_info)
from pothole_detector.errors import CalibrationError

P_LEFT = [700.0, 0, 320.5, 0, 0, 700.0, 240.5, 0, 0, 0, 1, 0]


def right(tx=-700.0 * 0.12, fy=700.0, cy=240.5):
    return [700.0, 0, 320.5, tx, 0, fy, cy, 0, 0, 0, 1, 0]


def test_baseline_from_the_right_projection():
    calibration = StereoCalibration.from_projections(P_LEFT, right())
    assert math.isclose(calibration.baseline, 0.12)
    assert (calibration.f, calibration.cx, calibration.cy) == (700.0, 320.5, 240.5)


@pytest.mark.parametrize("p_right, message", [
    (right(tx=0.0), "Tx"),
    (right(fy=720.0), "not rectified"),
    (right(cy=250.0), "not rectified"),
    (right(tx=float("nan")), "NaN"),
    (right(tx=84.0), "baseline must be positive"),
])
def test_bad_calibrations_are_refused(p_right, message):
    with pytest.raises(CalibrationError, match=message):
        StereoCalibration.from_projections(P_LEFT, p_right)


def test_camera_info_yaml_round_trip(tmp_path):
    calibration = StereoCalibration(650.0, 0.1, 300.0, 200.0)
    for side in ("left", "right"):
        (tmp_path / f"{side}.yaml").write_text(camera_info_yaml(calibration, 640, 400, side))
    camera, size = load_stereo_camera_info(tmp_path / "left.yaml", tmp_path / "right.yaml")
    loaded = camera.calibration()
    assert size == (640, 400) and not camera.needs_rectification()
    assert math.isclose(loaded.baseline, 0.1) and loaded.f == 650.0


def test_default_principal_point_is_the_image_centre():
    calibration = StereoCalibration.from_focal_baseline(500, 0.1, 641, 481)
    assert (calibration.cx, calibration.cy) == (320.0, 240.0)
