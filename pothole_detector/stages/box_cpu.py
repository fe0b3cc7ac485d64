"""The mean and the maximum over a square on the CPU. The mean compiled with Numba:
scipy.ndimage.uniform_filter's arithmetic (a pass down the columns, then one along the rows,
each a running sum in float64 of the window's values, divided by its size and written as
float32), with the columns of a pass and the rows of the next on Numba's threads; compiled once
and cached beside this file (or in the user's cache folder). The maximum by OpenCV's dilation.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

# how the square reaches past the border: the border pixel repeated, or zeros
MODES = ("nearest", "constant")
# the fewest columns of one thread's share of the pass down the columns
_COLUMN_CHUNK = 64


@numba.njit(cache=True, inline="always")
def _outside(row: int, height: int, nearest: bool) -> int:
    """The row whose value stands for ``row`` (-1: a zero)."""
    if 0 <= row < height:
        return row
    if not nearest:
        return -1
    return 0 if row < 0 else height - 1


@numba.njit(parallel=True, cache=True)
def _down_columns(image: np.ndarray, size: int, nearest: bool, threads: int,
                  out: np.ndarray) -> None:
    """The pass down the columns: each of ``threads`` threads a run of whole columns, row after
    row (each row's share read as one stretch)."""
    height, width = image.shape
    before = size // 2
    chunk = max(_COLUMN_CHUNK, -(-width // threads))
    chunks = (width + chunk - 1) // chunk
    for index in numba.prange(chunks):
        start = index * chunk
        stop = min(start + chunk, width)
        running = np.zeros(stop - start, dtype=np.float64)
        for k in range(size):
            source = _outside(k - before, height, nearest)
            if source >= 0:
                for u in range(start, stop):
                    running[u - start] += np.float64(image[source, u])
        for u in range(start, stop):
            out[0, u] = np.float32(running[u - start] / size)
        for v in range(1, height):
            entering = _outside(v + size - 1 - before, height, nearest)
            leaving = _outside(v - 1 - before, height, nearest)
            for u in range(start, stop):
                new = np.float64(image[entering, u]) if entering >= 0 else 0.0
                old = np.float64(image[leaving, u]) if leaving >= 0 else 0.0
                running[u - start] += new - old
                out[v, u] = np.float32(running[u - start] / size)


@numba.njit(parallel=True, cache=True)
def _along_rows(image: np.ndarray, size: int, nearest: bool, out: np.ndarray) -> None:
    """The pass along the rows: two rows a thread at a time, their running sums in one loop
    (two independent chains of additions), then divided in a loop of vectors."""
    height, width = image.shape
    before = size // 2
    for pair in numba.prange((height + 1) // 2):
        first, second = 2 * pair, min(2 * pair + 1, height - 1)
        sums = np.empty((2, width))
        for row, v in enumerate((first, second)):
            running = 0.0
            for k in range(size):
                source = _outside(k - before, width, nearest)
                if source >= 0:
                    running += np.float64(image[v, source])
            sums[row, 0] = running
        running_first, running_second = sums[0, 0], sums[1, 0]
        for u in range(1, width):
            entering = _outside(u + size - 1 - before, width, nearest)
            leaving = _outside(u - 1 - before, width, nearest)
            new = np.float64(image[first, entering]) if entering >= 0 else 0.0
            old = np.float64(image[first, leaving]) if leaving >= 0 else 0.0
            running_first += new - old
            new = np.float64(image[second, entering]) if entering >= 0 else 0.0
            old = np.float64(image[second, leaving]) if leaving >= 0 else 0.0
            running_second += new - old
            sums[0, u], sums[1, u] = running_first, running_second
        for row, v in enumerate((first, second)):
            for u in range(width):
                out[v, u] = np.float32(sums[row, u] / size)


def box_mean(image: np.ndarray, size: int, mode: str) -> np.ndarray:
    """float32 HxW: the mean of the ``size`` x ``size`` square about each pixel of the 2D
    ``image`` (any real dtype, read as float32), the square reaching past the border as
    ``mode`` says (MODES): scipy.ndimage.uniform_filter(image as float32, size, mode=mode)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, not {mode!r}")
    source = np.ascontiguousarray(image, dtype=np.float32)
    between = np.empty_like(source)
    out = np.empty_like(source)
    if source.size:
        _down_columns(source, size, mode == "nearest", numba.get_num_threads(), between)
        _along_rows(between, size, mode == "nearest", out)
    return out


@numba.njit(parallel=True, cache=True)
def gather_columns(image: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """float32 HxW: ``image[v, columns[v, u]]`` (np.take_along_axis along the rows) for the
    float32 HxW ``image`` and int32 HxW ``columns`` inside it."""
    height, width = columns.shape
    out = np.empty((height, width), dtype=np.float32)
    for v in numba.prange(height):
        for u in range(width):
            out[v, u] = image[v, columns[v, u]]
    return out


def square_maximum(image: np.ndarray, size: int) -> np.ndarray:
    """The maximum over the ``size`` x ``size`` square about each pixel of a uint8 or float32
    HxW image, the square clipped to the image (OpenCV's dilation, a separable pass each way):
    what scipy.ndimage.maximum_filter gives with mode "nearest" or "reflect", and for values
    >= 0 with mode "constant" (labels below 2^24 are exact in float32)."""
    return cv2.dilate(image, cv2.getStructuringElement(cv2.MORPH_RECT, (size, size)))
