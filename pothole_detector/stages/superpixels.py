"""SLIC superpixels on the transformed disparity map.

Pixels are clustered on (D2 value, u, v). The image is cut into S x S cells; a centre starts at
each cell's middle, moved to the lowest gradient of its 3x3 neighbourhood, and each k-means
iteration compares every pixel with the centres of its own and the eight surrounding cells
(those whose 2S x 2S windows can cover it). On the CPU the comparison is written as
broadcasts over a (cells_y, S, cells_x, S) view (the reference); on the GPU each iteration is
two kernels of kernels/slic.cu (assignment, centre update) with the same arithmetic. Invalid
pixels (NaN) join the spatially nearest centre and do not move centre values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..backend import CPU, Backend
from . import slic_cpu


# block size of the SLIC centre update (kernels/slic.cu, slic_update)
UPDATE_THREADS = 128
# slic_region_size_px 0: superpixels across the image width, and the smallest grid step (px)
REGIONS_ACROSS = 64
MIN_REGION_PX = 8
# slic_region_size_px 0 on a road seen at a grazing angle: the sine of the angle between the
# optical axis and the road below which the grid step shrinks in proportion, and by how much
# at most (a share of the step)
GRAZING_REFERENCE_SINE = 0.5
MIN_GRAZING_SHARE = 0.5
_SLIC_DEFINES = {"UPDATE_THREADS": UPDATE_THREADS}

def _block_mean(image: np.ndarray, valid: np.ndarray,
                factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Valid-pixel mean of ``factor`` x ``factor`` blocks (float32), and blocks at least half
    valid, on the host (slic_cpu.block_mean)."""
    return slic_cpu.block_mean(np.ascontiguousarray(image, dtype=np.float32),
                               np.ascontiguousarray(valid, dtype=np.bool_), factor)


def slic(backend: Backend, image: Any, valid: Any, region_size: int, compactness: float,
         iterations: int) -> tuple[Any, int]:
    """SLIC labels of an HxW float32 map with HxW bool ``valid``.

    ``region_size`` S (px) is the grid step, ``compactness`` m the weight of a spatial distance
    of S in value units. Returns (int32 HxW labels in [0, n), n); label ``i * cells_x + j``
    belongs to grid cell (i, j), and some labels may be empty. On the CPU the iterations are
    Numba kernels (stages/slic_cpu.py), on the GPU CUDA kernels (kernels/slic.cu): the same
    labels.
    """
    if backend.is_gpu:
        return _slic_gpu(backend, image, valid, region_size, compactness, iterations)
    step, cells_y, cells_x, filled, centre_v, centre_u, centre_d = _start(
        backend.xp, image, valid, region_size)
    labels = slic_cpu.iterate(filled, valid, step, cells_y, cells_x,
                              np.array(centre_v, dtype=np.float32),
                              np.array(centre_u, dtype=np.float32),
                              np.array(centre_d, dtype=np.float32), compactness, iterations)
    return labels, cells_y * cells_x


def _start(xp: Any, image: Any, valid: Any, region_size: int) -> tuple[Any, ...]:
    """What the SLIC reference starts from: (step, cells_y, cells_x, the map with 0 at invalid
    pixels, and the initial centres' row, column and value, float32 (cells,)); kernel
    slic_start computes the same centres on the GPU."""
    height, width = image.shape
    step = int(region_size)
    cells_y, cells_x = -(-height // step), -(-width // step)
    filled = xp.where(valid, image, 0).astype(xp.float32)
    centre_v, centre_u = _initial_centres(xp, filled, valid, cells_y, cells_x, step)
    centre_d = filled[centre_v.astype(xp.int32), centre_u.astype(xp.int32)]
    return step, cells_y, cells_x, filled, centre_v, centre_u, centre_d


def _slic_gpu(backend: Backend, image: Any, valid: Any, region_size: int, compactness: float,
              iterations: int) -> tuple[Any, int]:
    xp = backend.xp
    return _slic_gpu_filled(backend, xp.where(valid, image, 0).astype(xp.float32),
                            valid.astype(xp.uint8), region_size, compactness, iterations)


def _slic_gpu_filled(backend: Backend, filled: Any, valid_bytes: Any, region_size: int,
                     compactness: float, iterations: int) -> tuple[Any, int]:
    """slic on the GPU from the map with 0 at invalid pixels (float32 HxW) and the valid mask
    as bytes (uint8 HxW)."""
    xp = backend.xp
    height, width = filled.shape
    step = int(region_size)
    cells_y, cells_x = -(-height // step), -(-width // step)
    n_labels = cells_y * cells_x
    centres = xp.empty((3, n_labels), dtype=xp.float32)
    centre_v, centre_u, centre_d = centres
    labels = xp.empty((height, width), dtype=xp.int32)
    assign = _kernel(backend, "slic_assign")
    update = _kernel(backend, "slic_update")
    i32 = np.int32
    _kernel(backend, "slic_start")(
        ((n_labels + 127) // 128,), (128,),
        (filled, valid_bytes, centre_v, centre_u, centre_d, i32(height), i32(width), i32(step),
         i32(cells_y), i32(cells_x)))
    grid = ((width + 31) // 32, (height + 7) // 8)
    assign_args = (filled, valid_bytes, centre_v, centre_u, centre_d, labels, i32(height),
                   i32(width), i32(step), i32(cells_y), i32(cells_x),
                   np.float32((compactness / step) ** 2))
    update_args = (filled, valid_bytes, labels, centre_v, centre_u, centre_d, i32(height),
                   i32(width), i32(step), i32(cells_x))
    for iteration in range(iterations):
        assign(grid, (32, 8), assign_args)
        if iteration < iterations - 1:
            update((n_labels,), (UPDATE_THREADS,), update_args)
    return labels, n_labels


def _initial_centres(xp: Any, filled: Any, valid: Any, cells_y: int, cells_x: int,
                     step: int) -> tuple[Any, Any]:
    """Cell-middle centres moved to the lowest gradient of their 3x3 neighbourhood;
    float32 arrays (cells_y * cells_x,) of row and column."""
    height, width = filled.shape
    v0 = xp.minimum(xp.arange(cells_y) * step + step // 2, height - 1)
    u0 = xp.minimum(xp.arange(cells_x) * step + step // 2, width - 1)
    v0, u0 = xp.meshgrid(v0, u0, indexing="ij")
    padded = xp.pad(filled, 2, mode="edge")
    gradient = (padded[2:-2, 3:-1] - padded[2:-2, 1:-3]) ** 2 \
        + (padded[3:-1, 2:-2] - padded[1:-3, 2:-2]) ** 2
    gradient = xp.where(valid, gradient, xp.inf)
    candidates_v = xp.stack([xp.clip(v0 + a, 0, height - 1) for a in (-1, 0, 1) for _ in range(3)])
    candidates_u = xp.stack([xp.clip(u0 + b, 0, width - 1) for _ in range(3) for b in (-1, 0, 1)])
    best = xp.argmin(gradient[candidates_v, candidates_u], axis=0)
    v = xp.take_along_axis(candidates_v, best[None], axis=0)[0]
    u = xp.take_along_axis(candidates_u, best[None], axis=0)[0]
    return v.reshape(-1).astype(xp.float32), u.reshape(-1).astype(xp.float32)


@dataclass
class Superpixels:
    """SLIC superpixels of D2: ``grid`` int32 labels on the SLIC grid (H // downsample,
    W // downsample), ``count`` labels, ``labels`` int32 HxW (``grid`` enlarged), per label the
    mean of the valid D2 values ``means`` (float32 (count,), NaN where none is valid) and the
    fraction of valid pixels ``valid_fraction`` (float32 (count,))."""

    grid: Any
    count: int
    labels: Any
    means: Any
    valid_fraction: Any


def superpixels(backend: Backend, transformed: Any, region_size_px: int, compactness: float,
                iterations: int, downsample: int = 1) -> Superpixels:
    """The SLIC stage on the transformed map D2 (HxW float32 px, NaN invalid), on a copy reduced
    by ``downsample`` (valid-pixel block means). ``region_size_px`` is the superpixel grid step
    in full-resolution pixels."""
    grid, count = superpixel_grid(backend, transformed, region_size_px, compactness,
                                  iterations, downsample)
    labels = upsample_labels(backend, grid, downsample, transformed.shape)
    means, valid_fraction = superpixel_means(backend, transformed, labels, count)
    return Superpixels(grid, count, labels, means, valid_fraction)


def superpixel_grid(backend: Backend, transformed: Any, region_size_px: int,
                    compactness: float, iterations: int, downsample: int = 1
                    ) -> tuple[Any, int]:
    """SLIC labels of D2 reduced by ``downsample`` (valid-pixel block means): int32
    (H // downsample, W // downsample) labels and the label count. :func:`upsample_labels`
    gives the full-resolution labels."""
    xp = backend.xp
    step = grid_step(region_size_px, downsample)
    if backend.is_gpu and downsample > 1:
        return _slic_gpu_filled(backend, *_block_mean_gpu(backend, transformed, downsample),
                                step, compactness, iterations)
    valid = xp.isfinite(transformed)
    if downsample > 1:
        image, image_valid = _block_mean(transformed, valid, downsample)
    else:
        image, image_valid = transformed, valid
    return slic(backend, image, image_valid, step, compactness, iterations)


def _block_mean_gpu(backend: Backend, image: Any, factor: int) -> tuple[Any, Any]:
    """_block_mean of the finite values and the SLIC map with 0 where a block is not half
    valid, in one kernel (kernels/slic.cu): (float32, uint8 (H // factor, W // factor))."""
    xp = backend.xp
    height, width = image.shape[0] // factor, image.shape[1] // factor
    filled = xp.empty((height, width), dtype=xp.float32)
    valid = xp.empty((height, width), dtype=xp.uint8)
    _kernel(backend, "slic_block_mean")(
        ((width + 31) // 32, (height + 7) // 8), (32, 8),
        (xp.ascontiguousarray(image, dtype=xp.float32), np.int32(image.shape[1]),
         np.int32(factor), np.int32(height), np.int32(width), filled, valid))
    return filled, valid


def region_size(region_size_px: int, width: int, axis_sine: float = 1.0) -> int:
    """The SLIC grid step S (full-resolution px) for ``slic_region_size_px``: as given, or
    where it is 0, one that cuts the image width into REGIONS_ACROSS superpixels (at least
    MIN_REGION_PX), so that superpixels take the same share of the view on any image size.
    ``axis_sine``: the sine of the angle between the optical axis and the road. Rows foreshorten
    the road by that factor, so that a square superpixel reaches 1 / ``axis_sine`` times as far
    along the road as across it and covers a pothole seen at a grazing angle with road: below
    GRAZING_REFERENCE_SINE (the axis 30 degrees to the road) the step shrinks in proportion,
    to no less than MIN_GRAZING_SHARE of it."""
    if region_size_px > 0:
        return region_size_px
    share = min(1.0, max(MIN_GRAZING_SHARE, axis_sine / GRAZING_REFERENCE_SINE))
    return max(MIN_REGION_PX, round(width * share / REGIONS_ACROSS))


def grid_shape(shape: tuple[int, int], region_size_px: int,
               downsample: int = 1) -> tuple[int, int]:
    """The (rows, columns) of the SLIC grid of an HxW map, from its size alone."""
    height, width = shape[0] // downsample, shape[1] // downsample
    step = grid_step(region_size_px, downsample)
    return -(-height // step), -(-width // step)


def grid_count(shape: tuple[int, int], region_size_px: int, downsample: int = 1) -> int:
    """The label count :func:`superpixel_grid` returns for an HxW map, from its size alone."""
    rows, cols = grid_shape(shape, region_size_px, downsample)
    return rows * cols


def cell_centres(xp: Any, shape: tuple[int, int], region_size_px: int,
                 downsample: int = 1) -> tuple[Any, Any]:
    """Column and row (px of the full-resolution HxW map, float64 (count,)) of the centre of
    each superpixel's grid cell, in label order: where SLIC starts it, and within a cell of
    where it ends. Computed on the backend from the size alone."""
    height, width = shape[0] // downsample, shape[1] // downsample
    step = grid_step(region_size_px, downsample)
    _, cells_x = grid_shape(shape, region_size_px, downsample)
    label = xp.arange(grid_count(shape, region_size_px, downsample), dtype=xp.float64)
    row, col = xp.floor(label / cells_x), label % cells_x
    u = xp.minimum((col + 0.5) * step, width - 0.5) * downsample
    v = xp.minimum((row + 0.5) * step, height - 0.5) * downsample
    return u, v


def grid_step(region_size_px: int, downsample: int) -> int:
    """The SLIC grid step (px of the map reduced by ``downsample``)."""
    return max(2, int(round(region_size_px / downsample)))


def upsample_labels(backend: Backend, labels: Any, factor: int, shape: tuple[int, int]) -> Any:
    """Nearest-neighbour enlargement of a label image (any dtype) by ``factor`` to ``shape``;
    rows and columns past the enlarged image repeat the last one. On the GPU, one kernel for
    int32 labels (kernels/slic.cu); on the host a Numba kernel (slic_cpu.upsample)."""
    if factor == 1 and labels.shape == tuple(shape):
        return labels
    xp = backend.xp
    height, width = shape
    if backend.is_gpu and labels.dtype == np.int32:
        result = xp.empty((height, width), dtype=xp.int32)
        _kernel(backend, "upsample_labels")(
            ((width + 31) // 32, (height + 7) // 8), (32, 8),
            (xp.ascontiguousarray(labels), np.int32(labels.shape[0]),
             np.int32(labels.shape[1]), np.int32(factor), np.int32(height), np.int32(width),
             result))
        return result
    if xp is np:
        return slic_cpu.upsample(np.ascontiguousarray(labels), factor, height, width)
    rows = xp.minimum(xp.arange(height) // factor, labels.shape[0] - 1)
    cols = xp.minimum(xp.arange(width) // factor, labels.shape[1] - 1)
    return labels[rows[:, None], cols[None, :]]


def superpixel_means(backend: Backend, transformed: Any, labels: Any, n_labels: int,
                     ) -> tuple[Any, Any]:
    """Per-superpixel mean of the valid D2 values (float32 (n,), NaN where none is valid) and
    fraction of valid pixels (float32 (n,)). On the GPU: one pass of per-warp sums and one
    small kernel (kernels/slic.cu); on the CPU one pass of a Numba kernel
    (slic_cpu.superpixel_sums)."""
    xp = backend.xp
    if backend.is_gpu:
        sums = xp.zeros((n_labels, 3), dtype=xp.float64)
        size = transformed.size
        _kernel(backend, "superpixel_sums")(
            ((size + 255) // 256,), (256,),
            (xp.ascontiguousarray(transformed, dtype=xp.float32),
             xp.ascontiguousarray(labels, dtype=xp.int32), np.int64(size), sums))
        mean = xp.empty(n_labels, dtype=xp.float32)
        fraction = xp.empty(n_labels, dtype=xp.float32)
        _kernel(backend, "superpixel_finish")(
            ((n_labels + 255) // 256,), (256,), (sums, mean, fraction, np.int32(n_labels)))
        return mean, fraction
    count, count_valid, total = slic_cpu.superpixel_sums(
        np.ascontiguousarray(transformed).ravel(), np.ascontiguousarray(labels).ravel(),
        n_labels)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = xp.where(count_valid > 0, total / xp.maximum(count_valid, 1), xp.nan)
    fraction = count_valid / xp.maximum(count, 1)
    return mean.astype(xp.float32), fraction.astype(xp.float32)


def compile_cpu_kernels() -> None:
    """Compile (or load from Numba's cache) the CPU kernels of SLIC, the superpixel sums, the
    block means and the upsampling (int32 and bool labels) now, on a small map."""
    rng = np.random.default_rng(0)
    image = rng.normal(32, 1, (24, 40)).astype(np.float32)
    valid = rng.random(image.shape) < 0.9
    labels, count = slic(CPU, image, valid, 8, 2.0, 1)
    superpixel_means(CPU, image, labels, count)
    _block_mean(image, valid, 2)
    for small in (labels, valid):
        upsample_labels(CPU, small, 2, (48, 80))


def _kernel(backend: Backend, name: str) -> Any:
    """Kernel ``name`` of kernels/slic.cu with the numbers it shares with this module."""
    return backend.kernel("slic.cu", name, _SLIC_DEFINES)

