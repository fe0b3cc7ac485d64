"""Threshold by k-means on the 2D histogram of (D2, mean of D2 over the 8 neighbours)."""

from __future__ import annotations

import math
from typing import Any

from ..backend import to_host

# D2 values farther than this from the road level (px) are left out of the histogram.
HISTOGRAM_BELOW_PX = 128.0
HISTOGRAM_ABOVE_PX = 64.0


def neighbour_mean(xp: Any, image: Any) -> Any:
    """Mean of the valid values among each pixel's 8 neighbours (HxW float32; NaN if none)."""
    valid = xp.isfinite(image)
    values = xp.pad(xp.where(valid, image, 0).astype(xp.float32), 1)
    counts = xp.pad(valid.astype(xp.float32), 1)
    height, width = image.shape
    total = xp.zeros((height, width), dtype=xp.float32)
    number = xp.zeros((height, width), dtype=xp.float32)
    for dv in (0, 1, 2):
        for du in (0, 1, 2):
            if dv == 1 and du == 1:
                continue
            total += values[dv:dv + height, du:du + width]
            number += counts[dv:dv + height, du:du + width]
    return xp.where(number > 0, total / xp.maximum(number, 1), xp.nan).astype(xp.float32)


def histogram_threshold(xp: Any, transformed: Any, bin_px: float,
                        road_level: float) -> tuple[float, float]:
    """(t_r, road mean) in px: t_r is the diagonal threshold of the 2D histogram that minimises
    the within-cluster scatter E2 of region 1 (both components below t_r, pothole) and region 2
    (both above, road); the road mean is the mean D2 of region 2 at that t_r.

    Cumulative sums over the histogram make each candidate O(1). ``road_level`` (delta_DT)
    centres the histogram range. Returns (NaN, NaN) when two clusters cannot be formed.
    """
    g1 = transformed
    g2 = neighbour_mean(xp, transformed)
    lo = road_level - HISTOGRAM_BELOW_PX
    n_bins = int(math.ceil((HISTOGRAM_BELOW_PX + HISTOGRAM_ABOVE_PX) / bin_px))
    i1 = xp.floor((g1 - lo) / bin_px)
    i2 = xp.floor((g2 - lo) / bin_px)
    keep = xp.isfinite(i1) & xp.isfinite(i2) & (i1 >= 0) & (i2 >= 0) & (i1 < n_bins) \
        & (i2 < n_bins)
    size = n_bins * n_bins
    # pixels left out (NaN ones too) go to one extra bin past the table, dropped after the
    # count: no masked copy and no sync
    index = xp.where(keep, i1 * n_bins + i2, size).astype(xp.int64).ravel()
    a = g1.astype(xp.float64).ravel()
    b = g2.astype(xp.float64).ravel()

    def table(weights: Any) -> Any:
        hist = xp.bincount(index, weights=weights, minlength=size + 1)[:size]
        return hist.reshape(n_bins, n_bins).cumsum(axis=0).cumsum(axis=1)

    tables = xp.stack([table(None if w is None else w) for w in (None, a, b, a * a + b * b)])
    diagonal = xp.arange(n_bins - 1)
    last = n_bins - 1
    below = tables[:, diagonal, diagonal]
    above = tables[:, last, last][:, None] - tables[:, diagonal, last] \
        - tables[:, last, diagonal] + below
    scatter = xp.full(diagonal.shape, xp.inf)
    ok = (below[0] > 0) & (above[0] > 0)
    n1, n2 = xp.maximum(below[0], 1), xp.maximum(above[0], 1)
    e2 = below[3] + above[3] - (below[1] ** 2 + below[2] ** 2) / n1 \
        - (above[1] ** 2 + above[2] ** 2) / n2
    scatter = xp.where(ok, e2, scatter)
    best = xp.argmin(scatter)
    found, road_mean = to_host(xp.stack([ok[best], above[1][best] / n2[best]]))
    if not found:
        return float("nan"), float("nan")
    return lo + (int(to_host(best)) + 1) * bin_px, float(road_mean)


def select_superpixels(xp: Any, means: Any, valid_fraction: Any, threshold_px: Any,
                       min_valid_fraction: float) -> Any:
    """Bool (n,): superpixels whose mean D2 is below ``threshold_px`` (a scalar or (n,) array
    of t_s values) with more than ``min_valid_fraction`` valid pixels."""
    return xp.isfinite(means) & (means < threshold_px) & (valid_fraction > min_valid_fraction)
