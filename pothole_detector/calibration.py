"""Stereo calibration: the rectified pair (focal length, baseline, principal point) and the
cameras as calibrated (distortion, rectification and projection), with the maps that rectify
their images."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import yaml

from .errors import CalibrationError


@dataclass(frozen=True)
class StereoCalibration:
    """A rectified pair: focal length ``f`` (px), ``baseline`` (m), principal point (px).

    The left optical frame is the reference: x right, y down, z forward.
    """

    f: float
    baseline: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        values = (self.f, self.baseline, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values):
            raise CalibrationError(f"calibration has a non-finite value: {values}")
        if self.f <= 0:
            raise CalibrationError(f"focal length must be positive, got {self.f}")
        if self.baseline <= 0:
            raise CalibrationError(
                f"baseline must be positive, got {self.baseline} m: the right camera's "
                "projection matrix needs Tx = P[0,3] = -fx * baseline < 0"
            )

    @property
    def fb(self) -> float:
        """f * baseline (px m): depth Z = fb / disparity."""
        return self.f * self.baseline

    def back_project(self, u: Any, v: Any, disparity: Any) -> tuple[Any, Any, Any]:
        """x, y, z (m, left optical frame) of pixels at columns ``u``, rows ``v`` (px) with
        ``disparity`` (px); NumPy or CuPy arrays of one shape (or scalars)."""
        z = self.fb / disparity
        return (u - self.cx) * z / self.f, (v - self.cy) * z / self.f, z

    @classmethod
    def from_focal_baseline(
        cls, f: float, baseline: float, width: int, height: int,
        cx: float | None = None, cy: float | None = None,
    ) -> "StereoCalibration":
        """From focal length (px) and baseline (m); cx, cy default to the image centre."""
        return cls(float(f), float(baseline),
                   (width - 1) / 2.0 if cx is None else float(cx),
                   (height - 1) / 2.0 if cy is None else float(cy))

    @classmethod
    def from_projections(
        cls, p_left: Sequence[float], p_right: Sequence[float], tolerance_px: float = 1.0,
    ) -> "StereoCalibration":
        """From the two 3x4 rectified projection matrices (row-major, 12 numbers each)."""
        pl = np.asarray(p_left, dtype=np.float64).reshape(-1)
        pr = np.asarray(p_right, dtype=np.float64).reshape(-1)
        if pl.size != 12 or pr.size != 12:
            raise CalibrationError("projection matrices must have 12 entries (3x4)")
        if not (np.isfinite(pl).all() and np.isfinite(pr).all()):
            raise CalibrationError("projection matrix contains NaN or infinity; recalibrate")
        pl, pr = pl.reshape(3, 4), pr.reshape(3, 4)
        fx = pl[0, 0]
        if fx <= 0:
            raise CalibrationError("left projection matrix has fx <= 0; is the camera calibrated?")
        if abs(pr[0, 0] - fx) > tolerance_px or abs(pr[1, 1] - pl[1, 1]) > tolerance_px \
                or abs(pr[1, 2] - pl[1, 2]) > tolerance_px:
            raise CalibrationError(
                "left and right projection matrices differ in fx, fy or cy: the pair is not "
                "rectified; rectify it (e.g. stereo_image_proc) before detection"
            )
        tx = pr[0, 3] - pl[0, 3]
        if tx == 0:
            raise CalibrationError(
                "right projection matrix has Tx = P[0,3] = 0: the baseline is unknown; "
                "publish the right camera_info with P[0,3] = -fx * baseline"
            )
        return cls(float(fx), float(-tx / fx), float(pl[0, 2]), float(pl[1, 2]))


DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
# K and P's left 3x3 may differ by this much (px) in an image that needs no rectification
_INTRINSICS_TOLERANCE_PX = 0.5


@dataclass(frozen=True)
class CameraModel:
    """One camera as sensor_msgs/CameraInfo describes it: the raw image size (px), the
    distortion model and coefficients D, the intrinsic matrix K (3x3, row-major), the
    rectification rotation R (3x3) and the rectified projection P (3x4). Hashable, so that the
    maps of one calibration are built once."""

    width: int
    height: int
    distortion_model: str
    d: tuple[float, ...]
    k: tuple[float, ...]
    r: tuple[float, ...]
    p: tuple[float, ...]

    @classmethod
    def from_values(cls, width: int, height: int, distortion_model: str, d: Sequence[float],
                    k: Sequence[float], r: Sequence[float], p: Sequence[float]
                    ) -> "CameraModel":
        """From CameraInfo's fields; an all-zero R (unset) is the identity."""
        r = tuple(float(v) for v in r)
        return cls(int(width), int(height), str(distortion_model or "plumb_bob"),
                   tuple(float(v) for v in d), tuple(float(v) for v in k),
                   _IDENTITY if not any(r) else r, tuple(float(v) for v in p))

    def projection(self, focal_px: float = 0.0) -> np.ndarray:
        """The rectified projection P (3x4): the camera's own; K (with no translation) where P
        has no focal length; a pinhole of ``focal_px`` about the image centre where neither has
        one. Raises CalibrationError where none can be had."""
        p = np.asarray(self.p, dtype=np.float64)
        if p.size == 12 and np.isfinite(p).all() and p[0] > 0 and p[5] > 0:
            return p.reshape(3, 4)
        k = np.asarray(self.k, dtype=np.float64)
        if k.size == 9 and np.isfinite(k).all() and k[0] > 0 and k[4] > 0:
            return np.hstack([k.reshape(3, 3), np.zeros((3, 1))])
        if focal_px > 0:
            return np.array([[focal_px, 0.0, (self.width - 1) / 2.0, 0.0],
                             [0.0, focal_px, (self.height - 1) / 2.0, 0.0],
                             [0.0, 0.0, 1.0, 0.0]])
        raise CalibrationError(
            "camera_info has no focal length in K or P; is the camera calibrated? Give it with "
            "--focal (the focal_px parameter)")

    def is_rectified(self) -> bool:
        """Whether its images are already rectified: no distortion, R the identity and K equal
        to P's left 3x3 (within half a pixel)."""
        if any(abs(v) > 0 for v in self.d):
            return False
        if not np.allclose(np.asarray(self.r, dtype=np.float64).reshape(3, 3), np.eye(3),
                           atol=1e-9):
            return False
        k = np.asarray(self.k, dtype=np.float64)
        p = np.asarray(self.p, dtype=np.float64)
        if k.size != 9 or p.size != 12 or not (k[0] > 0 and p[0] > 0):
            return True
        return bool(np.abs(k.reshape(3, 3) - p.reshape(3, 4)[:, :3]).max()
                    <= _INTRINSICS_TOLERANCE_PX)

    def rectification_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Where each pixel of the rectified view (P's frame, the raw size) lies in the raw
        image: map_x, map_y (float32 HxW, px). Plumb_bob and rational_polynomial through
        OpenCV's undistortion model, equidistant through its fisheye model."""
        if self.distortion_model not in DISTORTION_MODELS:
            raise CalibrationError(
                f"camera_info distortion model {self.distortion_model!r} is not supported; "
                f"rectify the images first or calibrate with one of "
                f"{', '.join(DISTORTION_MODELS)}")
        k = np.asarray(self.k, dtype=np.float64).reshape(3, 3)
        if not (np.isfinite(k).all() and k[0, 0] > 0 and k[1, 1] > 0):
            raise CalibrationError("camera_info K has no focal length: the raw images cannot "
                                   "be rectified; is the camera calibrated?")
        r = np.asarray(self.r, dtype=np.float64).reshape(3, 3)
        p = self.projection()
        size = (self.width, self.height)
        d = np.asarray(self.d, dtype=np.float64)
        if self.distortion_model == "equidistant":
            d = np.concatenate([d, np.zeros(4)])[:4]
            map_x, map_y = cv2.fisheye.initUndistortRectifyMap(k, d, r, p, size, cv2.CV_32FC1)
        else:
            map_x, map_y = cv2.initUndistortRectifyMap(k, d, r, p, size, cv2.CV_32FC1)
        return map_x, map_y


@dataclass(frozen=True)
class StereoCamera:
    """A stereo camera as calibrated: its two :class:`CameraModel` and, where the calibration
    lacks them, the baseline (m) and focal length (px) the user gave (0: none given)."""

    left: CameraModel
    right: CameraModel
    baseline_m: float = 0.0
    focal_px: float = 0.0

    def needs_rectification(self) -> bool:
        """Whether either view's images need rectifying (:meth:`CameraModel.is_rectified`)."""
        return not (self.left.is_rectified() and self.right.is_rectified())

    def calibration(self) -> StereoCalibration:
        """The rectified pair of the two projections, the given baseline where the right one
        has no Tx (P[0,3] = 0) and the given focal length where neither K nor P has one."""
        left = self.left.projection(self.focal_px)
        right = self.right.projection(self.focal_px)
        if right[0, 3] == left[0, 3]:
            if self.baseline_m <= 0:
                raise CalibrationError(
                    "right camera_info has Tx = P[0,3] = 0, so the baseline is unknown: give "
                    "it with --baseline (the baseline_m parameter), or publish the right "
                    "camera_info with P[0,3] = -fx * baseline")
            right = right.copy()
            right[0, 3] = left[0, 3] - right[0, 0] * self.baseline_m
        return StereoCalibration.from_projections(left.reshape(-1), right.reshape(-1))

    def notes(self) -> list[str]:
        """What was taken from the user rather than the calibration, one line each."""
        notes = []
        if self.focal_px > 0 and not (self.left.p[0] > 0 or self.left.k[0] > 0):
            notes.append(f"camera_info has no focal length: using {self.focal_px:g} px "
                         "(--focal, focal_px)")
        left_tx = self.left.p[3] if len(self.left.p) == 12 else 0.0
        right_tx = self.right.p[3] if len(self.right.p) == 12 else 0.0
        if self.baseline_m > 0 and right_tx == left_tx:
            notes.append(f"right camera_info has Tx = P[0,3] = 0: using baseline "
                         f"{self.baseline_m:g} m (--baseline, baseline_m)")
        return notes


def read_camera_info_yaml(path: str | Path) -> dict:
    """A ROS calibration YAML (camera_calibration_parsers format) as a dict with
    ``width``, ``height``, ``K`` (9), ``P`` (12), ``model`` (the distortion model), ``D`` and
    ``R`` (9; the identity where absent)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"camera info file {path} does not exist") from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f"camera info file {path} is not valid YAML: {exc}") from None
    if not data:
        raise CalibrationError(f"camera info file {path} is empty: it needs image_width, "
                               "image_height, camera_matrix.data and projection_matrix.data")
    if not isinstance(data, dict):
        raise CalibrationError(f"camera info file {path} is not a ROS calibration mapping")
    try:
        width = int(data["image_width"])
        height = int(data["image_height"])
        k = [float(x) for x in data["camera_matrix"]["data"]]
        p = [float(x) for x in data["projection_matrix"]["data"]]
    except (TypeError, KeyError, ValueError) as exc:
        raise CalibrationError(
            f"camera info file {path} lacks {exc}: it needs image_width, image_height, "
            "camera_matrix.data and projection_matrix.data"
        ) from None
    if len(k) != 9 or len(p) != 12:
        raise CalibrationError(f"camera info file {path}: camera_matrix needs 9 numbers and "
                               "projection_matrix 12")
    try:
        d = [float(x) for x in (data.get("distortion_coefficients") or {}).get("data") or []]
        r = [float(x) for x in (data.get("rectification_matrix") or {}).get("data")
             or _IDENTITY]
    except (TypeError, ValueError, AttributeError) as exc:
        raise CalibrationError(f"camera info file {path}: distortion_coefficients or "
                               f"rectification_matrix is malformed ({exc})") from None
    if len(r) != 9:
        raise CalibrationError(f"camera info file {path}: rectification_matrix needs 9 numbers")
    return {"width": width, "height": height, "K": k, "P": p, "D": d, "R": r,
            "model": str(data.get("distortion_model") or "plumb_bob")}


def load_stereo_camera_info(left: str | Path, right: str | Path, baseline_m: float = 0.0,
                            focal_px: float = 0.0) -> tuple[StereoCamera, tuple[int, int]]:
    """The stereo camera and (width, height) of the left and right ROS calibration YAML files,
    with the baseline (m) and focal length (px) to use where they lack them (0: none)."""
    info_l, info_r = read_camera_info_yaml(left), read_camera_info_yaml(right)
    if (info_l["width"], info_l["height"]) != (info_r["width"], info_r["height"]):
        raise CalibrationError("left and right camera info give different image sizes")
    models = [CameraModel.from_values(info["width"], info["height"], info["model"], info["D"],
                                      info["K"], info["R"], info["P"])
              for info in (info_l, info_r)]
    return (StereoCamera(models[0], models[1], baseline_m, focal_px),
            (info_l["width"], info_l["height"]))


def camera_info_yaml(calibration: StereoCalibration, width: int, height: int,
                     side: str, name: str = "stereo") -> str:
    """A rectified ROS calibration YAML for the ``left`` or ``right`` camera."""
    f, cx, cy = calibration.f, calibration.cx, calibration.cy
    tx = 0.0 if side == "left" else -f * calibration.baseline
    data = {
        "image_width": width, "image_height": height, "camera_name": f"{name}_{side}",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0]},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
        "rectification_matrix": {"rows": 3, "cols": 3,
                                 "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]},
        "projection_matrix": {"rows": 3, "cols": 4,
                              "data": [f, 0.0, cx, tx, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0]},
    }
    return yaml.safe_dump(data, sort_keys=False)
