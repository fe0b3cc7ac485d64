"""Pixel-level refinement of the pothole labels: superpixels decide where potholes are; the
pixels around them that lie below the road join them, so that rims which straddle a
superpixel's edge are not cut off."""

from __future__ import annotations

from typing import Any

from ..backend import Backend

# side (px) of the square over which a pixel's transformed disparity is averaged
SMOOTHING_PX = 5


def refine_labels(backend: Backend, labels: Any, transformed: Any, superpixel_labels: Any,
                  drops: Any, observed: Any, road_level: float, radius_px: int,
                  fraction: float) -> Any:
    """The refinement stage: int32 HxW labels where, besides the pixels of ``labels``, every
    pixel within ``radius_px`` (a square) of pothole k whose superpixel is observed and whose
    transformed disparity, averaged over SMOOTHING_PX x SMOOTHING_PX valid pixels, lies more
    than ``fraction`` x its superpixel's threshold drop below ``road_level`` (delta_DT) is
    labelled k (the largest label where two are that close). ``labels``, ``superpixel_labels``
    int32 HxW; ``transformed`` float32 HxW (NaN invalid); ``drops`` float64 and ``observed``
    bool per superpixel (threshold.observation). ``fraction`` <= 0 returns ``labels``."""
    if fraction <= 0 or radius_px <= 0:
        return labels
    xp, ndimage = backend.xp, backend.ndimage
    valid = xp.isfinite(transformed)
    total = ndimage.uniform_filter(xp.where(valid, transformed, 0).astype(xp.float32),
                                   SMOOTHING_PX, mode="constant")
    share = ndimage.uniform_filter(valid.astype(xp.float32), SMOOTHING_PX, mode="constant")
    below = xp.float32(road_level) - total / xp.maximum(share, xp.float32(1e-6))
    deep = (share > 0) & (below > fraction * xp.take(drops, superpixel_labels)) \
        & xp.take(observed, superpixel_labels)
    near = ndimage.maximum_filter(labels, size=2 * radius_px + 1, mode="constant")
    return xp.where(labels > 0, labels, xp.where(deep, near, 0)).astype(xp.int32)


def radius(region_size_px: int) -> int:
    """How far (px) refinement reaches beyond a pothole's superpixels: half a superpixel."""
    return region_size_px // 2
