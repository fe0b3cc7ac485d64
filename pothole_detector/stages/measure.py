"""Per-pothole 3D: points, depth below the road, area on the road, volume, centroid."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..backend import Backend, to_host
from ..calibration import StereoCalibration
from .road_model import RoadModel


@dataclass(frozen=True)
class Pothole:
    """One pothole. Lengths in metres in the left optical frame (x right, y down, z forward);
    ``bbox_px`` is (u0, v0, u1, v1) inclusive."""

    label: int
    pixels: int
    area_m2: float
    max_depth_m: float
    mean_depth_m: float
    volume_m3: float
    centroid_cam_m: tuple[float, float, float]
    bbox_px: tuple[int, int, int, int]

    def as_dict(self) -> dict:
        return {
            "label": self.label, "pixels": self.pixels, "area_m2": self.area_m2,
            "max_depth_m": self.max_depth_m, "mean_depth_m": self.mean_depth_m,
            "volume_m3": self.volume_m3, "centroid_cam_m": list(self.centroid_cam_m),
            "bbox_px": list(self.bbox_px),
        }


def road_normal(model: RoadModel, calibration: StereoCalibration) -> np.ndarray:
    """Unit normal (3,) of the plane of the model's linear part, pointing away from the camera.

    Road disparity alpha + beta u + gamma v = f B / Z is the plane n . P = f B with
    n = (beta f, gamma f, alpha + beta cx + gamma cy)."""
    beta = -model.a1 * math.sin(model.roll_rad)
    gamma = model.a1 * math.cos(model.roll_rad)
    f, cx, cy = calibration.f, calibration.cx, calibration.cy
    normal = np.array([beta * f, gamma * f, model.a0 + beta * cx + gamma * cy])
    return normal / np.linalg.norm(normal)


def depth_below_road(xp: Any, u: Any, v: Any, disparity: Any, model: RoadModel,
                     calibration: StereoCalibration) -> tuple[Any, Any]:
    """Depth below the road (m, positive into the ground, NaN where the disparity is invalid)
    and footprint area on the road (m^2) of pixels at columns ``u``, rows ``v`` (px) with
    ``disparity`` (px); arrays of one shape, float32 results."""
    normal = road_normal(model, calibration)
    f = calibration.f
    u = u.astype(xp.float32)
    v = v.astype(xp.float32)
    incidence = normal[0] * (u - calibration.cx) / f + normal[1] * (v - calibration.cy) / f \
        + normal[2]
    road_z = calibration.fb / model.at(xp, u, v)
    depth = (calibration.fb / disparity - road_z) * incidence
    footprint = road_z * road_z / (f * f * incidence)
    return depth.astype(xp.float32), footprint.astype(xp.float32)


def measure_potholes(backend: Backend, labels: Any, count: int, disparity: Any, model: RoadModel,
                     calibration: StereoCalibration) -> list[Pothole]:
    """Measure potholes 1..count of the int32 HxW ``labels`` using the HxW float32 disparity D1
    (px, NaN invalid). Works on the labelled pixels only; one host readback of a (count, 12)
    table."""
    if count == 0:
        return []
    if backend.is_gpu:
        return _potholes_from_table(_table_gpu(backend, labels, count, disparity, model,
                                               calibration))
    xp, ndimage = backend.xp, backend.ndimage
    rows, cols = xp.nonzero(labels > 0)
    label = labels[rows, cols]
    disparity = disparity[rows, cols]
    depth, footprint = depth_below_road(xp, cols, rows, disparity, model, calibration)
    valid = xp.isfinite(depth)
    index = xp.arange(1, count + 1)
    x, y, z = calibration.back_project(cols, rows, disparity)

    def total(weights: Any) -> Any:
        return xp.bincount(label, weights=weights.astype(xp.float64), minlength=count + 1)[1:]

    valid_area = xp.where(valid, footprint, 0)

    def extreme(function: Any, values: Any) -> Any:
        return xp.asarray(function(values, label, index), dtype=xp.float64).reshape(count)

    table = xp.stack([
        total(xp.ones_like(footprint)), total(footprint), total(valid_area),
        total(xp.where(valid, depth * footprint, 0)),
        extreme(ndimage.maximum, xp.where(valid, depth, -xp.inf)),
        total(xp.where(valid, x * footprint, 0)), total(xp.where(valid, y * footprint, 0)),
        total(xp.where(valid, z * footprint, 0)),
        extreme(ndimage.minimum, cols), extreme(ndimage.minimum, rows),
        extreme(ndimage.maximum, cols), extreme(ndimage.maximum, rows),
    ], axis=1)
    return _potholes_from_table(to_host(table))


def _potholes_from_table(table: np.ndarray) -> list[Pothole]:
    """Potholes from the (count, 12) table: pixels, area, valid area, depth x area, largest
    depth, x, y, z x area, u min, v min, u max, v max."""
    potholes = []
    for label_id, row in enumerate(table, start=1):
        pixels, area, area_valid, depth_area, max_depth = row[:5]
        mean_depth = depth_area / area_valid if area_valid > 0 else float("nan")
        centroid = tuple(float(c / area_valid) if area_valid > 0 else float("nan")
                         for c in row[5:8])
        potholes.append(Pothole(
            label=label_id, pixels=int(pixels), area_m2=float(area),
            max_depth_m=float(max_depth) if np.isfinite(max_depth) else float("nan"),
            mean_depth_m=float(mean_depth), volume_m3=float(mean_depth * area),
            centroid_cam_m=centroid,  # type: ignore[arg-type]
            bbox_px=tuple(int(c) for c in row[8:12]),  # type: ignore[arg-type]
        ))
    return potholes


def _table_gpu(backend: Backend, labels: Any, count: int, disparity: Any, model: RoadModel,
               calibration: StereoCalibration) -> np.ndarray:
    """The (count, 12) table of measure_potholes by one pass of kernels/measure.cu over the
    label image (per-warp sums, atomics per label); one readback."""
    xp = backend.xp
    height, width = labels.shape
    sums_bytes = (count + 1) * 7 * 8
    buffer = xp.empty(sums_bytes + (count + 1) * 5 * 4, dtype=xp.uint8)
    sums = buffer[:sums_bytes].view(xp.float64)
    extremes = buffer[sums_bytes:].view(xp.int32)
    backend.kernel("measure.cu", "measure_reset", {})(
        ((count + 256) // 256,), (256,), (sums, extremes, np.int32(count)))
    normal = road_normal(model, calibration)
    pixels = height * width
    f64 = np.float64
    backend.kernel("measure.cu", "measure_potholes", {})(
        ((pixels + 255) // 256,), (256,),
        (xp.ascontiguousarray(labels, dtype=xp.int32),
         xp.ascontiguousarray(disparity, dtype=xp.float32), np.int32(height), np.int32(width),
         f64(calibration.f), f64(calibration.cx), f64(calibration.cy), f64(calibration.fb),
         *(f64(c) for c in normal), *model.kernel_args(), sums, extremes))
    host = to_host(buffer)
    sums_host = host[:sums_bytes].view(np.float64).reshape(count + 1, 7)[1:]
    extremes_host = host[sums_bytes:].view(np.int32).reshape(count + 1, 5)[1:]
    bits = extremes_host[:, 0]
    largest = np.where(bits >= 0, bits, bits ^ np.int32(0x7FFFFFFF)).view(np.float32)
    return np.column_stack([sums_host[:, :4], largest.astype(np.float64), sums_host[:, 4:7],
                            extremes_host[:, 1:].astype(np.float64)])
