"""Generalized perspective transformation (GPT): per-row shifts of the right image."""

from __future__ import annotations

import math
from typing import Any

from .road_model import RoadModel

LEVEL_MULTIPLE = 16


def round_up_levels(levels: float) -> int:
    """Disparity level count rounded up to the matcher's multiple of 16 (at least 16)."""
    return max(LEVEL_MULTIPLE, int(math.ceil(levels / LEVEL_MULTIPLE)) * LEVEL_MULTIPLE)


def band(xp: Any, model: RoadModel, height: int, width: int, margin_below_px: float,
         margin_above_px: float, max_levels: int) -> tuple[Any, int]:
    """GPT row shifts and the narrow band's level count from one evaluation of the road's row
    extremes: kappa(v) = floor(min_u f(u, v) - delta_PT), clipped at 0 (int32 (H,), px), and
    the road's highest disparity above kappa in any row plus the margin, rounded up to a
    multiple of 16 and capped at ``max_levels``."""
    row_min, row_max = model.row_extremes(xp, height, width)
    kappa = xp.maximum(xp.floor(row_min - margin_below_px), 0).astype(xp.int32)
    needed = float((row_max - kappa).max()) + margin_above_px
    return kappa, min(round_up_levels(needed), round_up_levels(max_levels))


def shift_rows(xp: Any, image: Any, kappa: Any) -> Any:
    """Shift every row v of ``image`` (HxW or HxWxC) right by kappa(v) px, zero-filling.

    Matching the left image against the result gives D0 = D1 - kappa(v).
    """
    width = image.shape[1]
    source = xp.arange(width, dtype=xp.int32)[None, :] - kappa[:, None]
    inside = source >= 0
    source = xp.maximum(source, 0)
    if image.ndim == 3:
        shifted = xp.take_along_axis(image, source[:, :, None], axis=1)
        return xp.where(inside[:, :, None], shifted, 0).astype(image.dtype)
    shifted = xp.take_along_axis(image, source, axis=1)
    return xp.where(inside, shifted, 0).astype(image.dtype)
