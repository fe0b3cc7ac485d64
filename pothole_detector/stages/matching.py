"""Dense matching: semi-global matching with subpixel refinement and left-right check.

Two matchers (``matcher`` parameter): ``census`` is our census SGM (stages/census_sgm.py), on
the GPU in CUDA kernels, on the CPU in Numba kernels, the same integers; ``opencv`` runs OpenCV's
StereoSGBM (Birchfield-Tomasi cost on Sobel-prefiltered images, path aggregation with P1/P2,
parabola subpixel, uniqueness, speckle filter) on the pair and on the mirrored pair for our own
left-right check (OpenCV's own, disp12MaxDiff, is left off); a 3x3 median follows.
Disparities are float32 pixels with NaN where invalid."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from ..backend import Backend, to_host
from ..errors import InputError, NoTextureError
from ..params import Config
from . import census_cpu, census_sgm
from .perspective import add_shifts, transform_right

_SGBM_MODES = {
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "hh": cv2.STEREO_SGBM_MODE_HH,
}


@lru_cache(maxsize=16)
def _sgbm(levels: int, block: int, p1: int, p2: int, mode: str, uniqueness: int,
          lr_max_diff: int, speckle_window: int, speckle_range: int) -> Any:
    """A memoized OpenCV matcher for one setting."""
    area = block * block
    return cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=levels, blockSize=block, P1=p1 * area, P2=p2 * area,
        disp12MaxDiff=lr_max_diff, uniquenessRatio=uniqueness,
        speckleWindowSize=speckle_window, speckleRange=speckle_range, mode=_SGBM_MODES[mode],
    )


def matched_columns(xp: Any, disparity: Any) -> Any:
    """int32 HxW: the right image's column each left pixel of a float32 HxW disparity map
    (px, NaN invalid) was matched to, u - d rounded and clipped to the image (u itself where
    the disparity is NaN)."""
    width = disparity.shape[1]
    columns = xp.arange(width, dtype=xp.float32)[None, :] - xp.where(
        xp.isfinite(disparity), disparity, xp.float32(0))
    return xp.clip(xp.rint(columns), 0, width - 1).astype(xp.int32)


def to_gray8(image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """uint8 grey image (HxW) from mono8/mono16 (HxW) or RGB/RGBA (HxWx3 or 4) host arrays.

    16-bit images are scaled so their largest value maps to 255; colour is averaged with the
    usual luma weights (input is assumed RGB). ``out``: a C-contiguous uint8 HxW array to
    write the grey image into (8-bit colour is converted straight into it), returned.
    """
    if out is not None:
        if image.ndim == 3 and image.dtype == np.uint8:
            cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY, dst=out)
        else:
            np.copyto(out, to_gray8(image))
        return out
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = image[:, :, :3]
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    if image.dtype == np.uint8:
        return np.ascontiguousarray(image)
    peak = float(image.max()) if image.size else 0.0
    scale = 255.0 / peak if peak > 0 else 1.0
    return cv2.convertScaleAbs(image.astype(np.float32), alpha=scale)


def _sgbm_view(left: np.ndarray, right: np.ndarray, levels: int, block: int,
               config: Config) -> np.ndarray:
    """One OpenCV SGBM pass: float32 disparity of ``left`` (px), -1 where invalid."""
    matcher = _sgbm(levels, block, config.sgm_p1, config.sgm_p2, config.sgm_mode,
                    config.sgm_uniqueness_percent, -1, config.speckle_window_px,
                    config.speckle_range_px * 16)
    fixed = matcher.compute(left, right)
    disparity = fixed.astype(np.float32) * np.float32(1.0 / 16.0)
    disparity[fixed < 0] = -1.0
    return disparity


def left_right_check(left_disparity: np.ndarray, right_disparity: np.ndarray,
                     max_diff: float) -> np.ndarray:
    """Bool HxW: left pixels whose disparity d lands on a right pixel u - d whose own disparity
    differs by at most ``max_diff`` px. Both maps float32 px, negative = invalid."""
    height, width = left_disparity.shape
    target = np.rint(np.arange(width, dtype=np.float32)[None, :] - left_disparity)
    inside = (left_disparity >= 0) & (target >= 0) & (target < width)
    target = np.clip(target, 0, width - 1).astype(np.intp)
    partner = np.take_along_axis(right_disparity, target, axis=1)
    return inside & (partner >= 0) & (np.abs(partner - left_disparity) <= max_diff)


def sgm_disparity(left: np.ndarray, right: np.ndarray, levels: int, config: Config,
                  block_size: int | None = None) -> np.ndarray:
    """SGM disparity of two rectified uint8 HxW images over [0, levels) px.

    ``levels`` must be a positive multiple of 16. With ``lr_max_diff_px`` >= 0 the right view is
    matched too (on the mirrored pair) and pixels failing the left-right check are dropped.
    Returns float32 HxW, NaN where invalid (outside the search range, failed uniqueness or
    left-right check, speckles, the image border where the matching block does not fit).
    """
    block = block_size or config.sgm_block_size
    disparity = _sgbm_view(left, right, levels, block, config)
    if config.lr_max_diff_px >= 0:
        mirrored = _sgbm_view(np.ascontiguousarray(right[:, ::-1]),
                              np.ascontiguousarray(left[:, ::-1]), levels, block, config)
        consistent = left_right_check(disparity, mirrored[:, ::-1], config.lr_max_diff_px)
        disparity[~consistent] = -1.0
    if config.median_filter:
        disparity = cv2.medianBlur(disparity, 3)
    disparity[disparity < 0] = np.nan
    border = block // 2 + 1
    disparity[:border] = np.nan
    disparity[-border:] = np.nan
    disparity[:, :border] = np.nan
    disparity[:, -border:] = np.nan
    return disparity


class Matcher:
    """D1 of a rectified pair on one backend: census SGM or OpenCV SGBM (``config.matcher``).
    Keeps the GPU buffers, or the host census SGM's volumes, between frames."""

    def __init__(self, backend: Backend, lender: Matcher | None = None) -> None:
        """``lender``: a matcher never run at the same time whose GPU path volume, or host
        volumes, this one may use (see census_sgm.GpuMatcher and HostVolumes)."""
        self.backend = backend
        self._gpu = census_sgm.GpuMatcher(
            backend, lender=lender._gpu if lender is not None else None) \
            if backend.is_gpu else None
        self._volumes = lender._volumes if lender is not None else census_sgm.HostVolumes()

    @property
    def generation(self) -> int:
        """Counts the replacements of the GPU matcher's device buffers (0 on the CPU)."""
        return self._gpu.generation if self._gpu is not None else 0

    def __call__(self, left: Any, right: Any, shifts: Any, levels: int, config: Config,
                 block_size: int | None = None) -> Any:
        """D1 (float32 HxW px, NaN invalid) of uint8 HxW images on the backend, matched over
        levels [0, levels) of the pair with the right image transformed by the GPT shift table
        ``shifts`` (int32 (3, H), stages/perspective.py): left pixel u at level d against the
        right pixel x - kappa(x, v) of x = u - d."""
        kind = config.matcher
        if kind == "census" and self._gpu is not None:
            return self._gpu(left, right, shifts, levels, config.census_p1, config.census_p2,
                             config.sgm_uniqueness_percent, config.lr_max_diff_px,
                             config.median_filter)
        left, right, shifts = to_host(left), to_host(right), to_host(shifts)
        if kind == "census":
            disparity = census_sgm.cpu_disparity(
                left, right, shifts, levels, config.census_p1, config.census_p2,
                config.sgm_uniqueness_percent, config.lr_max_diff_px, config.median_filter,
                self._volumes)
        else:
            disparity = add_shifts(sgm_disparity(left, transform_right(np, right, shifts),
                                                 levels, config, block_size), shifts)
            outside = np.arange(left.shape[1], dtype=np.float32)[None, :] - disparity < 0
            # SGBM matches a blank patch at the lowest level (every cost 0), which on the GPT
            # band is the road prior itself: drop such pixels as the census matcher does
            disparity[outside | census_sgm.textureless(census_sgm.census_transform(left))] = \
                np.nan
        return self.backend.upload(disparity)


def set_host_threads(count: int) -> None:
    """Run the host's matchers (OpenCV and the census SGM's CPU kernels) on at most ``count``
    threads: a worker process's or task's share of the cores."""
    cv2.setNumThreads(count)
    census_cpu.set_threads(count)


def host_threads() -> int:
    """The threads this process's host matchers run on: its share of the cores
    (:func:`set_host_threads`; OpenCV's count, all the cores unless set)."""
    return cv2.getNumThreads()


def downsample(xp: Any, image: Any, factor: int) -> Any:
    """Area-averaged reduction of a uint8 image by an integer factor (H//factor x W//factor):
    the block mean rounded half up, the same on both backends."""
    if factor == 1:
        return image
    height, width = image.shape[0] // factor, image.shape[1] // factor
    crop = image[: height * factor, : width * factor]
    total = crop.reshape(height, factor, width, factor).sum(axis=(1, 3), dtype=xp.int32)
    return ((total + factor * factor // 2) // (factor * factor)).astype(xp.uint8)


def check_pair(left: np.ndarray, right: np.ndarray) -> None:
    """Raise InputError unless ``left`` and ``right`` are a pair the pipeline can take, and
    NoTextureError where they are the same image (no disparity can be had)."""
    for name, image in (("left", left), ("right", right)):
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
            raise InputError(f"{name} image must be a non-empty HxW or HxWxC array")
        if image.ndim == 3 and image.shape[2] not in (3, 4):
            raise InputError(f"{name} image has {image.shape[2]} channels; use mono, RGB or RGBA")
        if image.dtype not in (np.uint8, np.uint16):
            raise InputError(f"{name} image is {image.dtype}; use 8- or 16-bit images")
    if left.shape[:2] != right.shape[:2]:
        raise InputError(
            f"left image is {left.shape[1]}x{left.shape[0]} but right is "
            f"{right.shape[1]}x{right.shape[0]}: a rectified pair has equal sizes"
        )
    if min(left.shape[:2]) < 16:
        raise InputError(f"images of {left.shape[1]}x{left.shape[0]} are too small (min 16x16)")
    # every 16th row first: a stereo pair differs there, so the whole comparison is rare; a
    # blank pair is left to the texture checks
    if np.array_equal(left[::16], right[::16]) and np.array_equal(left, right) \
            and left.min() != left.max():
        raise NoTextureError("no disparity: the left and right images are the same, not a "
                             "stereo pair")
