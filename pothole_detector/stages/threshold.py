"""Threshold by k-means on the 2D histogram of (D2, mean of D2 over the 8 neighbours)."""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from ..backend import Backend, to_host
from ..calibration import StereoCalibration
from . import road_model, superpixels

# D2 values farther than this from the road level (px) are left out of the histogram.
HISTOGRAM_BELOW_PX = 128.0
HISTOGRAM_ABOVE_PX = 64.0
# Per-block histograms of the GPU kernel stay in shared memory up to this size (bytes).
MAX_SHARED_TABLE_BYTES = 200 * 1024
# kernels/threshold.cu: the table kernel's tile (rows, columns), a thread's run of pixels along
# a row, the block size (a thread per run of a tile) and the blocks a multiprocessor holds with
# the default bins' tables in shared memory (48 KB each), which bounds the kernel's registers;
# the search's block size
_TILE_ROWS, _RUN, _TABLE_THREADS = 64, 16, 256
_THRESHOLD_KERNEL = {"TILE_ROWS": _TILE_ROWS, "TILE_COLUMNS": _TABLE_THREADS // _TILE_ROWS * _RUN,
                     "RUN": _RUN, "TABLE_THREADS": _TABLE_THREADS, "TABLE_BLOCKS": 4,
                     "SEARCH_THREADS": 1024}
# threshold_reference values select() takes, in the order kernels/threshold.cu numbers them
REFERENCES = ("split", "road_mean", "road_fit")


def neighbour_mean(image: np.ndarray) -> np.ndarray:
    """Mean of the valid values among each pixel's 8 neighbours (HxW float32 on the host; NaN
    if none): one Numba pass, the float32 sums added in row-major order of the neighbours."""
    return _neighbour_mean(np.ascontiguousarray(image, dtype=np.float32))


@numba.njit(parallel=True, cache=True)
def _neighbour_mean(image: np.ndarray) -> np.ndarray:
    height, width = image.shape
    out = np.empty((height, width), dtype=np.float32)
    for v in numba.prange(height):
        for u in range(width):
            total = np.float32(0.0)
            number = np.float32(0.0)
            for dv in range(-1, 2):
                for du in range(-1, 2):
                    if dv == 0 and du == 0:
                        continue
                    y, x = v + dv, u + du
                    if 0 <= y < height and 0 <= x < width and np.isfinite(image[y, x]):
                        total += image[y, x]
                        number += np.float32(1.0)
            out[v, u] = total / max(number, np.float32(1.0)) if number > 0 else np.nan
    return out


def histogram_range(bin_px: float, road_level: float) -> tuple[float, int]:
    """(lowest D2 of the histogram (px), bin count) around ``road_level`` (delta_DT)."""
    lo = road_level - HISTOGRAM_BELOW_PX
    return lo, int(math.ceil((HISTOGRAM_BELOW_PX + HISTOGRAM_ABOVE_PX) / bin_px))


def threshold_search(backend: Backend, transformed: Any, bin_px: float, road_level: float,
                     result: Any = None) -> Any:
    """The threshold stage's search: (found, best split index, road mean) as a backend float64
    (3,), written into ``result`` where given, nothing read back.

    The split t_r is the diagonal threshold of the 2D histogram of (D2, mean of D2 over the 8
    neighbours) that minimises the within-cluster scatter E2 of region 1 (both components below
    t_r, pothole) and region 2 (both above, road); the road mean is the mean D2 of region 2 at
    that t_r. A pixel with bins (i1, i2) is in region 1 for every split t >= max(i1, i2) and in
    region 2 for every t < min(i1, i2), so two 1D tables over max and min of the bin pair
    (count, sum of g1, of g2, of g1^2 + g2^2), a prefix and a suffix sum give each candidate in
    O(1): the same sums as cumulative sums over the 2D table. ``road_level`` (delta_DT)
    centres the histogram range. On the GPU the tables come from one kernel (shared-memory
    histograms per block where they fit) and the search from a one-block kernel
    (kernels/threshold.cu).
    """
    if backend.is_gpu:
        return _search_on_device(backend, transformed, bin_px, road_level, result)
    lo, n_bins = histogram_range(bin_px, road_level)
    found = np.array(_search(np, *_tables(transformed, lo, bin_px, n_bins)), float)
    if result is None:
        return found
    result[...] = found
    return result


def histogram_threshold(backend: Backend, transformed: Any, bin_px: float,
                        road_level: float) -> tuple[float, float]:
    """(t_r, road mean) in px of :func:`threshold_search`, read back; (NaN, NaN) when two
    clusters cannot be formed."""
    return split_from_result(to_host(threshold_search(backend, transformed, bin_px, road_level)),
                             bin_px, road_level)


def reference_level(result: np.ndarray, bin_px: float, road_level: float,
                    reference: str) -> float:
    """The level (px of D2) delta_PD is subtracted from, of a host copy of a search
    ``result``: t_r (split), the road cluster's mean (road_mean; both NaN where the search
    found no split) or ``road_level`` itself (road_fit)."""
    if reference == "road_fit":
        return float(road_level)
    t_r, road_mean = split_from_result(result, bin_px, road_level)
    return road_mean if reference == "road_mean" else t_r


def split_from_result(result: np.ndarray, bin_px: float, road_level: float
                      ) -> tuple[float, float]:
    """(t_r, road mean) in px from the search result (found, best split index, road mean);
    (NaN, NaN) when nothing was found."""
    found, best, road_mean = result
    if not found:
        return float("nan"), float("nan")
    lo, _ = histogram_range(bin_px, road_level)
    return lo + (int(best) + 1) * bin_px, float(road_mean)


def _tables(transformed: np.ndarray, lo: float, bin_px: float,
            n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(4, n_bins) float64 tables over max(i1, i2) and over min(i1, i2): count and sums of
    g1, g2, g1^2 + g2^2 of the pixels inside the histogram range (on the host)."""
    g1 = np.ascontiguousarray(transformed, dtype=np.float32)
    tables = _bin_sums(g1.ravel(), neighbour_mean(g1).ravel(), np.float32(lo),
                       np.float32(bin_px), n_bins)
    return tables[0], tables[1]


@numba.njit(cache=True)
def _bin_sums(g1: np.ndarray, g2: np.ndarray, lo: np.float32, bin_px: np.float32,
              n_bins: int) -> np.ndarray:
    """float64 (2, 4, n_bins): per bin pair (i1, i2) = floor((g - lo) / bin_px) of the pixels'
    D2 ``g1`` and neighbour mean ``g2`` (float32 (n,), both bins inside the table), by the
    larger and by the smaller bin, the count and the sums of g1, g2 and g1^2 + g2^2 (float64),
    added in pixel order."""
    tables = np.zeros((2, 4, n_bins))
    for k in range(g1.shape[0]):
        i1 = np.floor((g1[k] - lo) / bin_px)
        i2 = np.floor((g2[k] - lo) / bin_px)
        if not (i1 >= 0 and i2 >= 0 and i1 < n_bins and i2 < n_bins):
            continue
        a, b = np.float64(g1[k]), np.float64(g2[k])
        square = a * a + b * b
        for side, index in ((0, int(max(i1, i2))), (1, int(min(i1, i2)))):
            tables[side, 0, index] += 1.0
            tables[side, 1, index] += a
            tables[side, 2, index] += b
            tables[side, 3, index] += square
    return tables


def _search(xp: Any, by_high: Any, by_low: Any) -> tuple[bool, int, float]:
    """(found, best split index, road mean) from the two (4, n_bins) tables of _tables."""
    below = xp.cumsum(by_high, axis=1)[:, :-1]
    above = xp.cumsum(by_low[:, ::-1], axis=1)[:, ::-1][:, 1:]
    ok = (below[0] > 0) & (above[0] > 0)
    n1, n2 = xp.maximum(below[0], 1), xp.maximum(above[0], 1)
    e2 = below[3] + above[3] - (below[1] ** 2 + below[2] ** 2) / n1 \
        - (above[1] ** 2 + above[2] ** 2) / n2
    scatter = xp.where(ok, e2, xp.inf)
    best = int(xp.argmin(scatter))
    return bool(ok[best]), best, float(above[1][best] / n2[best])


def _search_on_device(backend: Backend, transformed: Any, bin_px: float, road_level: float,
                      result: Any) -> Any:
    """threshold_search on the GPU: the two tables by one kernel, the search by another."""
    xp = backend.xp
    lo, n_bins = histogram_range(bin_px, road_level)
    height, width = transformed.shape
    tables = xp.zeros((2, 4, n_bins), dtype=xp.float64)
    result = xp.empty(3, dtype=xp.float64) if result is None else result
    histogram = _kernel(backend, "threshold_tables")
    search = _kernel(backend, "threshold_search")
    shared = tables.nbytes
    in_shared = shared <= MAX_SHARED_TABLE_BYTES
    if in_shared and shared > 48 * 1024:
        histogram.max_dynamic_shared_size_bytes = shared
    rows, columns = _THRESHOLD_KERNEL["TILE_ROWS"], _THRESHOLD_KERNEL["TILE_COLUMNS"]
    histogram((-(-width // columns), -(-height // rows)), (_THRESHOLD_KERNEL["TABLE_THREADS"],),
              (transformed, tables, np.int32(height), np.int32(width), np.float32(lo),
               np.float32(bin_px), np.int32(n_bins), np.int32(in_shared)),
              shared_mem=shared if in_shared else 0)
    search((1,), (_THRESHOLD_KERNEL["SEARCH_THREADS"],), (tables, result, np.int32(n_bins)))
    return result


def reference_for(reference: str, threshold_mode: str) -> str:
    """The threshold reference ``threshold_reference`` asks for: auto is the road fit in the
    metric mode and the road cluster's mean (the paper's) in the pixel mode."""
    if reference != "auto":
        return reference
    return "road_mean" if threshold_mode == "pixels" else "road_fit"


def select(backend: Backend, result: Any, bin_px: float, road_level: float,
           reference: str, means: Any, valid_fraction: Any,
           threshold_drop: float | Any, min_valid_fraction: float) -> Any:
    """The selection stage: bool (n,) of pothole superpixels, those whose mean D2 (``means``,
    float32 (n,)) lies below t_s = reference - ``threshold_drop`` with more than
    ``min_valid_fraction`` valid pixels. The ``reference`` (REFERENCES) is t_r (split) or the
    road cluster's mean (road_mean) of the search ``result`` of :func:`threshold_search`, or
    the road model's own level ``road_level`` (road_fit); ``threshold_drop`` is delta_PD (px)
    or a float64 (n,) of per-superpixel drops (metric mode). With a reference from the search,
    no superpixel is selected where it found no split. On the GPU one kernel
    (kernels/threshold.cu) reads ``result`` on the device."""
    xp = backend.xp
    lo, _ = histogram_range(bin_px, road_level)
    n = means.shape[0]
    per_superpixel = not isinstance(threshold_drop, (float, int))
    if not backend.is_gpu:
        level = reference_level(result, bin_px, road_level, reference)
        if not math.isfinite(level):
            return xp.zeros(n, dtype=bool)
        return select_superpixels(xp, means, valid_fraction, level - threshold_drop,
                                  min_valid_fraction)
    drops = xp.ascontiguousarray(threshold_drop, dtype=xp.float64) if per_superpixel \
        else result
    selected = xp.empty(n, dtype=xp.bool_)
    _kernel(backend, "threshold_select")(
        ((n + 255) // 256,), (256,),
        (result, np.float64(lo), np.float64(bin_px), np.int32(REFERENCES.index(reference)),
         np.float64(road_level),
         np.float64(0.0 if per_superpixel else threshold_drop), drops,
         np.int32(per_superpixel), xp.ascontiguousarray(means, dtype=xp.float32),
         xp.ascontiguousarray(valid_fraction, dtype=xp.float32),
         np.float32(min_valid_fraction), np.int32(n), selected))
    return selected


def select_superpixels(xp: Any, means: Any, valid_fraction: Any, threshold_px: Any,
                       min_valid_fraction: float) -> Any:
    """Bool (n,): superpixels whose mean D2 is below ``threshold_px`` (a scalar or (n,) array
    of t_s values) with more than ``min_valid_fraction`` valid pixels."""
    return xp.isfinite(means) & (means < threshold_px) & (valid_fraction > min_valid_fraction)


def observation(backend: Backend, shape: tuple[int, int], region_size_px: int,
                downsample: int, road_params: Any, road_report: Any,
                calibration: StereoCalibration, depth_m: float, drop_px: float = 0.0,
                noise_sigmas: float = 3.0, max_depth_m: float = math.inf,
                observed_range: Any = None, noise_px: Any = None) -> tuple[Any, Any]:
    """Per superpixel, the threshold, as the drop below the road's disparity (px) of a pothole
    just deep enough, and whether the road is observed there; and how far along the road the
    observed superpixels reach. On the backend with nothing read back.

    Superpixel k sits at the centre of its grid cell (superpixels.cell_centres; the SLIC of an
    HxW ``shape`` map with ``region_size_px`` and ``downsample``), where the road's disparity
    is d and the ray meets the road plane at cos(incidence). Metric mode (``drop_px`` 0): the
    threshold depth is ``depth_m``, or where more, the depth the matcher resolves there:
    fB (1 / (d - k sigma) - 1 / d) cos(incidence), the depth whose disparity drop is
    k = ``noise_sigmas`` times the disparity noise sigma there: ``noise_px`` (float64
    (count,) px, the road's per superpixel, local_road.offsets) where given, else the road
    fit's robust sigma (road_model.fit_sigma); the drop is
    that depth's, and the road is observed where the ray meets it in front of the camera, the
    model's curvature stays within road_model.MAX_CURVATURE_SHARE of its plane's disparity (else
    it extrapolates past the road it was fitted on), and the threshold depth is at most
    ``max_depth_m``. Pixel mode (``drop_px`` > 0): the drop is
    ``drop_px``, observed where d > ``drop_px`` >= sigma, the ray meets the plane in front of the
    camera and the curvature is within that share. Returns bool (count,) observed and
    float64 (count,) drops, and writes into ``observed_range`` (float64 (2,), where given) the
    nearest and farthest distance (m) ahead along the road of an observed superpixel, NaN
    where none is: from the point below the camera along the optical axis's direction on the
    road plane (motion.road_frame's forward axis), (z - n_z h) / sqrt(1 - n_z^2) for the
    road point at depth z, n the plane's unit normal, h the camera's height. On the GPU one
    single-block kernel (kernels/threshold.cu)."""
    xp = backend.xp
    count = superpixels.grid_count(shape, region_size_px, downsample)
    observed_range = xp.empty(2, dtype=xp.float64) if observed_range is None \
        else observed_range
    if backend.is_gpu:
        observed = xp.empty(count, dtype=xp.bool_)
        drops = xp.empty(count, dtype=xp.float64)
        height, width = shape[0] // downsample, shape[1] // downsample
        step = superpixels.grid_step(region_size_px, downsample)
        f64, i32 = np.float64, np.int32
        _kernel(backend, "threshold_observation")(
            (1,), (_THRESHOLD_KERNEL["SEARCH_THREADS"],),
            (road_params, road_report, i32(count), i32(-(-width // step)), i32(step),
             i32(width), i32(height), i32(downsample), f64(calibration.f),
             f64(calibration.cx), f64(calibration.cy), f64(calibration.fb), f64(depth_m),
             f64(drop_px), f64(noise_sigmas), f64(min(max_depth_m, 1e300)),
             drops if noise_px is None else xp.ascontiguousarray(noise_px, dtype=xp.float64),
             np.int32(noise_px is not None), observed, drops, observed_range))
        return observed, drops
    with np.errstate(divide="ignore", invalid="ignore"):
        return _observation(xp, superpixels.cell_centres(xp, shape, region_size_px, downsample),
                            road_params, road_report, calibration, depth_m, drop_px,
                            noise_sigmas, max_depth_m, observed_range, noise_px)


def _observation(xp: Any, centres: tuple[Any, Any], road_params: Any, road_report: Any,
                 calibration: StereoCalibration, depth_m: float, drop_px: float,
                 noise_sigmas: float, max_depth_m: float, observed_range: Any,
                 noise_px: Any = None) -> tuple[Any, Any]:
    """observation on the host (NumPy): the reference of kernels/threshold.cu's."""
    u, v = centres
    road = road_model.params_at(xp, road_params, u, v)
    planar = road_model.params_planar(road_params, u, v)
    sigma = road_model.fit_sigma(xp, road_report, road_params)
    noise = noise_sigmas * (sigma if noise_px is None else noise_px)
    nx, ny, nz = road_model.params_normal(xp, road_params, calibration)
    f, fb = calibration.f, calibration.fb
    incidence = nx * (u - calibration.cx) / f + ny * (v - calibration.cy) / f + nz
    ahead = (incidence > 0) & (xp.abs(road - planar) <= road_model.MAX_CURVATURE_SHARE * planar)
    if drop_px > 0:
        near_road = (road > sigma) & ahead
        observed = near_road & (road > drop_px) & (drop_px >= sigma)
        drops = xp.full(road.shape, drop_px, dtype=xp.float64)
        safe = xp.where(near_road, road, 2.0 * sigma + 1.0)
    else:
        near_road = (road > noise) & ahead
        safe = xp.where(near_road, road, 2.0 * noise + 1.0)
        resolvable = fb * (1.0 / (safe - noise) - 1.0 / safe) * incidence
        threshold_m = xp.maximum(resolvable, depth_m)
        observed = near_road & (threshold_m <= max_depth_m)
        drops = safe - fb / (fb / safe + threshold_m / xp.where(near_road, incidence, 1.0))
    height_m = road_model.params_height(xp, road_params, calibration)
    along = (fb / safe - nz * height_m) / xp.sqrt(xp.maximum(1.0 - nz * nz, 1e-12))
    span = xp.stack([xp.where(observed, along, xp.inf).min(),
                     xp.where(observed, along, -xp.inf).max()])
    observed_range[...] = xp.where(xp.isfinite(span), span, xp.nan)
    return observed, drops



_THRESHOLD_DEFINES = {**_THRESHOLD_KERNEL, **road_model.FIT_LAYOUT,
                      **road_model.ROAD_DEFINES}


def _kernel(backend: Backend, name: str) -> Any:
    """Kernel ``name`` of kernels/threshold.cu with the numbers it shares with this module."""
    return backend.kernel("threshold.cu", name, _THRESHOLD_DEFINES)

