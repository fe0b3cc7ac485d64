"""Pixel-level refinement of the pothole labels: superpixels decide where potholes are; the
pixels around them that lie below the road join them, so that rims which straddle a
superpixel's edge are not cut off. Works on the disparity averaged over a small square
(:func:`smooth`), which measuring uses too."""

from __future__ import annotations

from typing import Any

from ..backend import Backend

# side (px) of the square over which a pixel's disparity is averaged
SMOOTHING_PX = 5


def smooth(backend: Backend, disparity: Any, fill: bool = False) -> Any:
    """The mean of the valid values of a float32 HxW map (NaN invalid) over the SMOOTHING_PX x
    SMOOTHING_PX square about each pixel (float32 HxW): matching noise averaged out, the depth
    structure of a pothole kept. NaN where the pixel is invalid, or with ``fill`` only where no
    value of its square is valid (an occluded pothole wall takes its neighbours')."""
    xp, ndimage = backend.xp, backend.ndimage
    valid = xp.isfinite(disparity)
    total = ndimage.uniform_filter(xp.where(valid, disparity, 0).astype(xp.float32),
                                   SMOOTHING_PX, mode="constant")
    share = ndimage.uniform_filter(valid.astype(xp.float32), SMOOTHING_PX, mode="constant")
    return xp.where((share > 0) if fill else valid, total / xp.maximum(share, xp.float32(1e-6)),
                    xp.float32(xp.nan)).astype(xp.float32)


def refine_labels(backend: Backend, labels: Any, smoothed_transformed: Any,
                  superpixel_labels: Any, drops: Any, observed: Any, road_level: float,
                  radius_px: int, fraction: float) -> Any:
    """The refinement stage: int32 HxW labels where, besides the pixels of ``labels``, every
    pixel within ``radius_px`` (a square) of pothole k whose superpixel is observed and whose
    smoothed transformed disparity (``smoothed_transformed``: D2 of the :func:`smooth` D1,
    float32 HxW, NaN invalid) lies more than ``fraction`` x its superpixel's threshold drop
    below ``road_level`` (delta_DT) is labelled k (the largest label where two are that close).
    ``labels``, ``superpixel_labels`` int32 HxW; ``drops`` float64 and ``observed`` bool per
    superpixel (threshold.observation). ``fraction`` <= 0 returns ``labels``."""
    if fraction <= 0 or radius_px <= 0:
        return labels
    xp, ndimage = backend.xp, backend.ndimage
    below = xp.float32(road_level) - smoothed_transformed
    deep = (below > fraction * xp.take(drops, superpixel_labels)) \
        & xp.take(observed, superpixel_labels)
    near = ndimage.maximum_filter(labels, size=2 * radius_px + 1, mode="constant")
    return xp.where(labels > 0, labels, xp.where(deep, near, 0)).astype(xp.int32)


def radius(region_size_px: int) -> int:
    """How far (px) refinement reaches beyond a pothole's superpixels: half a superpixel."""
    return region_size_px // 2
