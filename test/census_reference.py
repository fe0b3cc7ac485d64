"""The census SGM written plainly in NumPy: the statement of stages/census_sgm.py's algorithm
that the compiled matchers (stages/census_cpu.py on the CPU, kernels/sgm.cu on the GPU) are
tested against, to the integer. Slow (seconds per megapixel): for tests only."""

from __future__ import annotations

import numpy as np

from pothole_detector.stages import perspective
from pothole_detector.stages.census_sgm import (
    DIRECTIONS, INVALID_COST, census_transform, check_settings, finish)

_OUTSIDE = np.int32(1 << 20)


def matching_cost(census_left: np.ndarray, census_right: np.ndarray, shifts: np.ndarray,
                  levels: int) -> np.ndarray:
    """int32 HxWxD Hamming costs of left (v, u) against column u - d of the right census
    transformed by the GPT ``shifts`` (int32 (3, H), stages/perspective.py)."""
    height, width = census_left.shape
    transformed = perspective.transform_right(np, census_right, shifts)
    column = np.arange(width)[None, :, None] - np.arange(levels)[None, None, :]
    inside = column >= shifts[perspective.SHIFT_FIRST].astype(np.int64)[:, None, None]
    right = transformed[np.arange(height)[:, None, None], np.clip(column, 0, width - 1)]
    cost = np.bitwise_count(census_left[:, :, None] ^ right).astype(np.int32)
    return np.where(inside, cost, np.int32(INVALID_COST))


def _path_step(cost: np.ndarray, previous: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """One step of the path recurrence for N pixels: cost and previous are int32 (N, D)."""
    least = previous.min(axis=1, keepdims=True)
    lower = np.full_like(previous, _OUTSIDE)
    lower[:, 1:] = previous[:, :-1]
    upper = np.full_like(previous, _OUTSIDE)
    upper[:, :-1] = previous[:, 1:]
    best = np.minimum(np.minimum(previous, np.minimum(lower, upper) + p1), least + p2)
    return cost + best - least


def aggregate_path(cost: np.ndarray, dx: int, dy: int, p1: int, p2: int) -> np.ndarray:
    """int32 HxWxD path cost L_r along direction (dx, dy) (NumPy reference)."""
    height, width, _ = cost.shape
    paths = np.empty_like(cost)
    if dy == 0:
        columns = range(width) if dx > 0 else range(width - 1, -1, -1)
        for index, u in enumerate(columns):
            paths[:, u] = cost[:, u] if index == 0 else \
                _path_step(cost[:, u], paths[:, u - dx], p1, p2)
        return paths
    rows = range(height) if dy > 0 else range(height - 1, -1, -1)
    for index, v in enumerate(rows):
        if index == 0:
            paths[v] = cost[v]
            continue
        previous = paths[v - dy]
        if dx == 0:
            paths[v] = _path_step(cost[v], previous, p1, p2)
        elif dx > 0:
            paths[v, 0] = cost[v, 0]
            paths[v, 1:] = _path_step(cost[v, 1:], previous[:-1], p1, p2)
        else:
            paths[v, -1] = cost[v, -1]
            paths[v, :-1] = _path_step(cost[v, :-1], previous[1:], p1, p2)
    return paths


def aggregate(cost: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """uint8 8xHxWxD path costs in the order of DIRECTIONS (NumPy reference)."""
    return np.stack([aggregate_path(cost, dx, dy, p1, p2).astype(np.uint8)
                     for dx, dy in DIRECTIONS])


def select_disparities(paths: np.ndarray, uniqueness_percent: int,
                       lr_max_diff_px: int) -> np.ndarray:
    """float32 HxW winner-take-all disparity with subpixel offset, -1 where invalid
    (uniqueness, left of the image, left-right check), from uint8 8xHxWxD path costs."""
    total = paths.sum(axis=0, dtype=np.int32)
    height, width, levels = total.shape
    best = total.argmin(axis=2)
    least = np.take_along_axis(total, best[..., None], axis=2)[..., 0]
    far = np.abs(np.arange(levels)[None, None, :] - best[..., None]) > 1
    second = np.where(far, total, _OUTSIDE).min(axis=2)
    unique = (uniqueness_percent == 0) | (second == _OUTSIDE) \
        | (100 * least < (100 - uniqueness_percent) * second)
    below = np.take_along_axis(total, np.maximum(best - 1, 0)[..., None], axis=2)[..., 0]
    above = np.take_along_axis(total, np.minimum(best + 1, levels - 1)[..., None], axis=2)[..., 0]
    denominator = np.maximum(below + above - 2 * least, 1)
    offset = (below - above).astype(np.float32) / (np.float32(2) * denominator.astype(np.float32))
    inner = (best > 0) & (best < levels - 1)
    disparity = best.astype(np.float32) + np.where(inner, offset, np.float32(0))
    target = np.arange(width)[None, :] - best
    valid = unique & (target >= 0)
    if lr_max_diff_px >= 0:
        column = np.arange(width)[:, None] + np.arange(levels)[None, :]
        rows = np.arange(height)[:, None, None]
        right_total = np.where(column[None] < width,
                               total[rows, np.minimum(column, width - 1)[None],
                                     np.arange(levels)[None, None, :]], _OUTSIDE)
        right_best = right_total.argmin(axis=2)
        partner = np.take_along_axis(right_best, np.maximum(target, 0), axis=1)
        valid &= np.abs(partner - best) <= lr_max_diff_px
    return np.where(valid, disparity, np.float32(-1)).astype(np.float32)


def reference_disparity(left: np.ndarray, right: np.ndarray, shifts: np.ndarray, levels: int,
                        p1: int, p2: int, uniqueness_percent: int, lr_max_diff_px: int,
                        median: bool) -> np.ndarray:
    """The whole census SGM in NumPy on uint8 HxW images; float32 HxW D1 (px, NaN invalid).
    Slow (seconds per megapixel): for tests and for checking the GPU matcher."""
    check_settings(left.shape, levels, p1, p2)
    census_left = census_transform(left)
    cost = matching_cost(census_left, census_transform(right), shifts, levels)
    raw = select_disparities(aggregate(cost, p1, p2), uniqueness_percent, lr_max_diff_px)
    return finish(raw, shifts, median, census_left, levels)
