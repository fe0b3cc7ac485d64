"""The local road reference: the road around each superpixel, measured on the SLIC grid.

The global road model (road_model.py) is one surface for the whole view; real roads have
crowns, cross slopes that differ side to side, and edges that fall away. Each superpixel is
therefore compared with a robust local surface fitted to the superpixels around it, over a
window of ``radius_m`` metres on the road: larger than a pothole, smaller than the road's
bends. The surface is a weighted plane in grid coordinates fitted to the residuals of the
superpixel means from the global model; superpixels that lie off it by more than their own
threshold drop (potholes, bumps, mismatches) are left out, round after round. The spread of
the road's superpixels about that surface in the same window is the disparity noise a
superpixel's mean is judged against there: it grows with distance and with poor texture, and
holds what one plane cannot follow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..backend import Backend
from ..calibration import StereoCalibration
from . import road_model, superpixels

# robust rounds of the local fit (the first one about the global model)
ROUNDS = 4
# fewest inlier superpixels a window needs for a plane; with fewer, their mean; with none, 0
MIN_PLANE_SUPPORT = 6
# kernels/local_road.cu: threads of a block (one block per moment, on at most as many
# multiprocessors); the moments; the shared memory a block's summed-area table may take
# (bytes; where it does not fit, the tables lie in global memory)
_THREADS = 1024
_MOMENTS = 9
_SHARED_TABLE_BYTES = 200 * 1024
_DEFINES = {"ROUNDS": ROUNDS, "MIN_PLANE_SUPPORT": MIN_PLANE_SUPPORT, "MOMENTS": _MOMENTS,
            "THREADS": _THREADS,
            **road_model.FIT_LAYOUT, **road_model.ROAD_DEFINES}


def offsets(backend: Backend, means: Any, usable: Any, drops: Any, shape: tuple[int, int],
            region_size_px: int, downsample: int, road_params: Any,
            calibration: StereoCalibration, road_level: float, radius_m: float,
            road_report: Any) -> tuple[Any, Any]:
    """Per superpixel, how far (px of disparity) the local road lies below the global road
    model (float64 (count,); 0 where no road is near) and the noise of the road's superpixel
    means about it there (float64 (count,) px: the root mean square of the inliers'
    distances from the local surface over the window, with three degrees of freedom taken by
    the plane; the road fit's robust sigma, road_model.fit_sigma of ``road_report``, where the
    window holds fewer than MIN_PLANE_SUPPORT inliers). On the backend, nothing read back.

    ``means``: float32 (count,) mean transformed disparity D2 of each superpixel (grid label
    order, superpixels.grid_count of the HxW ``shape`` with ``region_size_px`` and
    ``downsample``); ``usable``: bool (count,), superpixels that may carry the road (the road
    ahead where the model holds, with valid pixels); ``drops``: float64 (count,) threshold
    drops (px), the band about the local surface a superpixel must lie in to count as road;
    ``road_params``: the global model's kernel parameters; ``road_level``: delta_DT (px). The
    window about superpixel k reaches ``radius_m`` along and across the road: B / d m per
    pixel across at road disparity d, B / (d cos i) along it, i the angle between the pixel's
    ray and the road's normal. On the GPU one cooperative launch (kernels/local_road.cu)
    holds every round and the noise, a block per moment building its summed-area table in
    shared memory."""
    xp = backend.xp
    height, width = shape[0] // downsample, shape[1] // downsample
    step = superpixels.grid_step(region_size_px, downsample)
    cells_y, cells_x = superpixels.grid_shape(shape, region_size_px, downsample)
    if backend.is_gpu:
        cells = cells_y * cells_x
        pitch = (cells_x + 1) | 1
        table_bytes = (cells_y + 1) * pitch * 8
        local_table = table_bytes <= _SHARED_TABLE_BYTES
        blocks = min(_MOMENTS, backend.multiprocessors())
        reference = xp.empty(cells, dtype=xp.float64)
        noise = xp.empty(cells, dtype=xp.float64)
        kernel = backend.kernel("local_road.cu", "local_road_fit", _DEFINES, cooperative=True)
        if local_table and table_bytes > 48 * 1024:
            kernel.max_dynamic_shared_size_bytes = table_bytes
        kernel(
            (blocks,), (_THREADS,),
            (xp.ascontiguousarray(means, dtype=xp.float32),
             xp.ascontiguousarray(usable, dtype=xp.bool_),
             xp.ascontiguousarray(drops, dtype=xp.float64), road_params, road_report,
             np.int32(cells_y),
             np.int32(cells_x), np.int32(step), np.int32(width), np.int32(height),
             np.int32(downsample), np.float64(calibration.f), np.float64(calibration.cx),
             np.float64(calibration.cy), np.float64(calibration.baseline),
             np.float64(road_level), np.float64(radius_m), np.int32(pitch),
             np.int32(local_table), xp.empty(2 * cells, dtype=xp.int32),
             xp.empty(2 * cells, dtype=xp.float64), xp.empty(cells, dtype=xp.uint8),
             xp.empty(cells, dtype=xp.float64), xp.empty(_MOMENTS * cells, dtype=xp.float64),
             xp.empty(1 if local_table else blocks * table_bytes // 8, dtype=xp.float64),
             reference, noise, xp.zeros(1, dtype=xp.uint32)),
            shared_mem=table_bytes if local_table else 0)
        return reference, noise
    u, v = superpixels.cell_centres(xp, shape, region_size_px, downsample)
    road = road_model.params_at(xp, road_params, u, v)
    nx, ny, nz = road_model.params_normal(xp, road_params, calibration)
    f = calibration.f
    ray_x, ray_y = (u - calibration.cx) / f, (v - calibration.cy) / f
    cosine = (nx * ray_x + ny * ray_y + nz) / xp.sqrt(ray_x * ray_x + ray_y * ray_y + 1.0)
    ahead = (road > 0) & (cosine > 0)
    cell_m = calibration.baseline * step * downsample / xp.where(ahead, road, 1.0)
    across = xp.where(ahead, xp.ceil(radius_m / cell_m), 1.0)
    along = xp.where(ahead, xp.ceil(radius_m * xp.where(ahead, cosine, 1.0) / cell_m), 1.0)
    half_x = xp.clip(across, 1, cells_x).astype(xp.int64).reshape(cells_y, cells_x)
    half_y = xp.clip(along, 1, cells_y).astype(xp.int64).reshape(cells_y, cells_x)
    residual = (road_level - means.astype(xp.float64)).reshape(cells_y, cells_x)
    usable = (usable & xp.isfinite(means)).reshape(cells_y, cells_x)
    residual = xp.where(usable, residual, 0.0)
    band = drops.astype(xp.float64).reshape(cells_y, cells_x)
    window = _Windows(xp, half_y, half_x)
    reference = xp.zeros((cells_y, cells_x), dtype=xp.float64)
    for _ in range(ROUNDS):
        inlier = usable & (xp.abs(residual - reference) <= band)
        reference = window.plane(inlier.astype(xp.float64), residual)
    inlier = (usable & (xp.abs(residual - reference) <= band)).astype(xp.float64)
    support, spread = window.totals(inlier, inlier * (residual - reference) ** 2)
    spread = xp.maximum(spread, 0.0)
    noise = xp.where(support >= MIN_PLANE_SUPPORT,
                     xp.sqrt(spread / xp.maximum(support - 3.0, 1.0)),
                     road_model.fit_sigma(xp, road_report, road_params))
    return reference.ravel(), noise.ravel()


@dataclass(frozen=True)
class LocalTests:
    """Per superpixel (count,), its mean D2 against the local road: ``drop``, float64 px, the
    threshold drop below the global road's level D2 = delta_DT with the local road's offset
    added (what a pothole's mean must lie under); ``depressed``, bool, searched and deeper
    than ``refine_fraction`` of its threshold drop below the local road (where the pixel
    refinement may grow); ``significant``, bool or None, searched and deeper than
    ``corner_significance`` times it (None where that is 0); ``bumps``, bool or None, searched
    and above the local road by more than ``noise_sigmas`` times the road's noise there: where
    a matcher that moved an edge (a lane marking's) reads one side as a dip, the other reads
    as a bump, which a road does not make next to a pothole (None where ``noise_sigmas`` is
    0)."""

    drop: Any
    depressed: Any
    significant: Any
    bumps: Any


def local_tests(backend: Backend, means: Any, reference: Any, noise: Any, drop: Any,
                searched: Any, road_level: float, refine_fraction: float,
                corner_significance: float, noise_sigmas: float) -> LocalTests:
    """The :class:`LocalTests` of superpixels of mean D2 ``means`` (float32 (count,) px), the
    local road's offset ``reference`` and ``noise`` (float64 (count,) px, :func:`offsets`),
    their threshold drops ``drop`` (float64 (count,) px, or one float for all) and the bool
    (count,) ``searched`` ones; ``road_level``: delta_DT (px). Nothing read back; on the GPU
    one kernel (kernels/local_road.cu)."""
    xp = backend.xp
    count = int(means.shape[0])
    if backend.is_gpu:
        drops = xp.full(count, drop, dtype=xp.float64) if np.isscalar(drop) \
            else xp.ascontiguousarray(drop, dtype=xp.float64)
        total = xp.empty(count, dtype=xp.float64)
        flags = xp.empty((3, count), dtype=xp.bool_)
        threads = 256
        backend.kernel("local_road.cu", "local_tests", _DEFINES)(
            (-(-count // threads),), (threads,),
            (xp.ascontiguousarray(means, dtype=xp.float32),
             xp.ascontiguousarray(reference, dtype=xp.float64),
             xp.ascontiguousarray(noise, dtype=xp.float64), drops,
             xp.ascontiguousarray(searched, dtype=xp.bool_), np.int32(count),
             np.float64(road_level), np.float64(refine_fraction),
             np.float64(corner_significance), np.float64(noise_sigmas), total, flags))
        return LocalTests(total, flags[0], flags[1] if corner_significance > 0 else None,
                          flags[2] if noise_sigmas > 0 else None)
    significant = None
    if corner_significance > 0:
        significant = deeper(searched, means, road_level, reference, drop, corner_significance)
    bumps = None
    if noise_sigmas > 0:
        below = road_level - means.astype(xp.float64) - reference
        bumps = searched & xp.isfinite(below) & (below < -noise_sigmas * noise)
    return LocalTests(drop + reference,
                      deeper(searched, means, road_level, reference, drop, refine_fraction),
                      significant, bumps)


def deeper(searched: Any, means: Any, road_level: float, reference: Any, drop: Any,
           factor: float) -> Any:
    """Bool (count,): the ``searched`` superpixels whose mean D2 (``means``, float32 (count,)
    px) lies below the road's level ``road_level`` (delta_DT, px) less ``reference`` (the local
    road's offset, float64 (count,) px, or 0 for the road model) by more than ``factor`` times
    their threshold ``drop`` (float64 (count,) px, or one float for all). Array code, either
    backend."""
    return searched & (means < np.float32(road_level) - reference - factor * drop)


class _Windows:
    """Box sums over per-cell windows of the grid (half sizes ``half_y``, ``half_x`` cells,
    clipped at the grid's edges) by summed-area tables."""

    def __init__(self, xp: Any, half_y: Any, half_x: Any) -> None:
        self.xp = xp
        rows, cols = half_y.shape
        i = xp.arange(rows, dtype=xp.int64)[:, None]
        j = xp.arange(cols, dtype=xp.int64)[None, :]
        self.top = xp.clip(i - half_y, 0, rows)
        self.bottom = xp.clip(i + half_y + 1, 0, rows)
        self.left = xp.clip(j - half_x, 0, cols)
        self.right = xp.clip(j + half_x + 1, 0, cols)
        self.y = xp.broadcast_to(i.astype(xp.float64), (rows, cols))
        self.x = xp.broadcast_to(j.astype(xp.float64), (rows, cols))
        self.shape = (rows, cols)

    def totals(self, *values: Any) -> Any:
        """The sums of each of ``values`` (rows x cols each) over each cell's window:
        float64 (len(values), rows, cols), one summed-area table per value."""
        xp = self.xp
        table = xp.zeros((len(values), self.shape[0] + 1, self.shape[1] + 1), dtype=xp.float64)
        table[:, 1:, 1:] = xp.cumsum(xp.cumsum(xp.stack(values), axis=1), axis=2)
        return (table[:, self.bottom, self.right] - table[:, self.top, self.right]
                - table[:, self.bottom, self.left] + table[:, self.top, self.left])

    def plane(self, weight: Any, value: Any) -> Any:
        """At each cell, the value at that cell of the plane fitted by weighted least squares
        to ``value`` over its window (the weighted mean where the window holds fewer than
        MIN_PLANE_SUPPORT weighted cells or they lie on a line; 0 where it holds none)."""
        xp = self.xp
        x, y = self.x, self.y
        n, sx, sy, sxx, syy, sxy, s, sxv, syv = self.totals(
            weight, weight * x, weight * y, weight * x * x, weight * y * y, weight * x * y,
            weight * value, weight * x * value, weight * y * value)
        safe = xp.maximum(n, 1e-12)
        mean = s / safe
        # moments about the window's weighted centroid
        cxx = sxx - sx * sx / safe
        cyy = syy - sy * sy / safe
        cxy = sxy - sx * sy / safe
        cxv = sxv - sx * s / safe
        cyv = syv - sy * s / safe
        det = cxx * cyy - cxy * cxy
        scale = xp.maximum(cxx * cyy, 1e-12)
        solvable = (n >= MIN_PLANE_SUPPORT) & (det > 1e-6 * scale)
        safe_det = xp.where(solvable, det, 1.0)
        slope_x = (cxv * cyy - cyv * cxy) / safe_det
        slope_y = (cyv * cxx - cxv * cxy) / safe_det
        fitted = mean + slope_x * (x - sx / safe) + slope_y * (y - sy / safe)
        return xp.where(solvable, fitted, xp.where(n > 0, mean, 0.0))


def pixel_offsets(backend: Backend, cell_offsets: Any, shape: tuple[int, int],
                  region_size_px: int, downsample: int) -> Any:
    """The per-superpixel ``cell_offsets`` (float64 (count,), grid label order) as a float32
    HxW map over the full-resolution ``shape``: bilinear between the grid cells' centres
    (superpixels.cell_centres), constant past the outer centres. On the GPU one kernel
    (kernels/local_road.cu)."""
    xp = backend.xp
    cells_y, cells_x = superpixels.grid_shape(shape, region_size_px, downsample)
    cell_px = float(superpixels.grid_step(region_size_px, downsample) * downsample)
    if backend.is_gpu:
        height, width = shape
        out = xp.empty((height, width), dtype=xp.float32)
        backend.kernel("local_road.cu", "local_pixel_offsets", _DEFINES)(
            (-(-width // 32), -(-height // 8)), (32, 8),
            (xp.ascontiguousarray(cell_offsets, dtype=xp.float64), np.int32(cells_y),
             np.int32(cells_x), np.float32(cell_px), np.int32(height), np.int32(width), out))
        return out
    grid = cell_offsets.reshape(cells_y, cells_x).astype(xp.float32)
    columns = _interpolation(xp, shape[1], cells_x, cell_px)
    rows = _interpolation(xp, shape[0], cells_y, cell_px)
    across = grid[:, columns[0]] * columns[2] + grid[:, columns[1]] * columns[3]
    return across[rows[0], :] * rows[2][:, None] + across[rows[1], :] * rows[3][:, None]


def _interpolation(xp: Any, size: int, cells: int, cell_px: float) -> tuple[Any, ...]:
    """For ``size`` pixel centres, the two grid cells about them and their linear weights
    (cells ``cell_px`` px apart, centres at (k + 0.5) ``cell_px``)."""
    position = (xp.arange(size, dtype=xp.float32) + 0.5) / np.float32(cell_px) - 0.5
    position = xp.clip(position, 0, cells - 1)
    low = xp.floor(position).astype(xp.int32)
    high = xp.minimum(low + 1, cells - 1)
    weight = (position - low).astype(xp.float32)
    return low, high, 1 - weight, weight
