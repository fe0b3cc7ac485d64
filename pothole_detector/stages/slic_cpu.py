"""SLIC's iterations on the CPU, compiled with Numba: the assignment of every pixel to the
nearest of the nine centres around its grid cell (grid rows on Numba's threads) and the centres'
update, in one pass each over the map instead of an array pass per neighbour; and the
superpixels' sums. The same float32
distances, ties and float64 sums, in the same order, as the array form they replace, so the
labels are those of kernels/slic.cu's reference to the bit. Compiled once and cached beside
this file (or in the user's cache folder).
"""

from __future__ import annotations

import numba
import numpy as np

# the row and column of a centre beyond the grid: no pixel ever takes it
FAR = np.float32(1e9)


@numba.njit(parallel=True, cache=True)
def _assign(filled: np.ndarray, valid: np.ndarray, step: int, cells_x: int, cells_y: int,
            centre_v: np.ndarray, centre_u: np.ndarray, centre_d: np.ndarray,
            spatial_weight: np.float32, labels: np.ndarray) -> None:
    """Each pixel's nearest centre of the 3 x 3 cells about its own (the first of equals in
    row-major order of the neighbours). The rows of a grid row of cells on one thread: the
    nine neighbours' centres (row, column, value, label) are laid out once per column for
    them, so that each neighbour's distances over a whole row are one loop of vectors."""
    height, width = filled.shape
    for cell_i in numba.prange(cells_y):
        near_v = np.empty((9, width), np.float32)
        near_u = np.empty((9, width), np.float32)
        near_d = np.empty((9, width), np.float32)
        near_label = np.empty((9, width), np.int32)
        for k in range(9):
            i = cell_i + k // 3 - 1
            for u in range(width):
                j = u // step + k % 3 - 1
                near_label[k, u] = i * cells_x + j
                if 0 <= i < cells_y and 0 <= j < cells_x:
                    index = i * cells_x + j
                    near_v[k, u] = centre_v[index]
                    near_u[k, u] = centre_u[index]
                    near_d[k, u] = centre_d[index]
                else:
                    near_v[k, u], near_u[k, u], near_d[k, u] = FAR, FAR, np.float32(0.0)
        best = np.empty(width, np.float32)
        for v in range(cell_i * step, min((cell_i + 1) * step, height)):
            row = np.float32(v)
            values, valids, out = filled[v], valid[v], labels[v]
            best[:] = np.float32(np.inf)
            for k in range(9):
                cv, cu, cd, label = near_v[k], near_u[k], near_d[k], near_label[k]
                for u in range(width):
                    weight = np.float32(1.0) if valids[u] else np.float32(0.0)
                    distance = values[u] - cd[u]
                    distance = distance * distance
                    distance = distance * weight
                    dv = row - cv[u]
                    du = np.float32(u) - cu[u]
                    distance = distance + spatial_weight * (dv * dv + du * du)
                    if distance < best[u]:
                        best[u] = distance
                        out[u] = label[u]


@numba.njit(cache=True)
def _update(filled: np.ndarray, valid: np.ndarray, labels: np.ndarray, centre_v: np.ndarray,
            centre_u: np.ndarray, centre_d: np.ndarray) -> None:
    """The centres as the means of their pixels (row, column; the value over the valid ones),
    summed in float64 in row-major order; a centre without pixels stays."""
    count = np.zeros(centre_v.size)
    count_valid = np.zeros(centre_v.size)
    sum_v = np.zeros(centre_v.size)
    sum_u = np.zeros(centre_v.size)
    sum_d = np.zeros(centre_v.size)
    height, width = filled.shape
    for v in range(height):
        for u in range(width):
            label = labels[v, u]
            count[label] += 1.0
            sum_v[label] += v
            sum_u[label] += u
            if valid[v, u]:
                count_valid[label] += 1.0
                sum_d[label] += filled[v, u]
    for label in range(centre_v.size):
        if count[label] > 0:
            centre_v[label] = np.float32(sum_v[label] / count[label])
            centre_u[label] = np.float32(sum_u[label] / count[label])
        if count_valid[label] > 0:
            centre_d[label] = np.float32(sum_d[label] / count_valid[label])


def iterate(filled: np.ndarray, valid: np.ndarray, step: int, cells_y: int, cells_x: int,
            centre_v: np.ndarray, centre_u: np.ndarray, centre_d: np.ndarray,
            compactness: float, iterations: int) -> np.ndarray:
    """``iterations`` rounds of SLIC on the float32 HxW ``filled`` map (0 at invalid pixels)
    with bool HxW ``valid``, from the float32 (cells,) centres (row, column, value; updated in
    place), grid step ``step`` px and compactness m: int32 HxW labels ``i * cells_x + j``."""
    labels = np.empty(filled.shape, dtype=np.int32)
    spatial_weight = np.float32((compactness / step) ** 2)
    filled = np.ascontiguousarray(filled, dtype=np.float32)
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    for _ in range(iterations):
        _assign(filled, valid, step, cells_x, cells_y, centre_v, centre_u, centre_d,
                spatial_weight, labels)
        _update(filled, valid, labels, centre_v, centre_u, centre_d)
    return labels


@numba.njit(cache=True)
def superpixel_sums(values: np.ndarray, labels: np.ndarray,
                    count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per label of the flat int ``labels`` (0..count-1): its pixels, its pixels with a finite
    value of the flat float ``values``, and their values' sum, float64 (count,) each, summed
    in the pixels' order."""
    pixels = np.zeros(count)
    finite = np.zeros(count)
    total = np.zeros(count)
    for index in range(labels.size):
        label = labels[index]
        if label < 0 or label >= count:
            raise ValueError("a superpixel label lies outside 0..count-1")
        pixels[label] += 1.0
        value = values[index]
        if np.isfinite(value):
            finite[label] += 1.0
            total[label] += np.float64(value)
    return pixels, finite, total


@numba.njit(parallel=True, cache=True)
def upsample(labels: np.ndarray, factor: int, height: int, width: int) -> np.ndarray:
    """superpixels.upsample_labels on the host: pixel (v, u) of the height x width result takes
    ``labels`` (2D, any dtype) at (min(v // factor, rows - 1), min(u // factor, cols - 1)):
    each source column's value written over its ``factor`` columns, the columns past the
    last source column's taking its value."""
    rows, cols = labels.shape
    out = np.empty((height, width), dtype=labels.dtype)
    spread = min(cols, -(-width // factor))
    for v in numba.prange(height):
        source, row = labels[min(v // factor, rows - 1)], out[v]
        for column in range(spread):
            value = source[column]
            for u in range(column * factor, min((column + 1) * factor, width)):
                row[u] = value
        for u in range(spread * factor, width):
            row[u] = source[cols - 1]
    return out


@numba.njit(parallel=True, cache=True)
def block_mean(image: np.ndarray, valid: np.ndarray, factor: int) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    """superpixels._block_mean on the host: the mean of the ``valid`` pixels of each ``factor``
    x ``factor`` block of the float32 HxW ``image`` (float32; each block row summed in float32,
    the rows added in order, as NumPy's reduction over the block axes adds them) and whether at
    least half of the block is valid."""
    height, width = image.shape[0] // factor, image.shape[1] // factor
    means = np.empty((height, width), dtype=np.float32)
    enough = np.empty((height, width), dtype=np.bool_)
    for i in numba.prange(height):
        for j in range(width):
            total = np.float32(0.0)
            count = 0
            for a in range(factor):
                row = np.float32(0.0)
                for b in range(factor):
                    if valid[i * factor + a, j * factor + b]:
                        row += image[i * factor + a, j * factor + b]
                        count += 1
                total += row
            means[i, j] = np.float32(np.float64(total) / max(count, 1))
            enough[i, j] = count * 2 >= factor * factor
    return means, enough
