"""Generalized perspective transformation (GPT): the right image shifted onto the road.

Column x of row v of the transformed right image shows the right image's column
x - kappa(x, v), with the shift

    kappa(x, v) = max(0, floor((base(v) + step(v) x) / 2^16))

a line per row in fixed point (1/65536 px, integer arithmetic: the same on every backend).
With ``gpt_shift: row`` (the paper) ``step`` is 0 and kappa(v) = floor(min_u f(u, v) - delta_PT);
with ``gpt_shift: pixel`` the line follows the road's disparity along the row less delta_PT, so
the road lies delta_PT above kappa everywhere and the band need not hold the road's slope
across a row (the roll). Matching the left image against the transformed right one over
levels [0, L) gives D0; the level d of left pixel u matches transformed column x = u - d, i.e.
the right pixel x - kappa(x, v), so D1 = D0 + kappa(u - D0, v) (kappa interpolated between
columns for subpixel D0). |step| < 2^16, so x - kappa(x, v) never decreases along a row: the
columns that show a right pixel are those from ``first`` (v) on.

The shifts travel as one int32 (3, H) table: rows SHIFT_FIRST (the first column with a right
pixel; the row shift of the matcher's kernels), SHIFT_BASE and SHIFT_STEP.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from .road_model import RoadModel

LEVEL_MULTIPLE = 16
SHIFT_BITS = 16
SHIFT_ONE = 1 << SHIFT_BITS
# Steepest road slope along a row that the shifts follow (px of disparity per px); a steeper
# slope is clipped and the band widens to hold the rest.
MAX_STEP = SHIFT_ONE // 2
SHIFT_FIRST, SHIFT_BASE, SHIFT_STEP = 0, 1, 2


def round_up_levels(levels: float) -> int:
    """Disparity level count rounded up to the matcher's multiple of 16 (at least 16)."""
    return max(LEVEL_MULTIPLE, int(math.ceil(levels / LEVEL_MULTIPLE)) * LEVEL_MULTIPLE)


def shifts_table(base: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The int32 (3, H) shift table of per-row lines ``base`` and ``step`` (int, 1/65536 px and
    1/65536 px per column; |step| < 2^16), with each row's first column that shows a right
    pixel: the least x >= 0 with x >= floor((base + step x) / 2^16)."""
    base = np.asarray(base, dtype=np.int64)
    step = np.asarray(step, dtype=np.int64)
    if np.any(np.abs(step) >= SHIFT_ONE):
        raise ValueError("GPT shift steps must be below one pixel per column (|step| < 2^16): "
                         "clip them to MAX_STEP as band() does")
    first = np.maximum((base - SHIFT_ONE) // (SHIFT_ONE - step) + 1, 0)
    return np.stack([first, base, step]).astype(np.int32)


def row_shifts(kappa: np.ndarray) -> np.ndarray:
    """The shift table of whole-row shifts ``kappa`` (int >= 0, (H,) px): the paper's GPT."""
    return shifts_table(np.asarray(kappa, dtype=np.int64) << SHIFT_BITS,
                        np.zeros(len(kappa), dtype=np.int64))


def no_shifts(height: int) -> np.ndarray:
    """The shift table of an untransformed pair (matching over [0, levels) px)."""
    return np.zeros((3, height), dtype=np.int32)


def shift_at(xp: Any, shifts: Any, columns: Any) -> Any:
    """kappa(x, v) (int64, px) at integer ``columns`` (an array broadcasting against (H, 1))."""
    base = shifts[SHIFT_BASE].astype(xp.int64)[:, None]
    step = shifts[SHIFT_STEP].astype(xp.int64)[:, None]
    return xp.maximum((base + step * columns) >> SHIFT_BITS, 0)


def source_columns(xp: Any, shifts: Any, width: int) -> Any:
    """int64 (H, W): the right image's column that each column x of the transformed right image
    shows, x - kappa(x, v); negative where it shows none (x < first(v))."""
    columns = xp.arange(width, dtype=xp.int64)[None, :]
    return columns - shift_at(xp, shifts, columns)


def transform_right(xp: Any, image: Any, shifts: Any) -> Any:
    """The transformed right image (HxW or HxWxC, same dtype): column x of row v shows
    column x - kappa(x, v), zero where that lies left of the image. An HxW image on the host
    goes through a Numba kernel, rows on its threads."""
    if xp is np and image.ndim == 2:
        table = np.asarray(shifts).astype(np.int64)
        return _transform_rows(np.ascontiguousarray(image), table[SHIFT_BASE],
                               table[SHIFT_STEP])
    source = source_columns(xp, shifts, image.shape[1])
    inside = source >= 0
    source = xp.maximum(source, 0)
    if image.ndim == 3:
        shifted = xp.take_along_axis(image, source[:, :, None], axis=1)
        return xp.where(inside[:, :, None], shifted, 0).astype(image.dtype)
    shifted = xp.take_along_axis(image, source, axis=1)
    return xp.where(inside, shifted, 0).astype(image.dtype)


@numba.njit(inline="always")
def _kappa(base: int, step: int, column: int) -> int:
    """shift_at in the host kernels: kappa (px) at an integer ``column`` of a row's line."""
    return max((base + step * column) >> SHIFT_BITS, 0)


@numba.njit(parallel=True, cache=True)
def _transform_rows(image: np.ndarray, base: np.ndarray, step: np.ndarray) -> np.ndarray:
    """transform_right's kernel for an HxW image on the host."""
    height, width = image.shape
    out = np.empty_like(image)
    for v in numba.prange(height):
        for x in range(width):
            source = x - _kappa(base[v], step[v], x)
            out[v, x] = image[v, source] if source >= 0 else 0
    return out


def add_shifts(d0: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """D1 = D0 + kappa(u - D0, v) (float32 HxW px) from level-space D0 (float32 HxW px, host;
    NaN stays NaN, values below 0, the invalid ones, come out meaningless): kappa interpolated
    linearly between the columns beside u - D0. float32 throughout, in the order the GPU's
    sgm_finish uses, so both give the same bits (the product t (k1 - k0) is exact: k1 - k0 is
    -1, 0 or 1). A Numba kernel, rows on its threads."""
    shifts = np.ascontiguousarray(shifts, dtype=np.int32)
    return _add_shifts(np.ascontiguousarray(d0, dtype=np.float32),
                       shifts[SHIFT_BASE].astype(np.int64), shifts[SHIFT_STEP].astype(np.int64))


@numba.njit(parallel=True, cache=True)
def _add_shifts(d0: np.ndarray, base: np.ndarray, step: np.ndarray) -> np.ndarray:
    """add_shifts' kernel."""
    height, width = d0.shape
    out = np.empty((height, width), dtype=np.float32)
    for v in numba.prange(height):
        for u in range(width):
            column = np.float32(u) - d0[v, u]
            if not np.isfinite(column):
                column = np.float32(0.0)
            left = np.floor(column)
            fraction = column - left
            left_column = np.int64(left)
            lower = _kappa(base[v], step[v], left_column)
            upper = _kappa(base[v], step[v], left_column + 1)
            shift = np.float32(lower) + fraction * np.float32(upper - lower)
            out[v, u] = d0[v, u] + shift
    return out


def shift_range(shifts: np.ndarray, width: int) -> tuple[int, int]:
    """Least and greatest kappa (px) over an image of ``width`` columns (kappa is monotonic
    along a row, so the ends hold them)."""
    ends = shift_at(np, shifts, np.array([0, width - 1]))
    return int(ends.min()), int(ends.max())


def band(xp: Any, model: RoadModel, height: int, width: int, margin_below_px: float,
         margin_above_px: float, max_levels: int, mode: str = "pixel") -> tuple[Any, int]:
    """GPT shifts (int32 (3, H), see the module's docstring) and the band's level count.

    ``mode`` row: kappa(v) = floor(min_u f(u, v) - delta_PT) clipped at 0, the paper's row
    shifts. pixel: per row the line through the road's disparity at the row's two ends,
    lowered until it lies delta_PT below the road at every sampled column
    (RoadModel.row_samples; a curved road bulges below the chord); kappa clipped at 0. Levels:
    the road's greatest disparity above kappa over the image plus the margin above, rounded up
    to a multiple of 16 and capped at
    ``max_levels``. ``xp`` must be NumPy (a host table; upload it)."""
    if mode == "row":
        row_min, row_max = model.row_extremes(np, height, width)
        base = np.floor((row_min - margin_below_px) * SHIFT_ONE).astype(np.int64)
        shifts = shifts_table(base, np.zeros(height, dtype=np.int64))
        needed = float((row_max - np.maximum(base >> SHIFT_BITS, 0)).max())
    else:
        columns, values = model.row_samples(height, width)
        slope = (values[:, -1] - values[:, 0]) / max(columns[-1], 1.0)
        step = np.clip(np.rint(slope * SHIFT_ONE), -MAX_STEP, MAX_STEP).astype(np.int64)
        gaps = values - (step / SHIFT_ONE)[:, None] * columns[None, :]
        lowest, highest = gaps.min(axis=1), gaps.max(axis=1)
        base = np.floor((lowest - margin_below_px) * SHIFT_ONE).astype(np.int64)
        shifts = shifts_table(base, step)
        # kappa >= floor((base + step x) / 2^16) > (base + step x) / 2^16 - 1
        needed = float((highest - base / SHIFT_ONE).max()) + 1.0
    levels = min(round_up_levels(needed + margin_above_px), round_up_levels(max_levels))
    return xp.asarray(shifts), levels

