"""camera_info as a calibration: the rectified pair of two CameraInfo, what is refused and why,
when images count as raw, and rectification maps that undo the lens they come from."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pothole_detector.recordings.camera import camera_info_message
from pothole_detector.recordings.messages import header_at
from pothole_detector.calibration import StereoCalibration
from pothole_detector.errors import CalibrationError
from pothole_detector.recordings.camera import (pipeline_inputs, rectifies, rectification,
                                                stereo_camera)
from pothole_detector.evaluation.synthetic import LENS_DISTORTION, raw_camera

HEADER = header_at(0, "cam")
CAL = StereoCalibration(700.0, 0.12, 320.5, 180.25)


def _infos():
    return (camera_info_message(CAL, 640, 360, HEADER),
            camera_info_message(CAL, 640, 360, HEADER, right=True))


def test_rectified_camera_info_round_trip_and_refusals():
    left, right = _infos()
    camera = stereo_camera(left, right, 640, 360)
    assert camera.calibration() == CAL and not camera.needs_rectification()
    assert pipeline_inputs(camera, "auto") == (CAL, None)
    with pytest.raises(CalibrationError, match="for 640x360 images but the images are 320x180"):
        stereo_camera(left, right, 320, 180)
    flat = camera_info_message(CAL, 640, 360, HEADER)
    with pytest.raises(CalibrationError, match="Tx = P.0,3. = 0.*--baseline.*baseline_m"):
        stereo_camera(left, flat, 640, 360).calibration()
    given = stereo_camera(left, flat, 640, 360, baseline_m=0.12)
    assert math.isclose(given.calibration().baseline, 0.12)
    assert any("using baseline 0.12 m" in note for note in given.notes())
    broken = camera_info_message(CAL, 640, 360, HEADER, right=True)
    broken.p[0] = math.nan
    with pytest.raises(CalibrationError, match="P has NaN"):
        stereo_camera(left, broken, 640, 360)
    for index, value, words in ((0, math.nan, "K has NaN"), (4, 0.0, "focal length <= 0"),
                                (2, math.inf, "K has NaN")):
        bad_k = camera_info_message(CAL, 640, 360, HEADER)
        bad_k.k[index] = value
        with pytest.raises(CalibrationError, match=words):
            stereo_camera(bad_k, right, 640, 360)


def test_a_missing_focal_length_comes_from_k_or_the_parameter():
    left, right = _infos()
    for info in (left, right):
        info.p[0] = info.p[5] = 0.0
    # P without a focal length: K's (the right one then has no Tx either)
    camera = stereo_camera(left, right, 640, 360, baseline_m=0.1)
    assert camera.calibration().f == 700.0
    for info in (left, right):
        info.k[:] = 0.0
    with pytest.raises(CalibrationError, match="--focal"):
        stereo_camera(left, right, 640, 360, baseline_m=0.1).calibration()
    camera = stereo_camera(left, right, 640, 360, baseline_m=0.1, focal_px=650.0)
    calibration = camera.calibration()
    assert (calibration.f, calibration.cx, calibration.cy) == (650.0, 319.5, 179.5)
    assert any("using 650 px" in note for note in camera.notes())


@pytest.mark.parametrize("change", ["d", "r", "k"])
def test_what_makes_images_raw(change):
    left, right = _infos()
    if change == "d":
        left.d = [-0.2, 0.05, 0.0, 0.0, 0.0]
    elif change == "r":
        left.r = list(cv2.Rodrigues(np.array([0.0, 0.01, 0.0]))[0].ravel())
    else:
        left.k[0] = left.k[4] = 760.0
    camera = stereo_camera(left, right, 640, 360)
    assert camera.needs_rectification()
    assert rectifies(camera, "auto") and rectifies(camera, "on") and not rectifies(camera, "off")
    calibration, tables = pipeline_inputs(camera, "auto")
    assert calibration == CAL and tables is not None and tables.shape == (360, 640)


@pytest.mark.parametrize("model", sorted(LENS_DISTORTION))
def test_the_maps_undo_the_lens(model):
    """Each rectified pixel's raw position, put back through the lens model (OpenCV's
    undistortion, the generator's direction), lands on that rectified pixel."""
    camera = raw_camera(CAL, 640, 360, model, seed=7)
    tables = rectification(camera)
    map_x, map_y = tables.left_maps
    rows, cols = np.mgrid[20:340:40, 20:620:40]
    raw = np.stack([map_x[rows, cols], map_y[rows, cols]], -1).reshape(-1, 1, 2)
    lens = camera.left
    k, d = np.asarray(lens.k).reshape(3, 3), np.asarray(lens.d)
    r, p = np.asarray(lens.r).reshape(3, 3), np.asarray(lens.p).reshape(3, 4)
    back = (cv2.fisheye.undistortPoints(raw.astype(np.float64), k, d[:4], R=r, P=p)
            if model == "equidistant" else cv2.undistortPoints(raw.astype(np.float64), k, d,
                                                                   R=r, P=p))
    error = np.hypot(back[:, 0, 0] - cols.ravel(), back[:, 0, 1] - rows.ravel())
    assert error.max() < 0.05
    assert rectification(camera) is tables  # built once per calibration


def test_an_unknown_distortion_model_is_refused():
    left, right = _infos()
    left.distortion_model = "kannala_brandt_8"
    left.d = [0.1]
    with pytest.raises(CalibrationError, match="kannala_brandt_8.*not supported"):
        rectification(stereo_camera(left, right, 640, 360))
