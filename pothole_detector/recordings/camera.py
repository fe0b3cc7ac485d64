"""camera_info as a calibration: the two sensor_msgs/CameraInfo of a stereo set as a
:class:`~pothole_detector.calibration.StereoCamera`, and what the pipeline needs of it (the
rectified pair, and the rectification where the images come raw)."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np

from ..calibration import CameraModel, StereoCalibration, StereoCamera
from ..errors import CalibrationError
from ..params import PARAMETER_BY_NAME
from ..stages.rectify import Rectification
from .messages import message
from .topics import INFO_TYPE

RECTIFY_CHOICES = PARAMETER_BY_NAME["rectify"].choices or ()


def camera_model(info: Any) -> CameraModel:
    """The :class:`CameraModel` of a sensor_msgs/CameraInfo."""
    return CameraModel.from_values(info.width, info.height, info.distortion_model,
                                   list(info.d), list(info.k), list(info.r), list(info.p))


def stereo_camera(left: Any, right: Any, width: int, height: int, baseline_m: float = 0.0,
                  focal_px: float = 0.0) -> StereoCamera:
    """The stereo camera of two CameraInfo for images ``width`` x ``height`` px, with the
    baseline (m) and focal length (px) to use where they lack them (0: none). Raises
    CalibrationError where they disagree with the images or hold NaN or infinity."""
    models = []
    for side, info in (("left", left), ("right", right)):
        if (int(info.width), int(info.height)) not in ((width, height), (0, 0)):
            raise CalibrationError(
                f"{side} camera_info is for {info.width}x{info.height} images but the images "
                f"are {width}x{height}; publish the camera_info of these images")
        for name in ("k", "p", "d", "r"):
            values = np.asarray(getattr(info, name), dtype=np.float64)
            if not np.isfinite(values).all():
                raise CalibrationError(f"{side} camera_info {name.upper()} has NaN or infinity "
                                       f"({list(values)}); is the camera calibrated?")
        k = np.asarray(info.k, dtype=np.float64)
        if k.size != 9 or (k[0] <= 0 or k[4] <= 0) and (k[0] != 0 or k[4] != 0):
            raise CalibrationError(
                f"{side} camera_info K has a focal length <= 0 ({list(k)}); is the camera "
                "calibrated?")
        models.append(dataclasses.replace(camera_model(info), width=width, height=height))
    return StereoCamera(models[0], models[1], float(baseline_m), float(focal_px))


def rectifies(camera: StereoCamera, mode: str) -> bool:
    """Whether images of ``camera`` are rectified before matching under ``mode`` (auto: where
    the calibration says they are not rectified already; on; off)."""
    if mode not in RECTIFY_CHOICES:
        raise CalibrationError(f"rectify must be one of {', '.join(RECTIFY_CHOICES)}")
    return mode == "on" or (mode == "auto" and camera.needs_rectification())


@functools.lru_cache(maxsize=8)
def rectification(camera: StereoCamera) -> Rectification:
    """The remap tables of ``camera``'s two views (built once per calibration)."""
    return Rectification.from_maps(camera.left.rectification_maps(),
                                   camera.right.rectification_maps(),
                                   (camera.left.height, camera.left.width))


def pipeline_inputs(camera: StereoCamera, mode: str
                    ) -> tuple[StereoCalibration, Rectification | None]:
    """The rectified pair's calibration and, where ``mode`` rectifies (:func:`rectifies`),
    the rectification: what a Pipeline is made with."""
    calibration = camera.calibration()
    return calibration, rectification(camera) if rectifies(camera, mode) else None


def camera_info_of(model: CameraModel, header: Any) -> Any:
    """sensor_msgs/CameraInfo of a calibrated camera (its raw images: D, K, R and P)."""
    return message(INFO_TYPE)(header=header, width=model.width, height=model.height,
                              distortion_model=model.distortion_model, d=list(model.d),
                              k=list(model.k), r=list(model.r), p=list(model.p))


def camera_info_message(calibration: StereoCalibration, width: int, height: int,
                        header: Any, right: bool = False) -> Any:
    """sensor_msgs/CameraInfo of one rectified view; the right one carries
    ``P[0,3] = -f * baseline``."""
    f, cx, cy = calibration.f, calibration.cx, calibration.cy
    tx = -f * calibration.baseline if right else 0.0
    return message(INFO_TYPE)(header=header, width=width, height=height,
                              distortion_model="plumb_bob", d=[0.0] * 5,
                              k=[f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
                              r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                              p=[f, 0.0, cx, tx, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
