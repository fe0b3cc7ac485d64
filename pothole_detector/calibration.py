"""Rectified stereo calibration: focal length, baseline, principal point."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

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


def read_camera_info_yaml(path: str | Path) -> dict:
    """A ROS calibration YAML (camera_calibration_parsers format) as a dict with
    ``width``, ``height``, ``K`` (9), ``P`` (12)."""
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
    return {"width": width, "height": height, "K": k, "P": p}


def load_stereo_camera_info(left: str | Path, right: str | Path,
                            ) -> tuple[StereoCalibration, tuple[int, int]]:
    """Calibration and (width, height) from the left and right ROS calibration YAML files."""
    info_l, info_r = read_camera_info_yaml(left), read_camera_info_yaml(right)
    if (info_l["width"], info_l["height"]) != (info_r["width"], info_r["height"]):
        raise CalibrationError("left and right camera info give different image sizes")
    return (StereoCalibration.from_projections(info_l["P"], info_r["P"]),
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
