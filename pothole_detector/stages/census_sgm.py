"""Census semi-global matching, the default matcher: CUDA kernels on the GPU (kernels/sgm.cu),
Numba kernels on the CPU (stages/census_cpu.py).

The algorithm, the same on both backends to the integer disparity:

1. Centre-symmetric census over a 9x7 window (31 bits, edge-clamped): bit i of pixel (v, u)
   says whether I(v + dy_i, u + dx_i) > I(v - dy_i, u - dx_i) for the 31 offsets with
   dy > 0, or dy = 0 and dx > 0.
2. Matching cost of left pixel (v, u) at level d against column u - d of the GPT-transformed
   right census (stages/perspective.py: that column shows the right pixel x - kappa(x, v) of
   x = u - d; the census is of the untransformed right image, so the transformation moves
   whole census words and needs no shifted image): the Hamming distance of the two census
   words, or 31 where x shows no right pixel (left of the image).
3. Eight path costs L_r(p, d) = C(p, d) + min(L_r(q, d), L_r(q, d -+ 1) + P1,
   min_k L_r(q, k) + P2) - min_k L_r(q, k), q the predecessor of p along r; pixels whose
   predecessor lies outside the image start with L_r = C. Each path cost fits a byte
   (C <= 31, P2 <= 224).
4. S = sum of the eight; winner d* = the smallest d of least S. Invalid when a level more than
   one from d* comes within the uniqueness margin (100 S(d*) >= (100 - U) S(d)), when d* points
   left of the image, or when the right view's winner at u - d* (least S(u - d* + d, d) over d,
   smallest d on ties) differs from d* by more than the left-right tolerance. Subpixel:
   d* + (S(d*-1) - S(d*+1)) / (2 max(S(d*-1) + S(d*+1) - 2 S(d*), 1)) inside the band.
5. 3x3 median (edge-replicated, invalid = -1 takes part), then the census border is invalid,
   the shift is added back (D1 = D0 + kappa(u - D0, v), perspective.add_shifts) and pixels
   whose match falls left of the image are invalid, as are pixels whose band reaches left of
   the right image (u - (D - 1) < first(v)): their true match may lie off the image, where
   the in-image levels left to them are the shallow, pothole-like ones.

Disparities are float32 px, NaN where invalid.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Callable, Iterator

import cv2
import numpy as np

from ..backend import Backend, StageClock
from ..errors import ConfigError
from . import census_cpu, perspective

CENSUS_RADIUS_Y, CENSUS_RADIUS_X = 3, 4
CENSUS_OFFSETS: tuple[tuple[int, int], ...] = tuple(
    (dy, dx) for dy in range(CENSUS_RADIUS_Y + 1)
    for dx in range(-CENSUS_RADIUS_X, CENSUS_RADIUS_X + 1) if dy > 0 or dx > 0)
CENSUS_BITS = len(CENSUS_OFFSETS)
_OFFSET_TABLE = np.array(CENSUS_OFFSETS, dtype=np.int64)
INVALID_COST = CENSUS_BITS
BORDER_Y, BORDER_X = CENSUS_RADIUS_Y + 1, CENSUS_RADIUS_X + 1
# (dx, dy) of the eight path directions, in the order of the kernels' blockIdx.y.
DIRECTIONS: tuple[tuple[int, int], ...] = (
    (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1))
# A path cost is at most INVALID_COST + P2; the GPU keeps two opposite paths' sum in a byte.
MAX_P2 = 127 - INVALID_COST
# Pairs of directions (indices into DIRECTIONS) that share one byte volume on the GPU: the first
# of each pair runs in the first launch, the second adds to it in the second.
DIRECTION_PAIRS: tuple[tuple[int, int], ...] = ((0, 2), (1, 3), (4, 6), (5, 7))


def census_transform(image: np.ndarray) -> np.ndarray:
    """uint32 HxW census words of a uint8 HxW image (on the host): bit k set where the pixel
    CENSUS_OFFSETS[k] ahead is brighter than the one as far behind, the border repeated
    (census_cpu.census_words, rows on Numba's threads)."""
    ry, rx = CENSUS_RADIUS_Y, CENSUS_RADIUS_X
    padded = np.pad(np.ascontiguousarray(image, dtype=np.uint8), ((ry, ry), (rx, rx)),
                    mode="edge")
    return census_cpu.census_words(padded, _OFFSET_TABLE, ry, rx, *image.shape)


def textureless(census_left: np.ndarray) -> np.ndarray:
    """bool HxW: pixels whose census word (uint32 HxW) is 0 together with their 8
    neighbours' (edge-replicated): no pair of the window differs upwards anywhere in the 3x3
    windows, so no match there means anything (a blank or saturated patch). A 3 x 3 erosion
    of the blank words."""
    blank = (census_left == 0).astype(np.uint8)
    return cv2.erode(blank, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0


def finish(raw: np.ndarray, shifts: np.ndarray, median: bool,
           census_left: np.ndarray, levels: int) -> np.ndarray:
    """D1 (float32 HxW px, NaN invalid) from the raw D0 (-1 invalid): median, census border,
    the GPT ``shifts`` added back (perspective.add_shifts), matches left of the image dropped,
    pixels whose band of ``levels`` reaches left of the right image dropped, and textureless
    pixels dropped: those whose left census word is 0 together with their 8 neighbours'
    (edge-replicated), i.e. no pair of the window differs upwards anywhere in 3x3 windows
    (on the host)."""
    height, width = raw.shape
    if median:
        raw = cv2.medianBlur(raw, 3)
    disparity = perspective.add_shifts(raw, shifts)
    columns = np.arange(width)[None, :]
    band_outside = columns - (levels - 1) < shifts[perspective.SHIFT_FIRST][:, None]
    invalid = (raw < 0) | (columns.astype(np.float32) - disparity < 0) | band_outside \
        | textureless(census_left)
    invalid[:BORDER_Y] = invalid[height - BORDER_Y:] = True
    invalid[:, :BORDER_X] = invalid[:, width - BORDER_X:] = True
    return np.where(invalid, np.float32(np.nan), disparity).astype(np.float32)


class HostVolumes:
    """The host matcher's cost (uint8) and path-sum (uint16) volumes, H x W x D, kept from
    frame to frame and grown to the largest asked for: a new array's pages are mapped and
    zeroed by the system at their first write, about 13 ms of a 1280x720 frame of 64 levels."""

    def __init__(self) -> None:
        self._cost = np.empty(0, dtype=np.uint8)
        self._total = np.empty(0, dtype=np.uint16)

    def take(self, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Views (cost, total) of ``shape`` into the held volumes (their values: any)."""
        size = shape[0] * shape[1] * shape[2]
        if self._cost.size < size:
            self._cost = self._total = np.empty(0, dtype=np.uint8)  # freed before the new
            self._cost = np.empty(size, dtype=np.uint8)
            self._total = np.empty(size, dtype=np.uint16)
        return self._cost[:size].reshape(shape), self._total[:size].reshape(shape)


def cpu_disparity(left: np.ndarray, right: np.ndarray, shifts: np.ndarray, levels: int,
                  p1: int, p2: int, uniqueness_percent: int, lr_max_diff_px: int,
                  median: bool, volumes: HostVolumes | None = None) -> np.ndarray:
    """The whole census SGM on the host: float32 HxW D1 (px, NaN invalid) of uint8 HxW images
    and the int32 (3, H) GPT ``shifts``, with stages/census_cpu.py's compiled kernels (the same
    integers as the GPU's); its volumes in ``volumes`` where given, else new ones."""
    check_settings(left.shape, levels, p1, p2)
    census_left = census_transform(left)
    transformed = perspective.transform_right(np, census_transform(right), shifts)
    cost, total = (volumes or HostVolumes()).take((*left.shape, levels))
    census_cpu.matching_cost(census_left, transformed, shifts[perspective.SHIFT_FIRST],
                             levels, INVALID_COST, cost)
    census_cpu.path_sums(cost, p1, p2, total)
    raw = census_cpu.select_disparities(total, uniqueness_percent, lr_max_diff_px)
    return finish(raw, shifts, median, census_left, levels)


def compile_cpu_kernels() -> None:
    """Compiles the CPU kernels, or loads them from Numba's cache, by matching a small random
    pair: about 5 s the first time after installation, under a second later."""
    texture = np.random.default_rng(0).integers(0, 256, (24, 64), dtype=np.uint8)
    cpu_disparity(texture, np.roll(texture, -4, axis=1), perspective.no_shifts(24), 16, 3, 20,
                  5, 1, True)


def check_settings(shape: tuple[int, ...], levels: int, p1: int, p2: int) -> None:
    """Raise ConfigError for settings the matcher cannot run."""
    if levels < 16 or levels % 16:
        raise ConfigError(f"census SGM needs a positive multiple of 16 levels, got {levels}")
    if not 0 <= p1 < p2 <= MAX_P2:
        raise ConfigError(f"census SGM needs 0 <= P1 < P2 <= {MAX_P2}, got P1={p1}, P2={p2}")
    if len(shape) != 2 or min(shape) < 1:
        raise ConfigError(f"census SGM needs a non-empty HxW image, got shape {shape}")


# Lines of a path pass times lanes below this share of the device's resident threads leave
# it underfilled: the lanes are doubled (see lanes_for).
FILL_SHARE = 0.15


def lanes_for(levels: int, lines: int = 0, resident_threads: int = 0) -> int:
    """Threads per path line of the GPU matcher (levels: a multiple of 16).

    The most of 4, 8, 16, 32 that leave each an even number of 4 to 8 levels (two levels per
    32-bit word); else the fewest that leave at most 8 (a multiple of 4 where possible), and
    32 (or 16) for longer ranges. Then, while ``lines`` (the path lines of one pass) times the
    lanes fill less than FILL_SHARE of ``resident_threads`` (the device's), twice the lanes
    as long as each keeps an even number of levels."""
    lanes = next((candidate for candidate in (32, 16, 8, 4)
                  if levels % candidate == 0 and levels // candidate in (4, 6, 8)), 0)
    if not lanes:
        lanes = _fewest_lanes(levels, lambda per_lane: per_lane <= 8 and per_lane % 4 == 0)
    while lanes < 32 and levels % (4 * lanes) == 0 \
            and lines * lanes < FILL_SHARE * resident_threads:
        lanes *= 2
    return lanes


def path_levels(levels: int) -> int:
    """Levels the GPU path lanes hold for ``levels`` (a multiple of 16): ``levels`` where some
    lane count leaves each lane an even 4 to 8 of them (two per 32-bit word), else ``levels``
    + 16 where that does (80 -> 96, 112 -> 128, 176 -> 192, 240 -> 256), else ``levels``.
    The padded levels cost more than any real one (sgm.cu, PADDED), so the path costs and
    disparities are those of ``levels``, at the speed of the packed kernels."""
    for held in (levels, levels + 16):
        if any(held % lanes == 0 and held // lanes in (4, 6, 8) for lanes in (4, 8, 16, 32)):
            return held
    return levels


def select_lanes_for(levels: int) -> int:
    """Threads per pixel of the GPU winner search (levels: a multiple of 16): the fewest of 4,
    8, 16, 32 that leave each a multiple of 4 levels, at most 12 (32-bit path reads); else the
    fewest that leave at most 8; 32 (or 16) for longer ranges."""
    return _fewest_lanes(levels, lambda per_lane: per_lane <= 12 and per_lane % 4 == 0)


def _fewest_lanes(levels: int, preferred: Callable[[int], bool]) -> int:
    """The fewest of 4, 8, 16, 32 lanes dividing ``levels`` whose levels per lane pass
    ``preferred``; else the fewest that leave at most 8 levels each; else 32 (or 16)."""
    for rule in (preferred, lambda per_lane: per_lane <= 8):
        for lanes in (4, 8, 16, 32):
            if levels % lanes == 0 and rule(levels // lanes):
                return lanes
    return 32 if levels % 32 == 0 else 16


def horizontals_second(levels: int, lanes: int) -> bool:
    """Whether the GPU path kernels walk the horizontal lines in the second pass (with the
    first pass's sums to read) rather than the first: where a lane holds at most 4 levels."""
    return levels // lanes <= 4


def path_threads(levels: int, lanes: int) -> int:
    """Threads of a GPU path block for the levels the lanes hold: 128 where each lane holds an
    even count up to 8 (the GPT bands; sgm.cu fits five such blocks on a multiprocessor), else
    256."""
    per_lane = levels // lanes
    return 128 if per_lane % 2 == 0 and per_lane <= 8 else 256


def select_threads(levels: int, lanes: int) -> int:
    """Threads of a GPU winner search block (one image row): 512 with path_threads' 128, else
    256."""
    return 512 if path_threads(levels, lanes) == 128 else 256


def slot_pair_bytes(p2: int) -> bool:
    """Whether the GPU winner search may add two slots' path bytes as bytes before it spreads
    them into halfwords: where a path cost is at most 63 (INVALID_COST + P2), so that two
    slots of two directions each stay below 256."""
    return INVALID_COST + p2 <= 63


def select_shared_bytes(levels: int, width: int, threads: int, lanes: int) -> int:
    """Shared memory of a GPU winner search block (bytes): an 8-byte record per pixel, the
    right view's best per column after ``levels`` columns left of the image, and each group
    of ``lanes`` threads' totals (halfwords, an odd number of words apart)."""
    return 4 * (3 * width + levels + threads // lanes * (((levels + 1) // 2) | 1))


def kernel_defines(levels: int, lanes: int, pair_bytes: bool) -> dict[str, int]:
    """The numbers kernels/sgm.cu is built with for ``levels`` disparity levels, ``lanes``
    threads per path line and slot pairs added as bytes (slot_pair_bytes) or not."""
    path_depth = path_levels(levels)
    return {"LEVELS": levels, "PATH_LEVELS": path_depth, "LANES": lanes,
            "SELECT_LANES": select_lanes_for(path_depth), "CENSUS_RY": CENSUS_RADIUS_Y,
            "CENSUS_RX": CENSUS_RADIUS_X, "INVALID_COST": INVALID_COST,
            "BORDER_Y": BORDER_Y, "BORDER_X": BORDER_X,
            "HORIZONTALS_SECOND": int(horizontals_second(path_depth, lanes)),
            "PATH_THREADS": path_threads(path_depth, lanes),
            "SELECT_THREADS": select_threads(path_depth, lanes),
            "SLOT_PAIR_BYTES": int(pair_bytes), "SHIFT_BITS": perspective.SHIFT_BITS}


def path_lines(height: int, width: int) -> int:
    """Path lines of one pass of the GPU matcher, on average: one straight direction of each
    axis and two diagonals."""
    return height + width + 2 * (width + height - 1)


class GpuMatcher:
    """Census SGM on the device with buffers kept per image size (see :meth:`buffers`).

    Kernels come from kernels/sgm.cu, built once per level count, lane count (``lanes``:
    more lanes per path line for images too small to fill the device) and whether P2 lets the
    winner search add slot pairs as bytes (slot_pair_bytes). Memory: 4 bytes per
    pixel and path level (path_levels) for the path costs (the sums of DIRECTION_PAIRS), plus
    12 bytes per pixel (the census words: left, right and the GPT-transformed right; the
    winner search writes over the right view's, no longer needed once transformed). A
    matcher with a ``lender`` (one that never runs at the same time, e.g. the seed pass's
    matcher beside the frame's) writes its path costs into the lender's volume where that is
    large enough. The GPT (stages/perspective.py) is one gather of the right census words
    (``gpt_census``); the path kernels take each row's first column that shows a right pixel
    as the row's shift, and ``sgm_finish`` adds kappa(u - D0, v) back. Two path launches: the
    first walks the first direction of every pair and writes, the second walks the other and
    adds in place. The path kernels keep the row shifts in shared memory and load each step's
    census words several steps ahead; the second copies the first's sums into a ring in
    shared memory ahead of its steps. Block sizes: path_threads.
    """

    def __init__(self, backend: Backend, fill_device: bool = True,
                 lender: GpuMatcher | None = None) -> None:
        if not backend.is_gpu:
            raise ConfigError("GpuMatcher needs the gpu backend")
        self.backend = backend
        self.fill_device = fill_device
        self._lender = lender
        self._buffers: dict[tuple[int, int], dict[str, Any]] = {}
        self.generation = 0
        self._kernel_sets: dict[tuple[int, int], dict[str, Any]] = {}

    def lanes(self, height: int, width: int, levels: int) -> int:
        """Lanes per path line for an image and level count (lanes_for of the levels the
        lanes hold, path_levels; with ``fill_device`` False, without doubling for small
        images)."""
        if not self.fill_device:
            return lanes_for(path_levels(levels))
        return lanes_for(path_levels(levels), path_lines(height, width),
                         self.backend.resident_threads())

    def _kernels(self, levels: int, lanes: int, p2: int) -> dict[str, Any]:
        key = (levels, lanes, slot_pair_bytes(p2))
        if key not in self._kernel_sets:
            self._kernel_sets[key] = self._build_kernels(*key)
        return self._kernel_sets[key]

    def _build_kernels(self, levels: int, lanes: int, pair_bytes: bool) -> dict[str, Any]:
        defines = kernel_defines(levels, lanes, pair_bytes)
        names = ("census_pair", "gpt_census", "sgm_paths_write", "sgm_paths_add",
                 "sgm_select", "sgm_finish")
        return {name: self.backend.kernel("sgm.cu", name, defines) for name in names} \
            | {"lanes": lanes, "select_lanes": defines["SELECT_LANES"],
               "path_threads": defines["PATH_THREADS"],
               "select_threads": defines["SELECT_THREADS"],
               "horizontals_second": bool(defines["HORIZONTALS_SECOND"])}

    def buffers(self, height: int, width: int, levels: int) -> dict[str, Any]:
        """The device buffers of an image size and level count: census (uint32 3xHxW: left,
        right, transformed right), paths (uint8 4xHxWxpath_levels(levels); levels from
        ``levels`` on are padding) and raw (float32 HxW, the right census's memory). Kept for
        one image size and reused by every frame, whatever its level count: the path volume
        holds the most levels asked for.
        Where the buffers are replaced (another size, more levels), the old ones are freed
        first and ``generation`` counts up (graphs captured with them are stale). With a
        lender, the path costs go into the lender's volume where it is large enough, else into
        one of this call's own."""
        xp = self.backend.xp
        path_depth = path_levels(levels)
        size = 4 * height * width * path_depth
        held = self._buffers.get((height, width))
        volume_needed = self._lender is None
        if held is None or (volume_needed and held["volume"].size < size):
            if self._buffers:  # another size's buffers or a smaller volume: of no use now
                self._buffers.clear()
                held = None  # their last reference, so that the allocator can free them
                self.backend.release_memory()
            held = self._buffers[height, width] = {
                "census": xp.empty((3, height, width), dtype=xp.uint32),
                "volume": xp.empty(size if volume_needed else 0, dtype=xp.uint8),
            }
            self.generation += 1
        volume = held["volume"]
        if self._lender is not None:
            lent = self._lender._buffers
            volume = next((b["volume"] for b in lent.values() if b["volume"].size >= size),
                          None)
            if volume is None:
                volume = xp.empty(size, dtype=xp.uint8)
        census = held["census"]
        return {"census": census, "raw": census[1].view(xp.float32),
                "paths": volume[:size].reshape(4, height, width, path_depth)}

    def __call__(self, left: Any, right: Any, shifts: Any, levels: int, p1: int, p2: int,
                 uniqueness_percent: int, lr_max_diff_px: int, median: bool,
                 clock: StageClock | None = None) -> Any:
        """D1 (float32 HxW px, NaN invalid) of device uint8 HxW images and the device int32
        (3, H) GPT shift table (stages/perspective.py). With a ``clock``, its stages census,
        paths, select and finish time the kernels."""
        stage = clock.stage if clock is not None else _no_stage
        height, width = left.shape
        check_settings(left.shape, levels, p1, p2)
        xp = self.backend.xp
        kernels = self._kernels(levels, self.lanes(height, width, levels), p2)
        buffers = self.buffers(height, width, levels)
        census, paths, raw = buffers["census"], buffers["paths"], buffers["raw"]
        out = xp.empty((height, width), dtype=xp.float32)
        first_columns = shifts[perspective.SHIFT_FIRST]
        i32 = np.int32
        with stage("census"):
            # blocks of 32 x 8 threads, four pixels of a row a thread
            kernels["census_pair"](((width + 127) // 128, (height + 7) // 8, 2), (32, 8, 1),
                                   (left, right, census[0], census[1], i32(height), i32(width)))
            kernels["gpt_census"](((width + 255) // 256, height), (256,),
                                  (census[1], shifts, census[2], i32(height), i32(width)))
        path_block = kernels["path_threads"]
        groups = path_block // kernels["lanes"]
        kappa_bytes = 4 * height
        diagonal_blocks = -(-(width + height - 1) // groups)
        with stage("paths"):
            # straight lines of each pass: one per row (horizontal) or per column (vertical)
            straight = (width, height) if kernels["horizontals_second"] else (height, width)
            for name, straight_lines in zip(("sgm_paths_write", "sgm_paths_add"), straight):
                walk = kernels[name]
                if kappa_bytes > 32 * 1024:  # beside at most 16 KB of the sums' rings
                    walk.max_dynamic_shared_size_bytes = kappa_bytes
                blocks = 2 * (-(-straight_lines // groups) + diagonal_blocks)
                walk((blocks,), (path_block,),
                     (census[0], census[2], first_columns, paths, i32(height), i32(width),
                      i32(p1), i32(p2)), shared_mem=kappa_bytes)
        path_depth = paths.shape[3]  # the levels the path lanes hold (path_levels)
        shared = select_shared_bytes(path_depth, width, kernels["select_threads"],
                                     kernels["select_lanes"])
        select = kernels["sgm_select"]
        if shared > 48 * 1024:
            select.max_dynamic_shared_size_bytes = shared
        with stage("select"):
            select((height,), (kernels["select_threads"],),
                   (paths, raw, i32(height), i32(width), i32(uniqueness_percent),
                    i32(lr_max_diff_px)), shared_mem=shared)
        with stage("finish"):
            kernels["sgm_finish"](((width + 31) // 32, (height + 7) // 8), (32, 8),
                                  (raw, census[0], shifts, out, i32(height), i32(width),
                                   i32(bool(median))))
        return out


@contextmanager
def _no_stage(name: str) -> Iterator[None]:
    yield
