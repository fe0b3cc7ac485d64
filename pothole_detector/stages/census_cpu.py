"""The census SGM's CPU kernels, compiled with Numba: matching cost, the eight path costs and
the winner search of stages/census_sgm.py, the same integers as kernels/sgm.cu.

Each kernel runs its rows (or, for the paths that cross rows, the pixels of a row) on Numba's
threads; compiled once and cached beside this file (or in the user's cache folder).
"""

from __future__ import annotations

import numba
import numpy as np

_OUTSIDE = 1 << 20
_MAX_PATH_COST = 1 << 14
_POPCOUNT_16 = np.array([bin(value).count("1") for value in range(1 << 16)], dtype=np.uint8)


@numba.njit(parallel=True, cache=True)
def _cost_volume(census_left: np.ndarray, transformed_right: np.ndarray, first: np.ndarray,
                 levels: int, invalid_cost: int, popcount: np.ndarray) -> np.ndarray:
    """matching_cost's kernel: rows on the threads."""
    height, width = census_left.shape
    cost = np.empty((height, width, levels), dtype=np.uint8)
    for v in numba.prange(height):
        for u in range(width):
            word = census_left[v, u]
            for d in range(levels):
                column = u - d
                if column >= first[v]:
                    other = word ^ transformed_right[v, min(max(column, 0), width - 1)]
                    cost[v, u, d] = popcount[other & 0xFFFF] + popcount[other >> 16]
                else:
                    cost[v, u, d] = invalid_cost
    return cost


@numba.njit(inline="always")
def _step(cost: np.ndarray, v: int, u: int, source: np.ndarray, before: tuple[int, int],
          target: np.ndarray, after: tuple[int, int], least: int, p1: int, p2: int) -> int:
    """One step of a path: target[after] (D,) = cost[v, u] plus the least of source[before]
    at the same level, a level off + P1 and its least + P2, less its ``least``; returns the
    least of target[after]."""
    levels = cost.shape[2]
    last = levels - 1
    jump = least + p2
    value = cost[v, u, 0] + min(min(source[before][0], source[before][1] + p1), jump) - least
    target[after][0] = value
    new_least = value
    for d in range(1, last):
        near = min(source[before][d], min(source[before][d - 1], source[before][d + 1]) + p1)
        value = cost[v, u, d] + min(near, jump) - least
        target[after][d] = value
        new_least = min(new_least, value)
    value = cost[v, u, last] + min(min(source[before][last], source[before][last - 1] + p1),
                                   jump) - least
    target[after][last] = value
    return min(new_least, value)


@numba.njit(inline="always")
def _start(cost: np.ndarray, v: int, u: int, paths: np.ndarray, after: tuple[int, int]) -> int:
    """A path's first pixel: paths[after] (D,) = cost[v, u]; returns its least."""
    least = _MAX_PATH_COST
    for d in range(cost.shape[2]):
        paths[after][d] = cost[v, u, d]
        least = min(least, cost[v, u, d])
    return least


@numba.njit(parallel=True, cache=True)
def _write_row_paths(cost: np.ndarray, total: np.ndarray, p1: int, p2: int) -> None:
    """Writes the sum of the two paths along the rows into ``total``: rows on the threads."""
    height, width, levels = cost.shape
    for v in numba.prange(height):
        paths = np.empty((2, 1, levels), dtype=np.int16)
        for forward in (True, False):
            u = 0 if forward else width - 1
            least = _start(cost, v, u, paths, (0, 0))
            for d in range(levels):
                total[v, u, d] = paths[0, 0, d] + (0 if forward else total[v, u, d])
            for step in range(1, width):
                u += 1 if forward else -1
                new, old = step % 2, 1 - step % 2
                least = _step(cost, v, u, paths, (old, 0), paths, (new, 0), least, p1, p2)
                for d in range(levels):
                    total[v, u, d] = paths[new, 0, d] + (0 if forward else total[v, u, d])


@numba.njit(parallel=True, cache=True)
def _add_crossing_row(cost: np.ndarray, total: np.ndarray, before: np.ndarray,
                      before_least: np.ndarray, after: np.ndarray, after_least: np.ndarray,
                      v: int, starts: bool, p1: int, p2: int) -> None:
    """Row ``v`` of the three paths that come from the row before (dx = -1, 0, 1): each
    pixel's step from pixel u - dx of ``before`` (3xWxD, leasts 3xW) into ``after``, their
    sum added to ``total``; pixels on the threads."""
    width, levels = cost.shape[1], cost.shape[2]
    for u in numba.prange(width):
        for path in range(3):
            previous = u - (path - 1)
            if starts or previous < 0 or previous >= width:
                after_least[path, u] = _start(cost, v, u, after, (path, u))
            else:
                after_least[path, u] = _step(cost, v, u, before, (path, previous), after,
                                             (path, u), before_least[path, previous], p1, p2)
        for d in range(levels):
            total[v, u, d] += after[0, u, d] + after[1, u, d] + after[2, u, d]


@numba.njit(parallel=True, cache=True)
def _select(total: np.ndarray, uniqueness_percent: int, lr_max_diff_px: int) -> np.ndarray:
    """select_disparities' kernel: rows on the threads, each with its right view's winners."""
    height, width, levels = total.shape
    raw = np.empty((height, width), dtype=np.float32)
    for v in numba.prange(height):
        right_best = np.empty(width, dtype=np.int64)
        for x in range(width):
            least, best = _OUTSIDE, 0
            for d in range(min(levels, width - x)):
                if total[v, x + d, d] < least:
                    least, best = np.int64(total[v, x + d, d]), d
            right_best[x] = best
        for u in range(width):
            sums = total[v, u]
            best, least = 0, np.int64(sums[0])
            for d in range(1, levels):
                if sums[d] < least:
                    best, least = d, np.int64(sums[d])
            second = _OUTSIDE
            for d in range(levels):
                if abs(d - best) > 1 and sums[d] < second:
                    second = np.int64(sums[d])
            valid = uniqueness_percent == 0 or second == _OUTSIDE \
                or 100 * least < (100 - uniqueness_percent) * second
            target = u - best
            valid = valid and target >= 0
            if valid and lr_max_diff_px >= 0:
                valid = abs(right_best[target] - best) <= lr_max_diff_px
            if not valid:
                raw[v, u] = -1.0
            elif 0 < best < levels - 1:
                below, above = np.int64(sums[best - 1]), np.int64(sums[best + 1])
                denominator = max(below + above - 2 * least, 1)
                raw[v, u] = np.float32(best) + np.float32(below - above) / (
                    np.float32(2) * np.float32(denominator))
            else:
                raw[v, u] = np.float32(best)
    return raw


def matching_cost(census_left: np.ndarray, transformed_right: np.ndarray, first: np.ndarray,
                  levels: int, invalid_cost: int) -> np.ndarray:
    """uint8 HxWxD Hamming costs of the left census words (uint32 HxW) against column u - d of
    the GPT-transformed right ones; ``invalid_cost`` where u - d < ``first`` (int (H,), each
    row's first column that shows a right pixel)."""
    return _cost_volume(census_left, transformed_right, first.astype(np.int64), levels,
                        invalid_cost, _POPCOUNT_16)


def path_sums(cost: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """uint16 HxWxD sum S of the eight path costs L_r (census_sgm.DIRECTIONS) of the uint8
    HxWxD ``cost``: the two along the rows, then the three from above a row at a time down the
    image, then the three from below up it."""
    height, width, levels = cost.shape
    total = np.empty(cost.shape, dtype=np.uint16)
    _write_row_paths(cost, total, p1, p2)
    before = np.empty((3, width, levels), dtype=np.int16)
    after = np.empty_like(before)
    before_least = np.empty((3, width), dtype=np.int16)
    after_least = np.empty_like(before_least)
    for rows in (range(height), range(height - 1, -1, -1)):
        for index, v in enumerate(rows):
            _add_crossing_row(cost, total, before, before_least, after, after_least, v,
                              index == 0, p1, p2)
            before, after = after, before
            before_least, after_least = after_least, before_least
    return total


def select_disparities(total: np.ndarray, uniqueness_percent: int,
                       lr_max_diff_px: int) -> np.ndarray:
    """float32 HxW winner with its subpixel offset, -1 where invalid (uniqueness, left of the
    image, left-right check), from the uint16 HxWxD path sums."""
    return _select(total, uniqueness_percent, lr_max_diff_px)


def set_threads(count: int) -> None:
    """Run the kernels on at most ``count`` threads (at most the cores Numba found)."""
    numba.set_num_threads(max(1, min(count, numba.config.NUMBA_NUM_THREADS)))
