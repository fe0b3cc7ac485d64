"""Disparity transformation (DT): subtract the road so potholes stand out."""

from __future__ import annotations

from typing import Any

from .road_model import RoadModel


def transform_disparity(xp: Any, disparity: Any, model: RoadModel, delta_dt_px: float) -> Any:
    """D2 = D1 - f(u, v) + delta_DT for an HxW float32 map (px, NaN stays NaN).

    On the road D2 is close to ``delta_dt_px``; potholes are lower, bumps higher.
    """
    height, width = disparity.shape
    road = model.disparity(xp, height, width, xp.float32)
    return (disparity - road + xp.float32(delta_dt_px)).astype(xp.float32)
