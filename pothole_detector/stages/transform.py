"""Disparity transformation (DT): subtract the road so potholes stand out."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from ..backend import Backend
from .road_model import ROAD_DEFINES, RoadModel, device_params


def transform_disparity(backend: Backend, disparity: Any, model: RoadModel | Any,
                        delta_dt_px: float) -> Any:
    """D2 = D1 - f(u, v) + delta_DT for an HxW float32 map (px, NaN stays NaN).

    On the road D2 is close to ``delta_dt_px``; potholes are lower, bumps higher. On the GPU
    one kernel (kernels/transform.cu) with the same arithmetic; there ``model`` may also be
    the device parameters of road_model.fit_on_device.
    """
    xp = backend.xp
    height, width = disparity.shape
    if backend.is_gpu:
        transformed = xp.empty((height, width), dtype=xp.float32)
        _kernel(backend, "transform_disparity")(
            ((width + 31) // 32, (height + 7) // 8), (32, 8),
            (xp.ascontiguousarray(disparity, dtype=xp.float32), transformed, np.int32(height),
             np.int32(width), device_params(backend, model), np.float32(delta_dt_px)))
        return transformed
    return transform_on_host(disparity, model, delta_dt_px)


def transform_on_host(disparity: np.ndarray, model: RoadModel, delta_dt_px: float,
                      box: tuple[slice, slice] = (slice(None), slice(None))) -> np.ndarray:
    """D2 of the host HxW float32 ``disparity`` over its window ``box`` (rows, columns):
    float32, with the road of :func:`road_grid` at those pixels."""
    return (disparity[box] - road_grid(model, *disparity.shape)[box]
            + np.float32(delta_dt_px)).astype(np.float32)


@lru_cache(maxsize=4)
def road_grid(model: RoadModel, height: int, width: int) -> np.ndarray:
    """The road disparity of ``model`` over an HxW grid (float32 px, read-only, on the host),
    kept for the frame's later stages: the transformation of D1 and the refinement's of the
    smoothed map read the same grid."""
    grid = model.disparity(np, height, width, np.float32)
    grid.flags.writeable = False
    return grid


def _kernel(backend: Backend, name: str) -> Any:
    """Kernel ``name`` of kernels/transform.cu with the road parameters' layout."""
    return backend.kernel("transform.cu", name, ROAD_DEFINES)

