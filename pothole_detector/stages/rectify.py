"""Rectification: each view's raw image resampled into the rectified frame, bilinearly in fixed
point (1/32 px, as OpenCV's remap), the same integers on the CPU (Numba) and the GPU
(kernels/rectify.cu).

The tables come from the calibration's maps (calibration.CameraModel.rectification_maps) once per
calibration; on the GPU they are uploaded once and every frame's remap runs on the device
after the frame's one upload.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numba
import numpy as np

from ..backend import Backend
from .census_sgm import BORDER_X, BORDER_Y
from .matching import matched_columns

REMAP_FRACTION_BITS = 5
_ONE = 1 << REMAP_FRACTION_BITS
_ROUND = 1 << (2 * REMAP_FRACTION_BITS - 1)
REMAP_DEFINES = {"REMAP_FRACTION_BITS": REMAP_FRACTION_BITS}


@dataclass(frozen=True, eq=False)
class RemapTable:
    """Where each pixel of a rectified HxW view samples its raw image (``source_shape``, px):
    ``index`` (int32 HxW) the flat raw index of the top left of its 2x2 neighbourhood, -1
    where it falls outside the raw image (the pixel is 0); ``fraction`` (uint16 HxW) the
    position inside it, x | y << 8, in 1/32 px (0 .. 32); ``unseen`` (bool HxW) the pixels
    outside the raw image and those whose matching window reaches them (the census window's
    half size). Host or device arrays."""

    index: Any
    fraction: Any
    source_shape: tuple[int, int]
    unseen: Any

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.index.shape)  # type: ignore[return-value]

    def on(self, backend: Backend) -> "RemapTable":
        """The table with its arrays on ``backend``."""
        return RemapTable(backend.upload(self.index), backend.upload(self.fraction),
                          self.source_shape, backend.upload(self.unseen))


def remap_table(map_x: np.ndarray, map_y: np.ndarray,
                source_shape: tuple[int, int]) -> RemapTable:
    """The fixed-point table of float32 HxW maps (raw x, y of each rectified pixel, px) into a
    raw image of ``source_shape`` (height, width; at least 2x2)."""
    height, width = source_shape
    xs = np.rint(map_x.astype(np.float64) * _ONE)
    ys = np.rint(map_y.astype(np.float64) * _ONE)
    inside = np.isfinite(xs) & np.isfinite(ys) & (xs >= 0) & (ys >= 0) \
        & (xs <= (width - 1) * _ONE) & (ys <= (height - 1) * _ONE)
    xs = np.where(inside, xs, 0).astype(np.int64)
    ys = np.where(inside, ys, 0).astype(np.int64)
    x0 = np.minimum(xs >> REMAP_FRACTION_BITS, width - 2)
    y0 = np.minimum(ys >> REMAP_FRACTION_BITS, height - 2)
    index = np.where(inside, y0 * width + x0, -1).astype(np.int32)
    fraction = ((xs - x0 * _ONE) | ((ys - y0 * _ONE) << 8)).astype(np.uint16)
    window = np.ones((2 * BORDER_Y + 1, 2 * BORDER_X + 1), np.uint8)
    unseen = cv2.dilate((~inside).astype(np.uint8), window) > 0
    return RemapTable(index, np.where(inside, fraction, 0).astype(np.uint16),
                      (int(height), int(width)), unseen)


@dataclass(frozen=True, eq=False)
class Rectification:
    """The tables of the left and right views, and the float maps of the left one (for the
    pictures drawn on its colour image, :meth:`left_view`)."""

    left: RemapTable
    right: RemapTable
    left_maps: tuple[np.ndarray, np.ndarray]

    @classmethod
    def from_maps(cls, left_maps: tuple[np.ndarray, np.ndarray],
                  right_maps: tuple[np.ndarray, np.ndarray],
                  source_shape: tuple[int, int]) -> "Rectification":
        """From each view's (map_x, map_y) into raw images of ``source_shape``."""
        return cls(remap_table(*left_maps, source_shape), remap_table(*right_maps, source_shape),
                   left_maps)

    @property
    def source_shape(self) -> tuple[int, int]:
        return self.left.source_shape

    @property
    def shape(self) -> tuple[int, int]:
        return self.left.shape

    def on(self, backend: Backend) -> "Rectification":
        """The tables on ``backend`` (the float maps stay on the host)."""
        return Rectification(self.left.on(backend), self.right.on(backend), self.left_maps)

    def left_view(self, image: np.ndarray) -> np.ndarray:
        """A raw left host image (HxW or HxWxC, any dtype) rectified for display (OpenCV's
        bilinear remap; 0 outside the raw image)."""
        return cv2.remap(np.ascontiguousarray(image), self.left_maps[0], self.left_maps[1],
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def invalidate_unseen(backend: Backend, disparity: Any, rectification: "Rectification"
                      ) -> Any:
    """D1 (float32 HxW px, NaN invalid, on ``backend``) with NaN where the rectified left
    pixel, or the right pixel it was matched to, is unseen by its raw camera (RemapTable's
    ``unseen``): the black outside a raw image matches anything."""
    xp = backend.xp
    right_unseen = xp.take_along_axis(rectification.right.unseen,
                                      matched_columns(xp, disparity), axis=1)
    return xp.where(rectification.left.unseen | right_unseen, xp.float32(np.nan), disparity)


def remap(backend: Backend, image: Any, table: RemapTable, out: Any = None) -> Any:
    """A raw uint8 HxW image (on ``backend``) resampled by ``table`` (on ``backend``): uint8 of
    the table's shape, into ``out`` where given."""
    xp = backend.xp
    height, width = table.shape
    if out is None:
        out = xp.empty((height, width), dtype=xp.uint8)
    source = xp.ascontiguousarray(image).reshape(-1)
    if backend.is_gpu:
        count = height * width
        backend.kernel("rectify.cu", "remap_bilinear", REMAP_DEFINES)(
            ((count + 255) // 256,), (256,),
            (source, np.int32(table.source_shape[1]), table.index, table.fraction,
             out, np.int32(count)))
        return out
    _remap_cpu(source, table.source_shape[1], table.index.reshape(-1),
               table.fraction.reshape(-1), out.reshape(-1))
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _remap_cpu(source: np.ndarray, width: int, index: np.ndarray, fraction: np.ndarray,
               out: np.ndarray) -> None:
    """remap's CPU kernel: pixels on Numba's threads, kernels/rectify.cu's arithmetic."""
    for pixel in numba.prange(index.size):
        start = index[pixel]
        if start < 0:
            out[pixel] = 0
            continue
        fx = np.int32(fraction[pixel] & 0xFF)
        fy = np.int32(fraction[pixel] >> 8)
        top = (_ONE - fx) * np.int32(source[start]) + fx * np.int32(source[start + 1])
        bottom = (_ONE - fx) * np.int32(source[start + width]) \
            + fx * np.int32(source[start + width + 1])
        out[pixel] = np.uint8(((_ONE - fy) * top + fy * bottom + _ROUND)
                              >> (2 * REMAP_FRACTION_BITS))


def compile_cpu_kernel() -> None:
    """Compile (or load from Numba's cache) the CPU kernel now, on a 2x2 image."""
    table = remap_table(np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32), (2, 2))
    _remap_cpu(np.zeros(4, np.uint8), 2, table.index.reshape(-1), table.fraction.reshape(-1),
               np.empty(4, np.uint8))
