"""Photometric consistency: whether the two views agree on the brightness of what they matched.

A road surface scatters light alike towards both cameras, so the pixels the matcher pairs show
the same brightness up to the cameras' gain. A glossy lane marking, a wet patch or a saturated
stripe does not: its brightness depends on the view (a highlight moves between the cameras,
one camera clips where the other does not), the census words match its edges and smudges
rather than a surface, and the disparities read as depressions. Such a region is measured by
its disagreement against the road's own, in the same frame.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from ..backend import Backend
from . import box_cpu
from .matching import matched_columns

# side (px) of the square over which each view's brightness is averaged before comparing
BRIGHTNESS_WINDOW_PX = 5
# the gain is taken again, GAIN_ROUNDS times, over the pixels that disagree by at most
# GAIN_TRIM times the mean disagreement of those kept before, so that a highlight does not
# bias it
GAIN_TRIM = 3.0
GAIN_ROUNDS = 3
# kernels/photometric.cu: the sums of a pass (left, right, disagreement, count), the most
# blocks and the threads of the rounds' launch (at most _SUM_BLOCKS_PER_MULTIPROCESSOR blocks a
# multiprocessor), and the pixels whose loads a thread keeps in flight
_SUMS = 4
_SUM_BLOCKS = 512
_SUM_BLOCKS_PER_MULTIPROCESSOR = 4
_THREADS = 256
_SUM_BATCH = 4
_DEFINES = {"WINDOW": BRIGHTNESS_WINDOW_PX, "SUMS": _SUMS, "BATCH": _SUM_BATCH,
            "THREADS": _THREADS, "BLOCKS_PER_MULTIPROCESSOR": _SUM_BLOCKS_PER_MULTIPROCESSOR,
            "ROUNDS": GAIN_ROUNDS}


def disagreement(backend: Backend, left: Any, right: Any, disparity: Any) -> Any:
    """Per left pixel, how far (grey levels) the brightness of its BRIGHTNESS_WINDOW_PX square
    lies from that of the right image's square it was matched to, after the gain between the
    views (the ratio of their summed brightness over the matched pixels, taken again over
    those that agree, GAIN_ROUNDS): float32 HxW, NaN where the disparity is. ``left``,
    ``right``: uint8 HxW on the backend; ``disparity``: float32 HxW px, NaN invalid. Nothing
    read back. On the GPU a kernel for the means and one for the rounds and the result
    (kernels/photometric.cu); on the CPU the means by stages/box_cpu.py and the rounds by
    Numba passes whose sums are NumPy's (:func:`host_sum`)."""
    if backend.is_gpu:
        return _disagreement_gpu(backend, left, right, disparity)
    left_mean = box_cpu.box_mean(left, BRIGHTNESS_WINDOW_PX, "nearest")
    right_mean = box_cpu.gather_columns(box_cpu.box_mean(right, BRIGHTNESS_WINDOW_PX, "nearest"),
                                        matched_columns(np, disparity))
    valid = np.isfinite(disparity).ravel()
    left_flat, right_flat = left_mean.ravel(), right_mean.ravel()
    agreeing = valid.copy()
    masked = (np.empty_like(left_flat), np.empty_like(left_flat))
    difference = np.empty_like(left_flat)
    buffer = np.getbufsize()
    for _ in range(GAIN_ROUNDS):
        gain = _host_gain(left_flat, right_flat, agreeing, masked, buffer)
        _differences(left_flat, right_flat, gain, agreeing, difference, masked[0])
        typical = host_sum(masked[0], buffer) / max(int(np.count_nonzero(agreeing)), 1)
        _agreeing(valid, difference, GAIN_TRIM * typical, agreeing)
    gain = _host_gain(left_flat, right_flat, agreeing, masked, buffer)
    _differences(left_flat, right_flat, gain, valid, difference, masked[0])
    return np.where(valid, difference, np.float32(np.nan)).reshape(disparity.shape)


def _disagreement_gpu(backend: Backend, left: Any, right: Any, disparity: Any) -> Any:
    """:func:`disagreement` by kernels/photometric.cu: a kernel for the means, then one
    cooperative launch for every pass of the gain (each block adds the passes' partial sums
    up in the same fixed order) and the result."""
    xp = backend.xp
    height, width = disparity.shape
    left_mean = xp.empty((height, width), dtype=xp.float32)
    right_mean = xp.empty((height, width), dtype=xp.float32)
    backend.kernel("photometric.cu", "photometric_means", _DEFINES)(
        (-(-width // 32), -(-height // 8)), (32, 8),
        (xp.ascontiguousarray(left, dtype=xp.uint8), xp.ascontiguousarray(right, dtype=xp.uint8),
         xp.ascontiguousarray(disparity, dtype=xp.float32), np.int32(height), np.int32(width),
         left_mean, right_mean))
    size = np.int64(height * width)
    blocks = min(_SUM_BLOCKS, _SUM_BLOCKS_PER_MULTIPROCESSOR * backend.multiprocessors())
    out = xp.empty((height, width), dtype=xp.float32)
    backend.kernel("photometric.cu", "photometric_rounds", _DEFINES, cooperative=True)(
        (blocks,), (_THREADS,),
        (left_mean, right_mean, size, np.float64(GAIN_TRIM),
         xp.empty((2, blocks, _SUMS), dtype=xp.float64), xp.zeros(1, dtype=xp.uint32), out))
    return out


def _host_gain(left: np.ndarray, right: np.ndarray, where: np.ndarray,
               masked: tuple[np.ndarray, np.ndarray], buffer: int) -> np.float32:
    """The ratio of the summed brightness of the two views (float32 (N,)) over ``where``
    (bool (N,)), through the scratch ``masked``, as float32."""
    _masked(left, right, where, masked[0], masked[1])
    return np.float32(host_sum(masked[0], buffer) / max(host_sum(masked[1], buffer), 1.0))


@numba.njit(cache=True)
def _pairwise(values: np.ndarray, start: int, count: int) -> float:
    """NumPy's pairwise float64 sum of ``values[start:start + count]`` (float32): eight
    accumulators over blocks of up to 128, halves (a multiple of 8) above."""
    if count < 8:
        total = 0.0
        for i in range(count):
            total += np.float64(values[start + i])
        return total
    if count <= 128:
        lanes = np.empty(8)
        for j in range(8):
            lanes[j] = np.float64(values[start + j])
        i = 8
        while i < count - count % 8:
            for j in range(8):
                lanes[j] += np.float64(values[start + i + j])
            i += 8
        total = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) \
            + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]))
        while i < count:
            total += np.float64(values[start + i])
            i += 1
        return total
    half = count // 2
    half -= half % 8
    return _pairwise(values, start, half) + _pairwise(values, start + half, count - half)


@numba.njit(parallel=True, cache=True)
def host_sum(values: np.ndarray, buffer: int) -> float:
    """np.sum(``values``, dtype=np.float64) of a float32 (N,) array, to the bit: NumPy casts
    ``buffer`` (np.getbufsize()) values at a time and adds each buffer's pairwise sum to the
    total in order; the buffers' sums on Numba's threads."""
    count = values.shape[0]
    buffers = (count + buffer - 1) // buffer
    sums = np.empty(buffers)
    for index in numba.prange(buffers):
        start = index * buffer
        sums[index] = _pairwise(values, start, min(buffer, count - start))
    total = 0.0
    for index in range(buffers):
        total += sums[index]
    return total


@numba.njit(parallel=True, cache=True)
def _masked(left: np.ndarray, right: np.ndarray, where: np.ndarray, left_out: np.ndarray,
            right_out: np.ndarray) -> None:
    for i in numba.prange(left.shape[0]):
        left_out[i] = left[i] if where[i] else np.float32(0.0)
        right_out[i] = right[i] if where[i] else np.float32(0.0)


@numba.njit(parallel=True, cache=True)
def _differences(left: np.ndarray, right: np.ndarray, gain: np.float32, where: np.ndarray,
                 difference: np.ndarray, masked: np.ndarray) -> None:
    for i in numba.prange(left.shape[0]):
        difference[i] = abs(left[i] - gain * right[i])
        masked[i] = difference[i] if where[i] else np.float32(0.0)


@numba.njit(parallel=True, cache=True)
def _agreeing(valid: np.ndarray, difference: np.ndarray, limit: float,
              agreeing: np.ndarray) -> None:
    for i in numba.prange(valid.shape[0]):
        agreeing[i] = valid[i] and difference[i] <= limit


def inconsistent(backend: Backend, means: Any, road: Any, factor: float) -> Any:
    """Bool (n,): the superpixels whose mean disagreement ``means`` (float32 (n,), NaN where
    none is valid) exceeds ``factor`` times the mean over the superpixels of the road (bool
    (n,) ``road``: observed and not selected). Nothing read back; on the GPU one kernel of
    one block (kernels/photometric.cu)."""
    xp = backend.xp
    if backend.is_gpu:
        count = means.shape[0]
        out = xp.empty(count, dtype=xp.bool_)
        backend.kernel("photometric.cu", "photometric_inconsistent", _DEFINES)(
            (1,), (1024,), (xp.ascontiguousarray(means, dtype=xp.float32),
                            xp.ascontiguousarray(road, dtype=xp.bool_), np.int32(count),
                            np.float64(factor), out))
        return out
    finite = xp.isfinite(means)
    weight = (road & finite).astype(xp.float64)
    level = xp.sum(weight * xp.where(finite, means, 0)) / xp.maximum(weight.sum(), 1.0)
    return finite & (means > factor * level)
