"""Pixel-level refinement of the pothole labels: superpixels decide where potholes are; the
pixels around them that lie below the road join them, so that rims which straddle a
superpixel's edge are not cut off, and so does the strip beside a right rim that only the
left camera sees; the pixels of their superpixels that lie on the road leave them. Works on
the disparity averaged over a small square (:func:`smooth`), which measuring uses too."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from ..backend import Backend
from . import box_cpu
from .road_model import ROAD_DEFINES, RoadModel, device_params
from .transform import transform_on_host

# side (px) of the square over which a pixel's disparity is averaged
SMOOTHING_PX = 7
# how far inside (px) a pixel finds the depth it must reach half of to belong to a pothole:
# short of the SMOOTHING_PX // 2 by which the mean over the square spreads a rim's step, so
# that a step's outline stays within two pixels and a rim that slopes down keeps its slope
RIM_REACH_PX = 2
# kernels/refine.cu: the block of one thread per pixel
_BLOCK = (32, 8)
_REFINE_DEFINES = {"SMOOTHING": SMOOTHING_PX, "RIM_REACH": RIM_REACH_PX, "BLOCK_X": _BLOCK[0],
                   "BLOCK_Y": _BLOCK[1], **ROAD_DEFINES}


def smooth(backend: Backend, disparity: Any, offsets: Any = None) -> tuple[Any, Any]:
    """The mean of the valid values of a float32 HxW disparity map (NaN invalid) over the
    SMOOTHING_PX x SMOOTHING_PX square about each pixel, clipped at the border: matching noise
    averaged out, the depth structure of a pothole kept. Returns float32 HxW ``filled`` (NaN
    only where no value of the square is valid: an occluded pothole wall takes its
    neighbours') and ``smoothed`` (NaN where the pixel itself is invalid), both plus
    ``offsets`` (float32 HxW px, the local road's: local_road.pixel_offsets) where given. On
    the GPU one kernel (kernels/refine.cu), on the CPU two box means (stages/box_cpu.py)."""
    xp = backend.xp
    if backend.is_gpu:
        height, width = disparity.shape
        filled = xp.empty((height, width), dtype=xp.float32)
        smoothed = xp.empty((height, width), dtype=xp.float32)
        _kernel(backend, "refine_smooth")(
            _grid(height, width), _BLOCK,
            (xp.ascontiguousarray(disparity, dtype=xp.float32),
             disparity if offsets is None else xp.ascontiguousarray(offsets, dtype=xp.float32),
             np.int32(offsets is not None), np.int32(height), np.int32(width), filled,
             smoothed))
        return filled, smoothed
    valid = xp.isfinite(disparity)
    total = box_cpu.box_mean(xp.where(valid, disparity, 0), SMOOTHING_PX, "constant")
    share = box_cpu.box_mean(valid, SMOOTHING_PX, "constant")
    mean = total / xp.maximum(share, xp.float32(1e-6))
    nan = xp.float32(xp.nan)
    filled = xp.where(share > 1e-4, mean, nan).astype(xp.float32)
    if offsets is not None:
        filled = filled + offsets
    return filled, xp.where(valid, filled, nan)


def refine_labels(backend: Backend, labels: Any, filled: Any, road: RoadModel | Any,
                  road_level: float, superpixel_labels: Any, drops: Any, observed: Any,
                  radius_px: int, fraction: float) -> Any:
    """The refinement stage: int32 HxW labels where, besides the pixels of ``labels``, every
    pixel within ``radius_px`` (a square) of pothole k whose superpixel is observed and whose
    transformed ``filled`` disparity (of :func:`smooth`, transformed with ``road`` and
    ``road_level`` = delta_DT) lies more than ``fraction`` x its superpixel's threshold drop
    below ``road_level`` is labelled k (the largest label where two are that close); and where
    a pixel, labelled or joining, lies less than half as deep below ``road_level`` as the
    deepest pixel within RIM_REACH_PX of it (a square, clipped), it is 0. The mean over
    SMOOTHING_PX spreads a rim's step in depth half the square's side into the road, and the
    step lies where the mean has come half way down: the road beside a rim, and the road-level
    pixels of the superpixels that straddle it, leave; a rim that slopes down loses at most its
    outer RIM_REACH_PX. A pixel whose ``filled`` is NaN keeps its label.
    ``labels``, ``superpixel_labels`` int32 HxW; ``drops`` float64 and ``observed`` bool per
    superpixel (threshold.observation); ``road`` a RoadModel, or on the GPU also its device
    parameters. ``fraction`` <= 0 returns ``labels``. On the GPU one kernel
    (kernels/refine.cu)."""
    if fraction <= 0 or radius_px <= 0:
        return labels
    xp = backend.xp
    if backend.is_gpu:
        height, width = labels.shape
        out = xp.empty((height, width), dtype=xp.int32)
        _kernel(backend, "refine_grow")(
            _grid(height, width), _BLOCK,
            (xp.ascontiguousarray(labels, dtype=xp.int32), filled,
             xp.ascontiguousarray(superpixel_labels, dtype=xp.int32),
             xp.ascontiguousarray(drops, dtype=xp.float64),
             xp.ascontiguousarray(observed, dtype=xp.bool_), device_params(backend, road),
             np.float32(road_level), np.float64(fraction), np.int32(radius_px),
             np.int32(height), np.int32(width), out))
        return out
    # only pixels within the radius of a labelled one can change: the labels' bounding box
    out = labels.astype(xp.int32)
    labelled = labels > 0
    rows = xp.flatnonzero(labelled.any(axis=1))
    if rows.size == 0:
        return out
    cols = xp.flatnonzero(labelled[rows[0]:rows[-1] + 1].any(axis=0))
    height, width = labels.shape
    box = _around(rows[0], rows[-1], cols[0], cols[-1], radius_px, height, width)
    # the depths within RIM_REACH_PX of the box, for the deepest near each of its pixels
    reach = _around(box[0].start, box[0].stop - 1, box[1].start, box[1].stop - 1,
                    RIM_REACH_PX, height, width)
    below_reach = xp.float32(road_level) - transform_on_host(filled, road, road_level, reach)
    deepest = box_cpu.square_maximum(
        xp.where(xp.isfinite(below_reach), below_reach, -xp.inf).astype(xp.float32),
        2 * RIM_REACH_PX + 1)
    within = (slice(box[0].start - reach[0].start, box[0].stop - reach[0].start),
              slice(box[1].start - reach[1].start, box[1].stop - reach[1].start))
    below = below_reach[within]
    off_step = below < xp.float32(0.5) * deepest[within]
    inside = superpixel_labels[box]
    deep = (below > fraction * xp.take(drops, inside)) & xp.take(observed, inside) & ~off_step
    near = box_cpu.square_maximum(out[box].astype(xp.float32), 2 * radius_px + 1
                                  ).astype(xp.int32)
    out[box] = xp.where(labelled[box], xp.where(off_step, 0, out[box]),
                        xp.where(deep, near, 0))
    return out


def _around(top: int, bottom: int, left: int, right: int, margin: int, height: int,
            width: int) -> tuple[slice, slice]:
    """Rows ``top``..``bottom`` and columns ``left``..``right`` (inclusive) widened by
    ``margin`` px each way, clipped to an HxW image: (rows, columns) slices."""
    return (slice(max(int(top) - margin, 0), min(int(bottom) + margin + 1, height)),
            slice(max(int(left) - margin, 0), min(int(right) + margin + 1, width)))


def extend_occluded(backend: Backend, labels: Any, filled: Any, smoothed: Any,
                    road: RoadModel | Any, superpixel_labels: Any, observed: Any) -> Any:
    """The occlusion stage: int32 HxW labels where the strip that only the left camera sees
    beside each pothole's right rim joins the pothole, and ``smoothed`` NaN there (in place).

    Left of a right rim (floor, then road going right) the right camera's view of the floor
    is cut off by the rim: the Dd = d_road - d_floor pixels of the left image just left of the
    rim have no match, and the matcher gives them the road's disparity, so the labels stop Dd
    pixels short. At the right end u of each labelled run of a row, d_floor is ``filled`` (the
    7x7 mean of :func:`smooth`) a smoothing square's width inside, at u - (SMOOTHING_PX - 1):
    the mean there takes in neither the strip nor the half square by which the smoothing, and
    so the refinement, carries the labels past the floor's edge; d_road is the road model's at
    u + 1. The unlabelled pixels u + k, 0 < k <= Dd, up to the next labelled one, whose
    superpixel is observed, take the run's label. Their disparity is the matcher's guess:
    ``smoothed`` (float32 HxW, what measuring reads) becomes NaN there, so they add to a
    pothole's area, not to its depth.
    ``labels``, ``superpixel_labels`` int32 HxW; ``observed`` bool per superpixel; ``road`` a
    RoadModel, or on the GPU also its device parameters. On the GPU one kernel
    (kernels/refine.cu) on a copy of the labels."""
    xp = backend.xp
    height, width = labels.shape
    if backend.is_gpu:
        labels = xp.ascontiguousarray(labels, dtype=xp.int32)
        out = labels.copy()
        _kernel(backend, "refine_occluded")(
            _grid(height, width), _BLOCK,
            (labels, filled, smoothed, xp.ascontiguousarray(superpixel_labels, dtype=xp.int32),
             xp.ascontiguousarray(observed, dtype=xp.bool_), device_params(backend, road),
             np.int32(height), np.int32(width), out))
        return out
    labelled = labels > 0
    ends = xp.nonzero(labelled[:, :-1] & ~labelled[:, 1:])
    inside = ends[1] - (SMOOTHING_PX - 1)
    floor = xp.where(inside >= 0, filled[ends[0], xp.maximum(inside, 0)], xp.nan)
    step = road.at(xp, (ends[1] + 1).astype(xp.float64), ends[0].astype(xp.float64)) - floor
    out = xp.ascontiguousarray(labels, dtype=xp.int32).copy()
    _join_strips(out, smoothed, ends[1], xp.searchsorted(ends[0], xp.arange(height + 1)),
                 xp.asarray(step, dtype=xp.float64), superpixel_labels,
                 xp.ascontiguousarray(observed, dtype=xp.bool_))
    return out


@numba.njit(parallel=True, cache=True)
def _join_strips(labels: np.ndarray, smoothed: np.ndarray, end_columns: np.ndarray,
                 row_starts: np.ndarray, steps: np.ndarray, superpixel_labels: np.ndarray,
                 observed: np.ndarray) -> None:
    """extend_occluded's strips, in place: after each run end (``end_columns`` of row v at
    ``row_starts[v]``..``row_starts[v + 1]``, its strip width in ``steps``), the unlabelled
    pixels up to that width and up to the next labelled one whose superpixel is observed take
    the run's label, and ``smoothed`` NaN there."""
    height, width = labels.shape
    for v in numba.prange(height):
        for at in range(row_starts[v], row_starts[v + 1]):
            end = end_columns[at]
            label = labels[v, end]
            u = end + 1
            while u < width and labels[v, u] <= 0 and u - end <= steps[at]:
                if observed[superpixel_labels[v, u]]:
                    labels[v, u] = label
                    smoothed[v, u] = np.nan
                u += 1


def radius(region_size_px: int) -> int:
    """How far (px) refinement reaches beyond a pothole's superpixels: half a superpixel."""
    return region_size_px // 2


def _grid(height: int, width: int) -> tuple[int, int]:
    return (-(-width // _BLOCK[0]), -(-height // _BLOCK[1]))


def _kernel(backend: Backend, name: str) -> Any:
    """Kernel ``name`` of kernels/refine.cu with the numbers it shares with this module."""
    return backend.kernel("refine.cu", name, _REFINE_DEFINES)
