"""Photometric consistency: whether the two views agree on the brightness of what they matched.

A road surface scatters light alike towards both cameras, so the pixels the matcher pairs show
the same brightness up to the cameras' gain. A glossy lane marking, a wet patch or a saturated
stripe does not: its brightness depends on the view (a highlight moves between the cameras,
one camera clips where the other does not), the census words match its edges and smudges
rather than a surface, and the disparities read as depressions. Such a region is measured by
its disagreement against the road's own, in the same frame.
"""

from __future__ import annotations

from functools import partial
from typing import Any

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
# kernels/photometric.cu: the sums of a pass (left, right, disagreement, count), the blocks
# and threads of a pass, and the layout of the device state between the passes
_SUMS = 4
_SUM_BLOCKS = 512
_THREADS = 256
_STATE = {"STATE_GAIN": 0, "STATE_GAIN_BEFORE": 1, "STATE_LIMIT": 2}
_DEFINES = {"WINDOW": BRIGHTNESS_WINDOW_PX, "SUMS": _SUMS, **_STATE}
_GAIN, _SPREAD = 0, 1


def disagreement(backend: Backend, left: Any, right: Any, disparity: Any) -> Any:
    """Per left pixel, how far (grey levels) the brightness of its BRIGHTNESS_WINDOW_PX square
    lies from that of the right image's square it was matched to, after the gain between the
    views (the ratio of their summed brightness over the matched pixels, taken again over
    those that agree, GAIN_ROUNDS): float32 HxW, NaN where the disparity is. ``left``,
    ``right``: uint8 HxW on the backend; ``disparity``: float32 HxW px, NaN invalid. Nothing
    read back. On the GPU a kernel for the means, two passes a round and one for the result
    (kernels/photometric.cu); on the CPU the means by stages/box_cpu.py."""
    if backend.is_gpu:
        return _disagreement_gpu(backend, left, right, disparity)
    xp = backend.xp
    valid = xp.isfinite(disparity)
    left_mean = box_cpu.box_mean(left, BRIGHTNESS_WINDOW_PX, "nearest")
    right_mean = box_cpu.gather_columns(box_cpu.box_mean(right, BRIGHTNESS_WINDOW_PX, "nearest"),
                                        matched_columns(xp, disparity))
    agreeing = valid
    for _ in range(GAIN_ROUNDS):
        difference = xp.abs(left_mean - _gain(xp, left_mean, right_mean, agreeing) * right_mean)
        typical = xp.sum(xp.where(agreeing, difference, 0), dtype=xp.float64) / xp.maximum(
            xp.count_nonzero(agreeing), 1)
        agreeing = valid & (difference <= GAIN_TRIM * typical)
    difference = xp.abs(left_mean - _gain(xp, left_mean, right_mean, agreeing) * right_mean)
    return xp.where(valid, difference, xp.float32(np.nan)).astype(xp.float32)


def _disagreement_gpu(backend: Backend, left: Any, right: Any, disparity: Any) -> Any:
    """:func:`disagreement` by kernels/photometric.cu: the means, one kernel a pass (the
    last of its blocks adds the partial sums up in a fixed order and sets the next pass's
    gain or limit) and the result."""
    xp = backend.xp
    height, width = disparity.shape
    left_mean = xp.empty((height, width), dtype=xp.float32)
    right_mean = xp.empty((height, width), dtype=xp.float32)
    kernel = partial(backend.kernel, "photometric.cu", defines=_DEFINES)
    kernel(name="photometric_means")(
        (-(-width // 32), -(-height // 8)), (32, 8),
        (xp.ascontiguousarray(left, dtype=xp.uint8), xp.ascontiguousarray(right, dtype=xp.uint8),
         xp.ascontiguousarray(disparity, dtype=xp.float32), np.int32(height), np.int32(width),
         left_mean, right_mean))
    size = np.int64(height * width)
    state = xp.full(len(_STATE), -1.0, dtype=xp.float64)  # a negative limit: all agree
    partials = xp.empty((_SUM_BLOCKS, _SUMS), dtype=xp.float64)
    arrivals = xp.zeros(1, dtype=xp.uint32)
    for mode in (_GAIN, _SPREAD) * GAIN_ROUNDS + (_GAIN,):
        kernel(name="photometric_sums")(
            (_SUM_BLOCKS,), (_THREADS,),
            (left_mean, right_mean, size, np.int32(mode), np.float64(GAIN_TRIM), state,
             partials, arrivals))
    out = xp.empty((height, width), dtype=xp.float32)
    kernel(name="photometric_difference")((-(-int(size) // _THREADS),), (_THREADS,),
                                          (left_mean, right_mean, size, state, out))
    return out


def _gain(xp: Any, left_mean: Any, right_mean: Any, where: Any) -> Any:
    """The ratio of the summed brightness of the two views over ``where`` (a float32 backend
    scalar)."""
    return (xp.sum(xp.where(where, left_mean, 0), dtype=xp.float64) / xp.maximum(
        xp.sum(xp.where(where, right_mean, 0), dtype=xp.float64), 1.0)).astype(xp.float32)


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
