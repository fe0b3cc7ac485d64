"""The fused road elevation map: each frame's road samples (the height below the frame's fitted
road, with its standard deviation from the disparity noise) placed by the ego-motion into a 2.5D
grid of square cells on the road, in tiles that exist only where the road was seen. Per cell,
the inverse-variance weighted mean of the views and its standard deviation; potholes are the
connected depressions of the map below a local road level, measured from all views that saw
them. The survey keeps every tile; the live node keeps a rolling window around the vehicle."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterator, Sequence

import cv2
import numba
import numpy as np

from ..calibration import StereoCalibration
from ..params import Config
from ..stages.road_model import RoadModel
from .motion import Pose2, RoadFrame, StereoOdometry

# cells per side of a tile
TILE_CELLS = 128
# the least disparity noise (px) a frame's samples are given: a road fit of a smooth rendered
# road can report less than the matcher's quantisation allows
MIN_NOISE_PX = 0.05
# a cell counts as seen by a frame whose splat gave it at least this share of a sample
VIEW_SHARE = 0.25
# rounds of the local road level that leave out the cells below the last one
LEVEL_ROUNDS = 3
# the views a cell counts up to (Tile.views is uint16)
_MOST_VIEWS = np.iinfo(np.uint16).max


@dataclass(frozen=True, eq=False)
class RoadPatch:
    """One frame's road samples on its road plane, binned to cells of ``cell_m`` m, compact
    (8 bytes a cell: the survey keeps every frame's until the drive's poses are known): their
    cell indices ``cells`` int16 (K, 2) (forward, left in the frame's road frame), the height
    below the frame's fitted road there ``depth`` float16 (K,) (m, positive into the ground)
    and its standard deviation ``sigma`` float16 (K,) (m)."""

    cells: np.ndarray
    cell_m: float
    depth: np.ndarray
    sigma: np.ndarray

    @classmethod
    def empty(cls, cell_m: float) -> "RoadPatch":
        return cls(np.zeros((0, 2), np.int16), cell_m, np.zeros(0, np.float16),
                   np.zeros(0, np.float16))

    @property
    def xy(self) -> np.ndarray:
        """The cells' centres (K, 2), float64 m (forward, left)."""
        return (self.cells.astype(np.float64) + 0.5) * self.cell_m

    def __len__(self) -> int:
        return len(self.depth)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RoadPatch) and self.cell_m == other.cell_m and all(
            np.array_equal(a, b) for a, b in ((self.cells, other.cells),
                                              (self.depth, other.depth),
                                              (self.sigma, other.sigma)))


def sample_pixels(shape: tuple[int, int], road: RoadModel, calibration: StereoCalibration,
                  cell_m: float) -> np.ndarray:
    """The pixels (flat indices row * width + column, int64) of an image of ``shape`` (H, W)
    whose road samples fill cells of ``cell_m`` m: rows and columns at the largest strides
    that keep them under half a cell apart on the road, along and across (from the road's
    disparity in each row)."""
    return sample_pixel_sets(shape, road, calibration, (cell_m,))[0]


def sample_pixel_sets(shape: tuple[int, int], road: RoadModel, calibration: StereoCalibration,
                      cells_m: Sequence[float]) -> list[np.ndarray]:
    """:func:`sample_pixels` for each cell size of ``cells_m`` (m), the road's rows worked
    out once: per row the strides, then the pixels, grouped by column stride (rising), row
    after row within a group."""
    height, width = shape
    rows_v = np.arange(height, dtype=np.float64)
    row_road = np.asarray(road.at(np, np.full(height, calibration.cx), rows_v), np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.abs(np.gradient(calibration.fb / np.where(row_road > 0, row_road, np.nan)))
    sets = []
    for cell_m in cells_m:
        with np.errstate(divide="ignore", invalid="ignore"):
            across = 0.5 * cell_m * row_road / calibration.baseline
            along = 0.5 * cell_m / slope
        column_stride = np.clip(np.nan_to_num(np.floor(across), nan=1.0), 1, 64).astype(np.int64)
        row_stride = np.clip(np.nan_to_num(np.floor(along), nan=1.0), 1, 64).astype(np.int64)
        sets.append(_strided_pixels(row_stride, column_stride, width))
    return sets


@numba.njit(cache=True)
def _strided_pixels(row_stride: np.ndarray, column_stride: np.ndarray, width: int
                    ) -> np.ndarray:
    """The flat indices of the rows v with v % row_stride[v] == 0, each at the columns 0,
    column_stride[v], 2 column_stride[v], ... below ``width``: the rows of the least column
    stride first, then those of the next, each group's rows in order."""
    kept = np.arange(len(row_stride))[np.arange(len(row_stride)) % row_stride == 0]
    count = 0
    for v in kept:
        count += (width + column_stride[v] - 1) // column_stride[v]
    pixels = np.empty(count, np.int64)
    at = 0
    for stride in np.unique(column_stride[kept]):
        for v in kept:
            if column_stride[v] == stride:
                for u in range(0, width, stride):
                    pixels[at] = v * width + u
                    at += 1
    return pixels


def near_potholes(pixels: np.ndarray, width: int,
                  boxes: list[tuple[int, int, int, int]]) -> np.ndarray:
    """Which of ``pixels`` (flat indices in an image ``width`` wide) lie near potholes: in a
    box (x0, y0, x1, y1 px, inclusive) grown on every side by its own width and height, so
    that the road around a pothole comes with it. Bool (K,)."""
    rows, cols = np.divmod(pixels, width)
    near = np.zeros(len(pixels), bool)
    for x0, y0, x1, y1 in boxes:
        grow_x, grow_y = x1 - x0 + 1, y1 - y0 + 1
        near |= ((cols >= x0 - grow_x) & (cols <= x1 + grow_x) & (rows >= y0 - grow_y)
                 & (rows <= y1 + grow_y))
    return near


def result_patches(result: Any, parts: Sequence[tuple[np.ndarray, float]], plane: RoadFrame,
                   calibration: StereoCalibration) -> list[RoadPatch]:
    """The road patches (:func:`road_patch`) of a PipelineResult, one per (pixels: flat
    indices, cell_m) of ``parts``, of the pixels of the road searched for potholes with a
    disparity: the values at every part's pixels read back from the backend together."""
    width = result.disparity.shape[1]
    pixels = np.concatenate([np.zeros(0, np.int64)] + [part for part, _ in parts])
    disparity = result.at("disparity", pixels)
    keep = result.at("searched", pixels) & (disparity > 0)
    patches, start = [], 0
    for part, cell_m in parts:
        stop = start + len(part)
        kept = keep[start:stop]
        rows, cols = np.divmod(part[kept], width)
        patches.append(road_patch(rows, cols, disparity[start:stop][kept], result.road, plane,
                                  calibration, cell_m))
        start = stop
    return patches


def road_patch(rows: np.ndarray, cols: np.ndarray, disparity: np.ndarray, road: RoadModel,
               plane: RoadFrame, calibration: StereoCalibration, cell_m: float) -> RoadPatch:
    """The road samples of pixels at ``rows``, ``cols`` with disparities ``disparity`` (px,
    > 0): each becomes a 3D point whose place on the road (forward, left in ``plane``) and
    height below ``road`` (along the road's normal) are binned into cells of ``cell_m`` m. A
    pixel's standard deviation is that of its disparity, the road fit's robust sigma (at
    least MIN_NOISE_PX), carried to a height: Z^2 / (f B) times the cosine of the ray's
    incidence on the road; a cell keeps its pixels' mean height (inverse-variance weighted)
    and their mean sigma (neighbouring pixels share the matcher's errors, so a cell of many
    pixels is no surer than one)."""
    if not len(rows):
        return RoadPatch.empty(cell_m)
    u, v = np.asarray(cols, np.float64), np.asarray(rows, np.float64)
    road_d = np.asarray(road.at(np, u, v), dtype=np.float64)
    cells, depth, sigma = _binned_samples(
        u, v, np.asarray(disparity, dtype=np.float64),
        np.ascontiguousarray(np.broadcast_to(road_d, u.shape)),
        calibration.f, calibration.cx, calibration.cy, calibration.fb,
        np.asarray(plane.origin, np.float64), np.asarray(plane.axes, np.float64),
        max(road.sigma_px, MIN_NOISE_PX), cell_m)
    return RoadPatch(cells.astype(np.int16), cell_m, depth.astype(np.float16),
                     sigma.astype(np.float16))


@numba.njit(cache=True)
def _binned_samples(u: np.ndarray, v: np.ndarray, d: np.ndarray, road_d: np.ndarray, f: float,
                    cx: float, cy: float, fb: float, origin: np.ndarray, axes: np.ndarray,
                    noise_px: float, cell_m: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """road_patch's samples, pixel by pixel in order: those with a road disparity whose ray
    meets the road from above, each as its cell (forward, left) in ``plane``'s road frame,
    its height below the road and its sigma; then per occupied cell, in the order of the
    cells (forward, then left), the inverse-variance weighted mean height and the mean sigma:
    int64 (K, 2) cells within int16's range, float64 (K,) heights and sigmas (m)."""
    count = len(u)
    normal = -axes[2]
    kept = np.zeros(count, np.bool_)
    forward = np.empty(count, np.int64)
    left = np.empty(count, np.int64)
    depth = np.empty(count)
    sigma = np.empty(count)
    for i in range(count):
        incidence = ((u[i] - cx) / f * normal[0] + (v[i] - cy) / f * normal[1] + normal[2])
        if not (road_d[i] > 0 and incidence > 0):
            continue
        z = fb / d[i]
        point = ((u[i] - cx) * z / f - origin[0], (v[i] - cy) * z / f - origin[1],
                 z - origin[2])
        ahead = point[0] * axes[0, 0] + point[1] * axes[0, 1] + point[2] * axes[0, 2]
        aside = point[0] * axes[1, 0] + point[1] * axes[1, 1] + point[2] * axes[1, 2]
        kept[i] = True
        forward[i] = math.floor(ahead / cell_m)
        left[i] = math.floor(aside / cell_m)
        depth[i] = (fb / d[i] - fb / road_d[i]) * incidence
        sigma[i] = z * z * incidence / fb * noise_px
    if not kept.any():
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
    low_f, low_l = forward[kept].min(), left[kept].min()
    span_l = left[kept].max() - low_l + 1
    bins = (forward[kept].max() - low_f + 1) * span_l
    total = np.zeros(bins)
    weighted = np.zeros(bins)
    sigmas = np.zeros(bins)
    counts = np.zeros(bins, np.int64)
    for i in range(count):
        if kept[i]:
            flat = (forward[i] - low_f) * span_l + (left[i] - low_l)
            weight = 1.0 / (sigma[i] * sigma[i])
            total[flat] += weight
            weighted[flat] += weight * depth[i]
            sigmas[flat] += sigma[i]
            counts[flat] += 1
    used = np.nonzero(total)[0]
    cells = np.empty((len(used), 2), np.int64)
    inside = np.zeros(len(used), np.bool_)
    for j in range(len(used)):
        cells[j, 0] = used[j] // span_l + low_f
        cells[j, 1] = used[j] % span_l + low_l
        inside[j] = abs(cells[j, 0]) < 32767 and abs(cells[j, 1]) < 32767
    return (cells[inside], (weighted[used] / total[used])[inside],
            (sigmas[used] / counts[used])[inside])


@dataclass
class Tile:
    """One tile of the map: per cell (TILE_CELLS x TILE_CELLS, rows along the map's y, columns
    along its x) the summed weights (1/m^2), the weighted sum of heights (m/m^2) and the views
    that saw it."""

    weight: np.ndarray
    weighted: np.ndarray
    views: np.ndarray

    @classmethod
    def new(cls) -> "Tile":
        shape = (TILE_CELLS, TILE_CELLS)
        return cls(np.zeros(shape, np.float32), np.zeros(shape, np.float32),
                   np.zeros(shape, np.uint16))


@dataclass(frozen=True)
class MapPothole:
    """A depression of the map: its centroid ``xy`` (m, map frame), its outline on the road
    (float64 (N, 2), m, map frame), its largest and mean depth below the local road level (m),
    the standard deviation of the largest (m), its area (m^2) and volume (m^3), the cells it
    covers, the most views any of them had, the map's cell size (m) and whether seen road
    surrounds it (every cell beside it was seen: a depression at the edge of the seen road may
    be the road falling away, a shoulder or a gutter whose far side no view reached)."""

    xy: tuple[float, float]
    outline: np.ndarray
    max_depth_m: float
    mean_depth_m: float
    max_depth_sigma_m: float
    area_m2: float
    volume_m3: float
    cells: int
    views: int
    cell_m: float
    enclosed: bool = True


def merged(depressions: Sequence[MapPothole]) -> MapPothole:
    """One depression of the map's ``depressions`` (pieces of one pothole): their cells
    together, the outline of their outlines' convex hull, the centroid weighted by area, the
    largest depth (and its sigma) of the deepest, the mean depth over the area, enclosed
    where each is."""
    if len(depressions) == 1:
        return depressions[0]
    area = sum(d.area_m2 for d in depressions)
    volume = sum(d.volume_m3 for d in depressions)
    deepest = max(depressions, key=lambda d: d.max_depth_m)
    xy = sum(np.asarray(d.xy) * d.area_m2 for d in depressions) / area
    hull = cv2.convexHull(np.concatenate([d.outline for d in depressions]).astype(np.float32))
    return MapPothole((float(xy[0]), float(xy[1])), hull.reshape(-1, 2).astype(np.float64),
                      deepest.max_depth_m, volume / area, deepest.max_depth_sigma_m, area,
                      volume, sum(d.cells for d in depressions),
                      max(d.views for d in depressions), depressions[0].cell_m,
                      all(d.enclosed for d in depressions))


@dataclass(frozen=True)
class MapView:
    """A block of the map: its lower corner ``origin`` (m, map frame, the corner of cell
    [0, 0]), its cell size (m) and per cell (rows along y, columns along x; float32) the fused
    height below the road (m; NaN where unseen), its standard deviation (m; NaN where unseen),
    the depth below the local road level (m; NaN where unseen), the views (uint16) and the
    pothole each cell belongs to (int32, 0 = none, else 1-based in ``potholes``)."""

    origin: tuple[float, float]
    cell_m: float
    height: np.ndarray
    sigma: np.ndarray
    depth: np.ndarray
    views: np.ndarray
    label: np.ndarray
    potholes: list[MapPothole]


def road_map(config: Config) -> "RoadMap":
    """An empty map as ``config`` sets it: cells of map_cell_m, the local level over
    local_road_radius_m, depressions deeper than threshold_noise_sigmas fused sigmas and
    delta_pd_m, potholes of min_pothole_area_m2 and min_pothole_depth_m."""
    return RoadMap(config.map_cell_m, config.local_road_radius_m,
                   config.threshold_noise_sigmas, config.delta_pd_m,
                   config.min_pothole_area_m2, config.min_pothole_depth_m)


class RoadMap:
    """The fused road elevation map, cells of ``cell_m`` m in tiles of TILE_CELLS. Potholes are
    depressions deeper than ``noise_sigmas`` times the fused standard deviation and than
    ``min_cell_depth_m`` below the local road level (the weighted mean of the cells within
    ``level_radius_m`` that are not significantly deep), of at least ``min_area_m2`` and
    ``min_depth_m`` deep on average."""

    def __init__(self, cell_m: float, level_radius_m: float, noise_sigmas: float,
                 min_cell_depth_m: float, min_area_m2: float, min_depth_m: float) -> None:
        self.cell_m = cell_m
        self.level_radius_m = level_radius_m
        self.noise_sigmas = noise_sigmas
        self.min_cell_depth_m = min_cell_depth_m
        self.min_area_m2 = min_area_m2
        self.min_depth_m = min_depth_m
        self.tiles: dict[tuple[int, int], Tile] = {}
        self._sums = np.zeros((3, TILE_CELLS * TILE_CELLS))
        self._touched = np.zeros(TILE_CELLS * TILE_CELLS, bool)

    @property
    def tile_m(self) -> float:
        return TILE_CELLS * self.cell_m

    def add(self, xy: np.ndarray, depth: np.ndarray, sigma: np.ndarray) -> None:
        """Fuse one frame's samples: ``xy`` (K, 2) places in the map frame (m), ``depth`` and
        ``sigma`` (K,) m. Each sample is splatted onto its four nearest cell centres with
        bilinear shares of its weight 1/sigma^2; per cell, the frame's shares are summed in
        float64 and added once to the tile's float32 sums (:func:`_tile_entries`,
        :func:`_fuse_into_tile`)."""
        keys, bounds, local, w, wz, share = _tile_entries(
            np.ascontiguousarray(xy, np.float64).reshape(-1, 2),
            np.ascontiguousarray(depth, np.float64), np.ascontiguousarray(sigma, np.float64),
            self.cell_m)
        for index, (tx, ty) in enumerate(keys.tolist()):
            tile = self.tiles.get((tx, ty))
            if tile is None:
                tile = self.tiles[(tx, ty)] = Tile.new()
            part = slice(bounds[index], bounds[index + 1])
            _fuse_into_tile(local[part], w[part], wz[part], share[part], tile.weight.ravel(),
                            tile.weighted.ravel(), tile.views.ravel(), VIEW_SHARE,
                            self._sums, self._touched)

    def views_at(self, xy: np.ndarray) -> np.ndarray:
        """The views (int (N,)) of the cells at ``xy`` (N, 2) m in the map frame."""
        cells = np.floor(np.asarray(xy, np.float64).reshape(-1, 2) / self.cell_m).astype(int)
        views = np.zeros(len(cells), np.int64)
        for index, (cx, cy) in enumerate(cells):
            tile = self.tiles.get((int(cx // TILE_CELLS), int(cy // TILE_CELLS)))
            if tile is not None:
                views[index] = tile.views[cy % TILE_CELLS, cx % TILE_CELLS]
        return views

    def forget_beyond(self, xy: tuple[float, float], radius_m: float) -> int:
        """Drop the tiles whose centre lies farther than ``radius_m`` from ``xy`` (m, map
        frame): the rolling window of a live map. Returns how many were dropped."""
        far = [key for key in self.tiles
               if math.hypot((key[0] + 0.5) * self.tile_m - xy[0],
                             (key[1] + 0.5) * self.tile_m - xy[1]) > radius_m]
        for key in far:
            del self.tiles[key]
        return len(far)

    def view(self, lower: tuple[int, int], upper: tuple[int, int],
             potholes_whole: bool = True) -> MapView:
        """The block of tiles ``lower`` to ``upper`` (tile indices, inclusive) with its
        potholes (those whose centroid lies in the block; with ``potholes_whole``, the block
        is read with a margin of a tile on each side so that they lie whole in it)."""
        margin = 1 if potholes_whole else 0
        span = (lower[0] - margin, lower[1] - margin, upper[0] + margin, upper[1] + margin)
        weight, weighted, views = self._mosaic(*span)
        inner = (slice(margin * TILE_CELLS, weight.shape[0] - margin * TILE_CELLS),
                 slice(margin * TILE_CELLS, weight.shape[1] - margin * TILE_CELLS))
        seen = weight > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            height = np.where(seen, weighted / weight, np.nan)
            sigma = np.where(seen, 1.0 / np.sqrt(weight), np.nan)
        depth = height - self._level(height, sigma, weight)
        label, potholes = self._segment(depth, sigma, views,
                                        (span[0] * self.tile_m, span[1] * self.tile_m), inner)
        origin = (lower[0] * self.tile_m, lower[1] * self.tile_m)
        return MapView(origin, self.cell_m, height[inner].astype(np.float32),
                       sigma[inner].astype(np.float32), depth[inner].astype(np.float32),
                       views[inner], label[inner], potholes)

    def around(self, xy: tuple[float, float], radius_m: float) -> MapView:
        """The tiles within ``radius_m`` of ``xy`` (m, map frame), with their potholes: the
        block that holds those of them the map has (an empty block where it has none)."""
        near = [key for key in self.tiles
                if math.hypot((key[0] + 0.5) * self.tile_m - xy[0],
                              (key[1] + 0.5) * self.tile_m - xy[1])
                <= radius_m + self.tile_m / math.sqrt(2)]
        if not near:
            cell = (math.floor(xy[0] / self.tile_m), math.floor(xy[1] / self.tile_m))
            return self.view(cell, cell, potholes_whole=False)
        keys = np.array(near)
        low, high = keys.min(axis=0), keys.max(axis=0)
        return self.view((int(low[0]), int(low[1])), (int(high[0]), int(high[1])))

    def tile_views(self) -> Iterator[tuple[tuple[int, int], MapView]]:
        """Each tile of the map (in row order) with its potholes: every pothole of the map
        once, memory of nine tiles at a time."""
        for key in sorted(self.tiles, key=lambda k: (k[1], k[0])):
            yield key, self.view(key, key)

    def potholes(self) -> list[MapPothole]:
        """Every pothole of the map."""
        return [p for _, view in self.tile_views() for p in view.potholes]

    def _mosaic(self, x0: int, y0: int, x1: int, y1: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        shape = ((y1 - y0 + 1) * TILE_CELLS, (x1 - x0 + 1) * TILE_CELLS)
        weight, weighted = np.zeros(shape), np.zeros(shape)
        views = np.zeros(shape, np.uint16)
        for (tx, ty), tile in self.tiles.items():
            if x0 <= tx <= x1 and y0 <= ty <= y1:
                rows = slice((ty - y0) * TILE_CELLS, (ty - y0 + 1) * TILE_CELLS)
                cols = slice((tx - x0) * TILE_CELLS, (tx - x0 + 1) * TILE_CELLS)
                weight[rows, cols], weighted[rows, cols] = tile.weight, tile.weighted
                views[rows, cols] = tile.views
        return weight, weighted, views

    def _level(self, height: np.ndarray, sigma: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """The local road level (m) of each cell: a plane fitted, weighted, to the heights of
        the road's cells within level_radius_m (a square window), taken at the cell (a plane,
        so that a slope or camber of the road and the edge of the seen road do not bias it).
        The road's cells are first all seen cells, then LEVEL_ROUNDS times those not
        significantly below the last level. NaN where the window has no road cell."""
        seen = weight > 0
        road = seen
        for _ in range(LEVEL_ROUNDS):
            level = self._plane(height, weight, road)
            road = seen & ~(height - level > self.noise_sigmas * sigma)
        return level

    def _plane(self, height: np.ndarray, weight: np.ndarray, road: np.ndarray) -> np.ndarray:
        """The weighted plane of the ``road`` cells' heights in each cell's window, at the
        cell; their weighted mean where they lie on a line."""
        side = 2 * max(1, round(self.level_radius_m / self.cell_m)) + 1
        w = np.where(road, weight, 0.0)
        z = np.where(road, height, 0.0)
        rows, cols = np.indices(height.shape, dtype=np.float64)
        rows -= height.shape[0] / 2
        cols -= height.shape[1] / 2

        def box(values: np.ndarray) -> np.ndarray:
            return cv2.boxFilter(values, cv2.CV_64F, (side, side), normalize=False,
                                 borderType=cv2.BORDER_CONSTANT)

        s, sx, sy = box(w), box(w * cols), box(w * rows)
        sxx, sxy, syy = box(w * cols * cols), box(w * cols * rows), box(w * rows * rows)
        sz, sxz, syz = box(w * z), box(w * cols * z), box(w * rows * z)
        # moments about each cell itself: the plane's value there is its constant term
        sx_c, sy_c = sx - cols * s, sy - rows * s
        sxx_c = sxx - 2 * cols * sx + cols * cols * s
        syy_c = syy - 2 * rows * sy + rows * rows * s
        sxy_c = sxy - cols * sy - rows * sx + cols * rows * s
        sxz_c, syz_c = sxz - cols * sz, syz - rows * sz
        with np.errstate(divide="ignore", invalid="ignore"):
            mean = np.where(s > 0, sz / s, np.nan)
            # the determinant of the cells' covariance (cells^4) times s^2: a plane needs
            # cells that spread over at least about a cell each way
            spread = ((sxx_c - sx_c * sx_c / s) * (syy_c - sy_c * sy_c / s)
                      - (sxy_c - sx_c * sy_c / s) ** 2)
            planar = (s > 0) & (spread > 0.25 * s * s)
            # the plane's constant term by Cramer's rule on the symmetric normal equations
            minor = sxx_c * syy_c - sxy_c * sxy_c
            determinant = (s * minor - sx_c * (sx_c * syy_c - sy_c * sxy_c)
                           + sy_c * (sx_c * sxy_c - sy_c * sxx_c))
            constant = (sz * minor - sx_c * (sxz_c * syy_c - sxy_c * syz_c)
                        + sy_c * (sxz_c * sxy_c - sxx_c * syz_c))
            level = np.where(planar, constant / determinant, mean)
        return level

    def _segment(self, depth: np.ndarray, sigma: np.ndarray, views: np.ndarray,
                 origin: tuple[float, float], inner: tuple[slice, slice]
                 ) -> tuple[np.ndarray, list[MapPothole]]:
        deep = np.isfinite(depth) & (depth > self.noise_sigmas * sigma) \
            & (depth > self.min_cell_depth_m)
        count, labels, stats, centroids = cv2.connectedComponentsWithStats(
            deep.astype(np.uint8), connectivity=8)
        cell_area = self.cell_m * self.cell_m
        kept = np.zeros(count, np.int32)
        potholes: list[MapPothole] = []
        if count > 1:
            flat = labels.ravel()
            values = np.where(deep, depth, 0.0).ravel()
            sums = np.bincount(flat, values, count)
            deepest = np.full(count, -np.inf)
            np.maximum.at(deepest, flat, values)
            for index in range(1, count):
                cx, cy = centroids[index]
                cells = int(stats[index, cv2.CC_STAT_AREA])
                inside = (inner[0].start <= cy < inner[0].stop
                          and inner[1].start <= cx < inner[1].stop)
                if (not inside or cells * cell_area < self.min_area_m2
                        or sums[index] / cells < self.min_depth_m):
                    continue
                mine = labels == index
                beside = cv2.dilate(mine.astype(np.uint8), np.ones((3, 3), np.uint8)) > mine
                at = np.unravel_index(np.argmax(np.where(mine, depth, -np.inf)), depth.shape)
                potholes.append(MapPothole(
                    (origin[0] + (cx + 0.5) * self.cell_m, origin[1] + (cy + 0.5) * self.cell_m),
                    self._outline(mine, origin), float(deepest[index]),
                    float(sums[index] / cells), float(sigma[at]), cells * cell_area,
                    float(sums[index] * cell_area), cells, int(views[mine].max()),
                    self.cell_m, bool(np.isfinite(depth[beside]).all())))
                kept[index] = len(potholes)
        return kept[labels], potholes

    def _outline(self, mask: np.ndarray, origin: tuple[float, float]) -> np.ndarray:
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE)
        largest = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
        return np.asarray(origin) + (largest + 0.5) * self.cell_m


def compile_map_kernels() -> None:
    """The map's fusion kernels (Numba's) compiled, or loaded from Numba's cache, now: set-up
    and the live node's start call it, so that no frame waits for the compiler."""
    road_map(Config()).add(np.full((1, 2), 0.5), np.zeros(1), np.ones(1))


@numba.njit(cache=True)
def _tile_entries(xy: np.ndarray, depth: np.ndarray, sigma: np.ndarray, cell_m: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                             np.ndarray]:
    """The bilinear splat of the samples at ``xy`` (K, 2 m) with heights ``depth`` and
    standard deviations ``sigma`` (K,) m, float64, that are finite with sigma > 0: four entries
    a sample (its cell corners (0, 0), (1, 0), (0, 1), (1, 1) about the cell centre below it,
    every sample's first corner first), grouped by the tile they fall in, tiles in the order
    first met, entries in their order within a tile. Returns the tiles' (tx, ty) int64 (T, 2),
    their entries' bounds int64 (T + 1,) and per entry its cell in the tile (row-major, int64),
    its weight share * 1/sigma^2 (1/m^2), that times the height (m/m^2) and its share."""
    good = np.zeros(len(depth), np.int64)
    count = 0
    for i in range(len(depth)):
        if (np.isfinite(depth[i]) and np.isfinite(sigma[i]) and sigma[i] > 0
                and np.isfinite(xy[i, 0]) and np.isfinite(xy[i, 1])):
            good[count] = i
            count += 1
    entries = 4 * count
    cx = np.empty(entries, np.int64)
    cy = np.empty(entries, np.int64)
    share = np.empty(entries)
    w = np.empty(entries)
    wz = np.empty(entries)
    for n in range(count):
        i = good[n]
        gx, gy = xy[i, 0] / cell_m - 0.5, xy[i, 1] / cell_m - 0.5
        bx, by = np.floor(gx), np.floor(gy)
        fx, fy = gx - bx, gy - by
        weight = 1.0 / (sigma[i] * sigma[i])
        for corner in range(4):
            dx, dy = corner % 2, corner // 2
            e = corner * count + n
            cx[e], cy[e] = np.int64(bx) + dx, np.int64(by) + dy
            share[e] = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
            w[e] = share[e] * weight
            wz[e] = w[e] * depth[i]
    seen = np.empty((entries, 2), np.int64)
    slot = np.empty(entries, np.int64)
    local = np.empty(entries, np.int64)
    sizes = np.zeros(entries + 1, np.int64)
    tiles, found = 0, -1
    for e in range(entries):
        tx, ty = cx[e] // TILE_CELLS, cy[e] // TILE_CELLS
        if found < 0 or tx != seen[found, 0] or ty != seen[found, 1]:
            found = 0
            while found < tiles and (seen[found, 0] != tx or seen[found, 1] != ty):
                found += 1
            if found == tiles:
                seen[found, 0], seen[found, 1] = tx, ty
                tiles += 1
        slot[e] = found
        local[e] = (cy[e] - ty * TILE_CELLS) * TILE_CELLS + (cx[e] - tx * TILE_CELLS)
        sizes[found + 1] += 1
    bounds = np.cumsum(sizes[:tiles + 1])
    at = bounds[:tiles].copy()
    order = np.empty(entries, np.int64)
    for e in range(entries):
        order[at[slot[e]]] = e
        at[slot[e]] += 1
    return seen[:tiles], bounds, local[order], w[order], wz[order], share[order]


@numba.njit(cache=True)
def _fuse_into_tile(local: np.ndarray, w: np.ndarray, wz: np.ndarray, share: np.ndarray,
                    weight: np.ndarray, weighted: np.ndarray, views: np.ndarray,
                    view_share: float, sums: np.ndarray, touched: np.ndarray) -> None:
    """One frame's entries of one tile (:func:`_tile_entries`) fused into the tile's flat
    float32 sums ``weight`` and ``weighted`` and uint16 ``views`` (TILE_CELLS^2,): per cell,
    the entries' float64 sums, in entry order, each added once to the float32 sum; a view
    more where the shares sum to ``view_share`` or more (at most the uint16 maximum).
    ``sums`` float64 (3, TILE_CELLS^2) and ``touched`` bool (TILE_CELLS^2,): scratch, zero on
    entry and left zero."""
    touched_cells = np.empty(len(local), np.int64)
    count = 0
    for e in range(len(local)):
        cell = local[e]
        if not touched[cell]:
            touched[cell] = True
            touched_cells[count] = cell
            count += 1
        sums[0, cell] += w[e]
        sums[1, cell] += wz[e]
        sums[2, cell] += share[e]
    for n in range(count):
        cell = touched_cells[n]
        weight[cell] = np.float32(np.float64(weight[cell]) + sums[0, cell])
        weighted[cell] = np.float32(np.float64(weighted[cell]) + sums[1, cell])
        if sums[2, cell] >= view_share and views[cell] < _MOST_VIEWS:
            views[cell] += 1
        sums[:, cell] = 0.0
        touched[cell] = False


class LiveMap:
    """The road map around a moving camera, for the live node: each frame's road samples
    placed by the given pose (odometry) or, without one, by our stereo visual odometry chained
    from the first frame; the road farther than ``map_radius_m`` forgotten; a view of the map
    around the camera due at most ``map_publish_rate_hz`` times a second."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.roadmap = road_map(config)
        self.odometry = StereoOdometry()
        self.pose = Pose2()
        self.last_view_s = -math.inf

    def add(self, result: Any, plane: RoadFrame, calibration: StereoCalibration,
            gray: np.ndarray, pose: Pose2 | None = None) -> Pose2:
        """Fuse one frame (its PipelineResult, road frame and HxW grey left image) at ``pose``
        (its road frame in the map frame), or at the visual odometry's pose where None; returns
        the pose used."""
        if pose is None:
            step = self.odometry.step(gray, result.host("disparity"), plane, calibration)
            pose = self.pose.compose(step) if step is not None else self.pose
        self.pose = pose
        cell_m = self.config.map_cell_m
        pixels = sample_pixels(result.disparity.shape, result.road, calibration, cell_m)
        patch, = result_patches(result, [(pixels, cell_m)], plane, calibration)
        self.roadmap.add(pose.apply(patch.xy), patch.depth, patch.sigma)
        self.roadmap.forget_beyond((pose.x, pose.y),
                                   self.config.map_radius_m + self.roadmap.tile_m)
        return pose

    def due(self, now_s: float) -> MapView | None:
        """The map within map_radius_m of the camera when a view is due at ``now_s`` (s, a
        monotonic clock), else None."""
        if now_s - self.last_view_s < 1.0 / self.config.map_publish_rate_hz:
            return None
        self.last_view_s = now_s
        return self.roadmap.around((self.pose.x, self.pose.y), self.config.map_radius_m)
