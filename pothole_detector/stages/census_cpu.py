"""The census SGM's CPU kernels, compiled with Numba: matching cost, the eight path costs and
the winner search of stages/census_sgm.py, the same integers as kernels/sgm.cu.

Each kernel runs its rows (or, for the paths that cross rows, the pixels of a row) on Numba's
threads; compiled once and cached beside this file (or in the user's cache folder).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numba import types
from numba.extending import intrinsic

# A path cost above any real one (31 + P2 <= 127): the sentinel at both ends of a path's levels
# (index 0 and D + 1), so that every level takes the same steps; plus P1 it fits int16.
_FAR = 1 << 14
# Above any sum of the eight path costs (uint16, at most 8 x 127): "none" in the winner search.
_NO_SUM = (1 << 16) - 1


@intrinsic
def _popcount(typingctx: Any, word: Any) -> Any:
    """The number of set bits of an integer (the CPU's population count), as uint8."""
    if not isinstance(word, types.Integer):
        return None

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.trunc(builder.ctpop(args[0]), context.get_value_type(types.uint8))

    return types.uint8(word), codegen


@numba.njit(parallel=True, cache=True)
def census_words(padded: np.ndarray, offsets: np.ndarray, radius_y: int, radius_x: int,
                 height: int, width: int) -> np.ndarray:
    """uint32 height x width census words of the uint8 image ``padded`` by ``radius_y``,
    ``radius_x`` (border repeated): bit k where the pixel ``offsets[k]`` = (dy, dx) ahead is
    brighter than the one as far behind; rows on the threads, a bit at a time along a row."""
    words = np.zeros((height, width), dtype=np.uint32)
    for v in numba.prange(height):
        out = words[v]
        for bit in range(offsets.shape[0]):
            dy, dx = offsets[bit, 0], offsets[bit, 1]
            ahead = padded[radius_y + dy + v, radius_x + dx:radius_x + dx + width]
            behind = padded[radius_y - dy + v, radius_x - dx:radius_x - dx + width]
            shift = np.uint32(bit)
            for u in range(width):
                out[u] |= np.uint32(ahead[u] > behind[u]) << shift
    return words


@numba.njit(parallel=True, cache=True)
def _cost_volume(census_left: np.ndarray, transformed_right: np.ndarray, first: np.ndarray,
                 invalid_cost: int, cost: np.ndarray) -> None:
    """matching_cost's kernel, into ``cost``: rows on the threads. A row's right words are
    reversed first, so that pixel u's levels d = 0, 1, ... read theirs (column u - d, at
    width - 1 - u + d) forward, as vectors."""
    height, width, levels = cost.shape
    for v in numba.prange(height):
        reversed_right = transformed_right[v, ::-1].copy()
        for u in range(width):
            word = census_left[v, u]
            out = cost[v, u]
            inside = min(levels, max(u - first[v] + 1, 0))
            candidates = reversed_right[width - 1 - u:width - 1 - u + inside]
            for d in range(inside):
                out[d] = _popcount(word ^ candidates[d])
            for d in range(inside, levels):
                out[d] = invalid_cost


@numba.njit(inline="always")
def _step(cost: np.ndarray, source: np.ndarray, target: np.ndarray, least: int, p1: int,
          p2: int) -> int:
    """One step of a path: target[1:D+1] = ``cost`` (D,) plus the least of ``source`` at the
    same level, a level off + P1 and ``least`` + P2, less ``least`` (``source`` and
    ``target``: (D + 2,) with _FAR at both ends); returns the least of the new costs. In int16
    throughout (every value fits), so the loop runs on the widest vectors."""
    floor = np.int16(least)
    jump = np.int16(floor + p2)
    new_least = np.int16(_FAR)
    for d in range(cost.shape[0]):
        near = min(source[d + 1], np.int16(min(source[d], source[d + 2]) + p1))
        value = np.int16(np.int16(cost[d]) + min(near, jump) - floor)
        target[d + 1] = value
        new_least = min(new_least, value)
    return new_least


@numba.njit(inline="always")
def _start(cost: np.ndarray, target: np.ndarray) -> int:
    """A path's first pixel: target[1:D+1] = ``cost`` (D,); returns its least."""
    least = _FAR
    for d in range(cost.shape[0]):
        target[d + 1] = cost[d]
        least = min(least, cost[d])
    return least


@numba.njit(parallel=True, cache=True)
def _write_row_paths(cost: np.ndarray, total: np.ndarray, p1: int, p2: int) -> None:
    """Writes the sum of the two paths along the rows into ``total``: rows on the threads."""
    height, width, levels = cost.shape
    penalty1, penalty2 = np.int16(p1), np.int16(p2)
    for v in numba.prange(height):
        paths = np.full((2, levels + 2), _FAR, dtype=np.int16)
        least = _start(cost[v, 0], paths[0])
        for d in range(levels):
            total[v, 0, d] = paths[0, d + 1]
        for u in range(1, width):
            least = _step(cost[v, u], paths[1 - u % 2], paths[u % 2], least, penalty1,
                          penalty2)
            out, path = total[v, u], paths[u % 2]
            for d in range(levels):
                out[d] = path[d + 1]
        least = _start(cost[v, width - 1], paths[0])
        out = total[v, width - 1]
        for d in range(levels):
            out[d] += paths[0, d + 1]
        for step in range(1, width):
            u = width - 1 - step
            least = _step(cost[v, u], paths[1 - step % 2], paths[step % 2], least, penalty1,
                          penalty2)
            out, path = total[v, u], paths[step % 2]
            for d in range(levels):
                out[d] += path[d + 1]


@numba.njit(parallel=True, cache=True)
def _add_crossing_paths(cost: np.ndarray, total: np.ndarray, p1: int, p2: int,
                        down: bool) -> None:
    """Adds the three paths that come from the row before (dx = -1, 0, 1) to ``total``, row
    after row down the image (``down``) or up it: each pixel's step from pixel u - dx of the
    row before; the pixels of a row on the threads."""
    height, width, levels = cost.shape
    penalty1, penalty2 = np.int16(p1), np.int16(p2)
    before = np.full((3, width, levels + 2), _FAR, dtype=np.int16)
    after = np.full((3, width, levels + 2), _FAR, dtype=np.int16)
    before_least = np.empty((3, width), dtype=np.int16)
    after_least = np.empty((3, width), dtype=np.int16)
    for index in range(height):
        v = index if down else height - 1 - index
        for u in numba.prange(width):
            here = cost[v, u]
            for path in range(3):
                previous = u - (path - 1)
                if index == 0 or previous < 0 or previous >= width:
                    after_least[path, u] = _start(here, after[path, u])
                else:
                    after_least[path, u] = _step(here, before[path, previous], after[path, u],
                                                 before_least[path, previous], penalty1,
                                                 penalty2)
            out, first, second, third = total[v, u], after[0, u], after[1, u], after[2, u]
            for d in range(levels):
                out[d] += first[d + 1] + second[d + 1] + third[d + 1]
        before, after = after, before
        before_least, after_least = after_least, before_least


@numba.njit(parallel=True, cache=True)
def _select(total: np.ndarray, uniqueness_percent: int, lr_max_diff_px: int) -> np.ndarray:
    """select_disparities' kernel: rows on the threads. One pass over a row's pixels finds
    each pixel's least sum, winner and uniqueness and, in the same loop over its levels, the
    right view's winners: pixel u's sums at levels d = 0, 1, ... are candidates of right
    pixels u, u - 1, ..., kept mirrored (right pixel x at width - 1 - x) so that each pixel's
    levels meet them in order, as vectors; a second pass, once every right pixel's winner is
    known, makes the left-right check and the subpixel offset. Minima are branch-free uint16
    reductions (sums are at most 8 x 127), a winner the first level at its minimum (the
    lowest d of ties)."""
    height, width, levels = total.shape
    none = np.uint16(_NO_SUM)
    raw = np.empty((height, width), dtype=np.float32)
    for v in numba.prange(height):
        row = total[v]
        mirrored_least = np.full(width, none, dtype=np.uint16)
        mirrored_best = np.zeros(width, dtype=np.uint16)
        winners = np.empty(width, dtype=np.int64)
        leasts = np.empty(width, dtype=np.int64)
        unique = np.empty(width, dtype=np.bool_)
        for u in range(width):
            sums = row[u]
            first = width - 1 - u
            count = min(levels, u + 1)
            right_least = mirrored_least[first:first + count]
            right_best = mirrored_best[first:first + count]
            least = none
            for d in range(count):
                value = sums[d]
                better = value < right_least[d]
                right_best[d] = np.uint16(d) if better else right_best[d]
                right_least[d] = value if better else right_least[d]
                least = min(least, value)
            for d in range(count, levels):
                least = min(least, sums[d])
            first_least = none
            for d in range(levels):
                first_least = min(first_least, np.uint16(d) if sums[d] == least else none)
            best = np.int64(first_least)
            second = none
            for d in range(levels):
                second = min(second, sums[d] if abs(d - best) > 1 else none)
            winners[u], leasts[u] = best, least
            unique[u] = uniqueness_percent == 0 or second == none \
                or 100 * np.int64(least) < (100 - uniqueness_percent) * np.int64(second)
        for u in range(width):
            best = winners[u]
            target = u - best
            valid = unique[u] and target >= 0
            if valid and lr_max_diff_px >= 0:
                valid = abs(np.int64(mirrored_best[width - 1 - target]) - best) <= lr_max_diff_px
            if not valid:
                raw[v, u] = -1.0
            elif 0 < best < levels - 1:
                below, above = np.int64(row[u, best - 1]), np.int64(row[u, best + 1])
                denominator = max(below + above - 2 * leasts[u], 1)
                raw[v, u] = np.float32(best) + np.float32(below - above) / (
                    np.float32(2) * np.float32(denominator))
            else:
                raw[v, u] = np.float32(best)
    return raw


def matching_cost(census_left: np.ndarray, transformed_right: np.ndarray, first: np.ndarray,
                  levels: int, invalid_cost: int, out: np.ndarray | None = None) -> np.ndarray:
    """uint8 HxWxD Hamming costs of the left census words (uint32 HxW) against column u - d of
    the GPT-transformed right ones; ``invalid_cost`` where u - d < ``first`` (int (H,), each
    row's first column that shows a right pixel; below 0 taken as 0). Into ``out`` (uint8
    HxWxD) where given."""
    if out is None:
        out = np.empty((*census_left.shape, levels), dtype=np.uint8)
    _cost_volume(census_left, transformed_right, np.maximum(first, 0).astype(np.int64),
                 invalid_cost, out)
    return out


def path_sums(cost: np.ndarray, p1: int, p2: int, out: np.ndarray | None = None
              ) -> np.ndarray:
    """uint16 HxWxD sum S of the eight path costs L_r (census_sgm.DIRECTIONS) of the uint8
    HxWxD ``cost``: the two along the rows, then the three from above a row at a time down the
    image, then the three from below up it. Into ``out`` (uint16 HxWxD) where given."""
    total = np.empty(cost.shape, dtype=np.uint16) if out is None else out
    _write_row_paths(cost, total, p1, p2)
    _add_crossing_paths(cost, total, p1, p2, True)
    _add_crossing_paths(cost, total, p1, p2, False)
    return total


def select_disparities(total: np.ndarray, uniqueness_percent: int,
                       lr_max_diff_px: int) -> np.ndarray:
    """float32 HxW winner with its subpixel offset, -1 where invalid (uniqueness, left of the
    image, left-right check), from the uint16 HxWxD path sums."""
    return _select(total, uniqueness_percent, lr_max_diff_px)


def set_threads(count: int) -> None:
    """Run the kernels on at most ``count`` threads (at most the cores Numba found)."""
    numba.set_num_threads(max(1, min(count, numba.config.NUMBA_NUM_THREADS)))
