"""Per-pothole 3D: points, depth below the road, area on the road, volume, centroid."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Sequence

import numpy as np

from ..backend import Backend, to_host
from ..calibration import StereoCalibration
from .components import FarCorners, in_far_corner, relabel
from .refine import SMOOTHING_PX
from .road_model import ROAD_DEFINES, RoadModel, device_params, road_plane

# A surface patch seen at a grazing angle (sine) under GRAZING_PERCENT % of the road's there is
# seen edge-on: the floor behind it is hidden (surface_patches). Its depth is taken BLEND_PERCENT
# % of the way from the ray past the near rim to the floor seen beyond it, within ROWS rows:
# those the pipeline's smoothing spreads a near rim's step over.
HIDDEN_FLOOR_CONSTANTS = {"HIDDEN_FLOOR_GRAZING_PERCENT": 50, "HIDDEN_FLOOR_BLEND_PERCENT": 50,
                          "HIDDEN_FLOOR_ROWS": SMOOTHING_PX}
HIDDEN_FLOOR_GRAZING = HIDDEN_FLOOR_CONSTANTS["HIDDEN_FLOOR_GRAZING_PERCENT"] / 100.0
HIDDEN_FLOOR_BLEND = HIDDEN_FLOOR_CONSTANTS["HIDDEN_FLOOR_BLEND_PERCENT"] / 100.0
HIDDEN_FLOOR_ROWS = HIDDEN_FLOOR_CONSTANTS["HIDDEN_FLOOR_ROWS"]


class Sum(IntEnum):
    """The columns of :func:`measure`'s per-label float64 sums (kernels/measure.cu reads them
    as SUM_<name>): pixels, footprint area, valid area (pixels with a depth), floor area
    (:func:`surface_patches`), depth x floor area, x, y, z x valid area, pixels in a far
    corner region, pixels of significant superpixels."""

    PIXELS = 0
    AREA = 1
    VALID_AREA = 2
    FLOOR = 3
    DEPTH_FLOOR = 4
    X = 5
    Y = 6
    Z = 7
    CORNER = 8
    SIGNIFICANT = 9


class Extreme(IntEnum):
    """The columns of :func:`measure`'s per-label int32 extremes (kernels/measure.cu:
    EXTREME_<name>): largest depth (order-preserving float32 bits), u min, v min, u max, v
    max."""

    LARGEST_DEPTH = 0
    U_MIN = 1
    V_MIN = 2
    U_MAX = 3
    V_MAX = 4


@dataclass(frozen=True)
class Pothole:
    """One pothole. Lengths in metres in the left optical frame (x right, y down, z forward);
    ``bbox_px`` is (u0, v0, u1, v1) inclusive: every pixel of the label lies in it."""

    label: int
    pixels: int
    area_m2: float
    max_depth_m: float
    mean_depth_m: float
    volume_m3: float
    centroid_cam_m: tuple[float, float, float]
    bbox_px: tuple[int, int, int, int]

    def as_dict(self) -> dict:
        return {
            "label": self.label, "pixels": self.pixels, "area_m2": self.area_m2,
            "max_depth_m": self.max_depth_m, "mean_depth_m": self.mean_depth_m,
            "volume_m3": self.volume_m3, "centroid_cam_m": list(self.centroid_cam_m),
            "bbox_px": list(self.bbox_px),
        }

    def window(self, shape: tuple[int, ...]) -> tuple[slice, slice]:
        """Rows and columns of an image of ``shape`` (H, W, ...) that hold this pothole: its
        bounding box and one pixel more on each side where the image has it (an outline
        traced there is the one traced over the whole image)."""
        u0, v0, u1, v1 = self.bbox_px
        return (slice(max(v0 - 1, 0), min(v1 + 2, shape[0])),
                slice(max(u0 - 1, 0), min(u1 + 2, shape[1])))


def window_of(potholes: Sequence[Pothole], shape: tuple[int, ...]) -> tuple[slice, slice]:
    """Rows and columns of an image of ``shape`` (H, W, ...) that hold all of ``potholes``:
    the box around their windows (Pothole.window); empty where there are none."""
    if not potholes:
        return slice(0, 0), slice(0, 0)
    windows = [pothole.window(shape) for pothole in potholes]
    return (slice(min(rows.start for rows, _ in windows), max(rows.stop for rows, _ in windows)),
            slice(min(columns.start for _, columns in windows),
                  max(columns.stop for _, columns in windows)))


def road_normal(model: RoadModel, calibration: StereoCalibration) -> np.ndarray:
    """Unit normal (3,) of the plane of the model's linear part, pointing away from the camera.

    Road disparity alpha + beta u + gamma v = f B / Z is the plane n . P = f B with
    n = (beta f, gamma f, alpha + beta cx + gamma cy)."""
    normal = np.array(road_plane(np, model.kernel_params(), calibration)[0], dtype=np.float64)
    return normal / np.linalg.norm(normal)


def depth_below_road(xp: Any, u: Any, v: Any, disparity: Any, model: RoadModel,
                     calibration: StereoCalibration) -> tuple[Any, Any]:
    """Depth below the road (m, >= 0 into the ground; NaN where the disparity is invalid) and
    footprint area on the road (m^2) of pixels at columns ``u``, rows ``v`` (px) with
    ``disparity`` (px); arrays of one shape, float32 results. Only a pixel whose ray meets the
    road plane in front of the camera has a footprint (else 0) and a depth (else NaN)."""
    normal = road_normal(model, calibration)
    f = calibration.f
    u = u.astype(xp.float32)
    v = v.astype(xp.float32)
    incidence = normal[0] * (u - calibration.cx) / f + normal[1] * (v - calibration.cy) / f \
        + normal[2]
    road_d = model.at(xp, u, v)
    on_road = (road_d > 0) & (incidence > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        road_z = calibration.fb / road_d
        depth = xp.maximum(((calibration.fb / disparity - road_z) * incidence)
                           .astype(xp.float32), 0)
        footprint = (road_z * road_z / (f * f * incidence)).astype(xp.float32)
    depth = xp.where(on_road & (disparity > 0), depth, xp.float32(xp.nan))
    return depth, xp.where(on_road, footprint, xp.float32(0))


def surface_patches(xp: Any, u: Any, v: Any, disparity: Any, normal: np.ndarray,
                    calibration: StereoCalibration) -> tuple[Any, Any]:
    """The area (m^2, float64) that the surface seen by pixels at columns ``u``, rows ``v``
    (int arrays of one shape) covers on the road plane: n . (dQ/du x dQ/dv) of the 3D points Q
    of the HxW float32 ``disparity`` (px, NaN invalid), central differences, ``normal`` the
    road's unit normal (road_normal). A floor parallel to the road covers what the road
    would; a wall seen edge-on covers little; a fold (an occlusion edge) and a pixel with a
    neighbour off the image or without a disparity cover nothing (0). Also bool: whether the
    patch is seen edge-on, at a grazing angle (its sine) under HIDDEN_FLOOR_GRAZING of the
    road's there: its points run along the rays, as where the pipeline's smoothing spreads the
    step from a near rim to the floor beyond what it hides."""
    height, width = disparity.shape
    inside = (u > 0) & (u < width - 1) & (v > 0) & (v < height - 1)
    cu, cv = xp.clip(u, 1, width - 2), xp.clip(v, 1, height - 2)

    def point(du: int, dv: int) -> tuple[Any, Any, Any]:
        d = disparity[cv + dv, cu + du].astype(xp.float64)
        return calibration.back_project(cu + du, cv + dv, xp.where(d > 0, d, xp.nan))

    with np.errstate(divide="ignore", invalid="ignore"):
        right, left, below, above = point(1, 0), point(-1, 0), point(0, 1), point(0, -1)
        along_u = [0.5 * (a - b) for a, b in zip(right, left)]
        along_v = [0.5 * (a - b) for a, b in zip(below, above)]
        cross = (along_u[1] * along_v[2] - along_u[2] * along_v[1],
                 along_u[2] * along_v[0] - along_u[0] * along_v[2],
                 along_u[0] * along_v[1] - along_u[1] * along_v[0])
        area = normal[0] * cross[0] + normal[1] * cross[1] + normal[2] * cross[2]
        ray = ((cu - calibration.cx) / calibration.f, (cv - calibration.cy) / calibration.f)
        seen = xp.abs(cross[0] * ray[0] + cross[1] * ray[1] + cross[2])
        incidence = normal[0] * ray[0] + normal[1] * ray[1] + normal[2]
        size = xp.sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2])
        edge_on = inside & (seen < HIDDEN_FLOOR_GRAZING * incidence * size)
    return xp.where(inside & xp.isfinite(area) & (area > 0), area, 0.0), edge_on


def hidden_floor_depth(xp: Any, labels: Any, rows: Any, cols: Any, label: Any, depth: Any,
                       edge_on: Any, disparity: Any, model: RoadModel,
                       calibration: StereoCalibration) -> Any:
    """The depth (m) that a pothole's volume takes at labelled pixels ``rows``, ``cols`` of
    label ``label`` with finite ``depth`` (depth_below_road): where the pixel's patch is seen
    edge-on (``edge_on``, :func:`surface_patches`) the floor behind it is hidden; it lies
    between the ray past the near rim (the depth seen, the least it can be) and the deepest
    floor the camera sees beyond it (a flat floor), within HIDDEN_FLOOR_ROWS - 1 rows farther
    up the column in the same pothole, and is taken HIDDEN_FLOOR_BLEND of the way from the one
    to the other. Elsewhere ``depth``. float32 arrays of one shape (labelled pixels);
    ``labels`` int32 HxW, ``disparity`` float32 HxW px."""
    if not bool(edge_on.any()):
        return depth
    at = xp.nonzero(edge_on)[0]
    beyond = xp.full(at.shape, -xp.inf, dtype=xp.float32)
    for step in range(1, HIDDEN_FLOOR_ROWS):
        row = xp.maximum(rows[at] - step, 0)
        same = (rows[at] >= step) & (labels[row, cols[at]] == label[at])
        seen, _ = depth_below_road(xp, cols[at], row, disparity[row, cols[at]], model,
                                   calibration)
        beyond = xp.where(same & xp.isfinite(seen), xp.maximum(beyond, seen), beyond)
    out = depth.copy()
    out[at] += HIDDEN_FLOOR_BLEND * xp.maximum(beyond - depth[at], 0)
    return out


def under_opening(xp: Any, labels: Any, rows: Any, cols: Any, label: Any, depth: Any,
                  disparity: Any, normal: np.ndarray, calibration: StereoCalibration) -> Any:
    """Whether the surface points of labelled pixels ``rows``, ``cols`` of label ``label``
    with ``depth`` (depth_below_road, m) lie under their pothole's opening: the camera sees a
    point below the road only through the opening, so the road point right above it (along
    the road's unit ``normal``) lies inside the pothole's outline: its pixel is labelled
    ``label``. Where that pixel lies off the image, the pixel where the image step from
    the point's pixel towards it leaves the image stands for it: the pothole must reach the
    image's edge there. A point deeper than the opening allows is a mismatch. Bool array of
    the shape of ``rows``; NaN depths give True. ``labels`` int32 HxW, ``disparity`` float32
    HxW px."""
    height, width = labels.shape
    u0, v0 = cols.astype(xp.float64), rows.astype(xp.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y, z = calibration.back_project(u0, v0, disparity[rows, cols].astype(xp.float64))
        lift = xp.nan_to_num(depth.astype(xp.float64))
        x, y, z = x - lift * normal[0], y - lift * normal[1], z - lift * normal[2]
        du = calibration.f * x / z + calibration.cx - u0
        dv = calibration.f * y / z + calibration.cy - v0
        reach = xp.minimum(
            xp.where(du > 0, (width - 1 - u0) / du, xp.where(du < 0, -u0 / du, xp.inf)),
            xp.where(dv > 0, (height - 1 - v0) / dv, xp.where(dv < 0, -v0 / dv, xp.inf)))
        step = xp.clip(reach, 0.0, 1.0)
    known = xp.isfinite(depth) & (z > 0) & xp.isfinite(du) & xp.isfinite(dv)
    at_u = xp.clip(xp.rint(u0 + xp.where(known, step * du, 0)), 0, width - 1).astype(xp.int64)
    at_v = xp.clip(xp.rint(v0 + xp.where(known, step * dv, 0)), 0, height - 1).astype(xp.int64)
    return ~known | (labels[at_v, at_u] == label)


def measure(backend: Backend, labels: Any, capacity: int, disparity: Any,
            road: RoadModel | Any, calibration: StereoCalibration, sums: Any = None,
            extremes: Any = None, corners: FarCorners | None = None,
            superpixel_labels: Any = None, significant: Any = None) -> tuple[Any, Any]:
    """The measure stage: per-label sums of labels 1..capacity of the int32 HxW ``labels``
    with the HxW float32 disparity D1 (px, NaN invalid), nothing read back: backend float64
    (capacity + 1, MEASURE_SUMS) sums (columns :class:`Sum`; pixels in a far corner region of
    ``corners``, none where not given; pixels of superpixels (int32 HxW
    ``superpixel_labels``) flagged in the bool (n,) ``significant``, none where not given) and
    int32 (capacity + 1, MEASURE_EXTREMES) extremes (columns :class:`Extreme`; the largest
    depth of the points under the opening, :func:`under_opening`); row 0 unused; written into
    ``sums`` and ``extremes`` where given. The mean depth is taken over the
    floor that the camera sees, each point weighted by the area it covers on the road, so
    that a far wall seen at grazing angles does not make a pothole shallow; where the near rim
    hides the floor, at the depth :func:`hidden_floor_depth` estimates. ``road``: a
    RoadModel, or on the GPU also road_model.device_params. On the GPU one pass of
    kernels/measure.cu over the label image (per-warp sums, atomics per label)."""
    if backend.is_gpu:
        return _measure_on_device(backend, labels, capacity, disparity,
                                  device_params(backend, road), calibration, sums, extremes,
                                  corners, superpixel_labels, significant)
    xp = backend.xp
    sums = np.zeros((capacity + 1, MEASURE_SUMS)) if sums is None else sums
    extremes = np.zeros((capacity + 1, MEASURE_EXTREMES), np.int32) if extremes is None \
        else extremes
    rows, cols = xp.nonzero((labels > 0) & (labels <= capacity))
    if rows.size == 0:
        return sums, extremes
    label = labels[rows, cols]
    count = int(label.max())
    pixel_disparity = disparity[rows, cols]
    depth, footprint = depth_below_road(xp, cols, rows, pixel_disparity, road, calibration)
    valid = xp.isfinite(depth)
    floor, edge_on = surface_patches(xp, cols, rows, disparity, road_normal(road, calibration),
                                     calibration)
    floor = xp.where(valid, floor, 0.0)
    volume_depth = hidden_floor_depth(xp, labels, rows, cols, label, depth, edge_on & valid,
                                      disparity, road, calibration)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y, z = calibration.back_project(cols, rows, pixel_disparity)

    def total(weights: Any) -> Any:
        return xp.bincount(label, weights=weights.astype(xp.float64), minlength=count + 1)[1:]

    none = xp.zeros(rows.shape, dtype=bool)
    cornered = none if corners is None else in_far_corner(corners, rows, cols)
    flagged = none if significant is None else significant[superpixel_labels[rows, cols]]

    present = np.bincount(label, minlength=count + 1)[1:] > 0

    def extreme(reduction: np.ufunc, values: np.ndarray) -> np.ndarray:
        """Per label 1..count the least (np.minimum) or greatest (np.maximum) of ``values`` at
        its pixels, 0 for a label without any (as ndimage.minimum and maximum give)."""
        kind = np.finfo if values.dtype.kind == "f" else np.iinfo
        start = kind(values.dtype).max if reduction is np.minimum else kind(values.dtype).min
        found = np.full(count + 1, start, dtype=values.dtype)
        reduction.at(found, label, values)
        return np.where(present, found[1:], 0)

    columns = {
        Sum.PIXELS: xp.ones_like(footprint), Sum.AREA: footprint,
        Sum.VALID_AREA: xp.where(valid, footprint, 0),
        Sum.FLOOR: floor, Sum.DEPTH_FLOOR: xp.where(valid, volume_depth, 0) * floor,
        Sum.X: xp.where(valid, x * footprint, 0), Sum.Y: xp.where(valid, y * footprint, 0),
        Sum.Z: xp.where(valid, z * footprint, 0), Sum.CORNER: cornered,
        Sum.SIGNIFICANT: flagged}
    sums[1:count + 1] = xp.stack([total(columns[column]) for column in Sum], axis=1)
    opening = under_opening(xp, labels, rows, cols, label, depth, disparity,
                            road_normal(road, calibration), calibration)
    largest = extreme(np.maximum, xp.where(valid & opening, depth, -xp.inf)
                      ).astype(xp.float32)
    extremes[1:count + 1, Extreme.LARGEST_DEPTH] = _ordered_bits(largest.view(xp.int32))
    for column, reduction, values in ((Extreme.U_MIN, np.minimum, cols),
                                      (Extreme.V_MIN, np.minimum, rows),
                                      (Extreme.U_MAX, np.maximum, cols),
                                      (Extreme.V_MAX, np.maximum, rows)):
        extremes[1:count + 1, column] = extreme(reduction, values)
    return sums, extremes


def _ordered_bits(bits: Any) -> Any:
    """float32 bit patterns (int32) to integers that order as the floats do, and back."""
    return np.where(bits >= 0, bits, bits ^ np.int32(0x7FFFFFFF))


def measure_potholes(backend: Backend, labels: Any, count: int, disparity: Any, model: RoadModel,
                     calibration: StereoCalibration) -> list[Pothole]:
    """Potholes 1..count of :func:`measure`, read back."""
    if count == 0:
        return []
    sums, extremes = measure(backend, labels, count, disparity, model, calibration)
    return potholes_from_sums(to_host(sums)[1:], to_host(extremes)[1:])


def _potholes_from_table(table: np.ndarray) -> list[Pothole]:
    """Potholes from the (count, 13) table: pixels, area, valid area, floor area, depth x
    floor area, largest depth, x, y, z x valid area, u min, v min, u max, v max."""
    potholes = []
    for label_id, row in enumerate(table, start=1):
        pixels, area, area_valid, floor, depth_floor, max_depth = row[:6]
        mean_depth = depth_floor / floor if floor > 0 else float("nan")
        centroid = tuple(float(c / area_valid) if area_valid > 0 else float("nan")
                         for c in row[6:9])
        potholes.append(Pothole(
            label=label_id, pixels=int(pixels), area_m2=float(area),
            max_depth_m=float(max_depth) if np.isfinite(max_depth) else float("nan"),
            mean_depth_m=float(mean_depth), volume_m3=float(mean_depth * area),
            centroid_cam_m=centroid,  # type: ignore[arg-type]
            bbox_px=tuple(int(c) for c in row[9:13]),  # type: ignore[arg-type]
        ))
    return potholes


def potholes_from_sums(sums: np.ndarray, extremes: np.ndarray) -> list[Pothole]:
    """Potholes 1..k from host copies of rows 1..k of :func:`measure`'s sums
    (float64 (k, MEASURE_SUMS)) and extremes (int32 (k, MEASURE_EXTREMES))."""
    largest = _ordered_bits(extremes[:, Extreme.LARGEST_DEPTH]).astype(np.int32).view(np.float32)
    return _potholes_from_table(np.column_stack(
        [sums[:, [Sum.PIXELS, Sum.AREA, Sum.VALID_AREA, Sum.FLOOR, Sum.DEPTH_FLOOR]],
         largest.astype(np.float64), sums[:, [Sum.X, Sum.Y, Sum.Z]],
         extremes[:, [Extreme.U_MIN, Extreme.V_MIN, Extreme.U_MAX, Extreme.V_MAX]]
         .astype(np.float64)]))


# per-label float64 sums and int32 extremes of measure (kernels/measure.cu), its block size
MEASURE_SUMS = len(Sum)
MEASURE_EXTREMES = len(Extreme)
MEASURE_THREADS = 256
_MEASURE_DEFINES = {"SUMS": MEASURE_SUMS, "EXTREMES": MEASURE_EXTREMES,
                    "THREADS": MEASURE_THREADS, **{f"SUM_{c.name}": int(c) for c in Sum},
                    **{f"EXTREME_{c.name}": int(c) for c in Extreme},
                    **HIDDEN_FLOOR_CONSTANTS, **ROAD_DEFINES}


def _measure_on_device(backend: Backend, labels: Any, capacity: int, disparity: Any,
                       road_params: Any, calibration: StereoCalibration, sums: Any,
                       extremes: Any, corners: FarCorners | None, superpixel_labels: Any,
                       significant: Any) -> tuple[Any, Any]:
    """measure on the GPU (road_params: road_model.device_params)."""
    xp = backend.xp
    height, width = labels.shape
    if corners is None:
        spans = xp.zeros(1, dtype=xp.int32)
        corners = FarCorners(spans, spans, 0)
    has_significant = significant is not None
    if not has_significant:
        superpixel_labels = xp.zeros(1, dtype=xp.int32)
        significant = xp.zeros(1, dtype=xp.bool_)
    if sums is None:
        sums = xp.empty((capacity + 1, MEASURE_SUMS), dtype=xp.float64)
    if extremes is None:
        extremes = xp.empty((capacity + 1, MEASURE_EXTREMES), dtype=xp.int32)
    _kernel(backend, "measure_reset")(
        ((capacity + 256) // 256,), (256,), (sums, extremes, np.int32(capacity)))
    pixels = height * width
    f64 = np.float64
    _kernel(backend, "measure_potholes")(
        (-(-pixels // MEASURE_THREADS),), (MEASURE_THREADS,),
        (xp.ascontiguousarray(labels, dtype=xp.int32),
         xp.ascontiguousarray(disparity, dtype=xp.float32), np.int32(height), np.int32(width),
         f64(calibration.f), f64(calibration.cx), f64(calibration.cy), f64(calibration.fb),
         road_params, corners.first, corners.last, np.int32(corners.side),
         xp.ascontiguousarray(superpixel_labels, dtype=xp.int32),
         xp.ascontiguousarray(significant, dtype=xp.bool_),
         np.int32(has_significant), sums, extremes))
    return sums, extremes


def area_filter(backend: Backend, labels: Any, sums: Any, kept: Any, capacity: int,
                min_area_m2: float, kept_after: Any, min_depth_m: float = 0.0,
                max_depth_m: float = math.inf) -> Any:
    """Labels 1..kept (backend int32 (1,)) of the int32 HxW ``labels`` whose footprint area in
    :func:`measure`'s ``sums`` reaches ``min_area_m2``, whose mean depth lies in
    [``min_depth_m``, ``max_depth_m``] and that make a report (:func:`reportable`),
    renumbered 1..m in order (in place on the GPU: a one-thread kernel and a gather, nothing
    read back); writes m to the backend int32 (1,) ``kept_after``. Returns the labels.
    :func:`keep_large` keeps the same rows."""
    xp = backend.xp
    if not backend.is_gpu:
        count = int(kept[0])
        keep = np.concatenate([[False], reportable(sums[1:count + 1], min_area_m2,
                                                   min_depth_m, max_depth_m)])
        kept_after[0] = int(keep.sum())
        if kept_after[0] < count:
            labels, _ = relabel(xp, labels, keep)
        return labels
    new_id = xp.empty(capacity + 1, dtype=xp.int32)
    _kernel(backend, "measure_keep")(
        (1,), (32,), (sums, kept, np.int32(capacity), np.float64(min_area_m2),
                      np.float64(min_depth_m), np.float64(min(max_depth_m, 1e300)), new_id,
                      kept_after))
    return xp.take(new_id, labels, out=labels)


def reportable(sums: np.ndarray, min_area_m2: float, min_depth_m: float = 0.0,
               max_depth_m: float = math.inf) -> np.ndarray:
    """Bool (k,) over rows of measure sums (float64 (k, MEASURE_SUMS)): the pothole's sums are
    finite, its area reaches ``min_area_m2`` and is positive, it has measured points (valid
    area positive) and a measured depth (floor area and depth x floor area positive) whose
    mean lies in [``min_depth_m``, ``max_depth_m``] and is at most its width (the square root
    of its area: a hole deeper than it is wide is a mismatch): a report with finite, positive,
    possible numbers; and where it reaches into a far corner region (components.FarCorners),
    more than half of its pixels lie on significant superpixels (where the road model is
    extrapolated, a pothole needs more evidence: params' corner_significance)."""
    sums = np.asarray(sums)
    floor, depth_floor, area = sums[:, Sum.FLOOR], sums[:, Sum.DEPTH_FLOOR], sums[:, Sum.AREA]
    return np.isfinite(sums).all(axis=1) & (area >= min_area_m2) & (area > 0) \
        & (sums[:, Sum.VALID_AREA] > 0) & (floor > 0) & (depth_floor > 0) \
        & (depth_floor >= min_depth_m * floor) & (depth_floor <= max_depth_m * floor) \
        & (depth_floor <= np.sqrt(np.maximum(area, 0.0)) * floor) \
        & ((sums[:, Sum.CORNER] == 0) | (2 * sums[:, Sum.SIGNIFICANT] > sums[:, Sum.PIXELS]))


def keep_large(sums: np.ndarray, extremes: np.ndarray, min_area_m2: float,
               min_depth_m: float = 0.0, max_depth_m: float = math.inf
               ) -> tuple[list[Pothole], np.ndarray]:
    """The potholes of host copies of rows 1..k of :func:`measure`'s sums (float64 (k,
    MEASURE_SUMS)) and extremes (int32 (k, MEASURE_EXTREMES)) that make a report
    (:func:`reportable`), renumbered 1..m, and the bool (k+1,) keep table over labels 0..k
    (label 0 never kept): the rows :func:`area_filter` keeps."""
    keep = np.concatenate([[False], reportable(sums, min_area_m2, min_depth_m, max_depth_m)])
    return potholes_from_sums(sums[keep[1:]], extremes[keep[1:]]), keep


def _kernel(backend: Backend, name: str) -> Any:
    """Kernel ``name`` of kernels/measure.cu with the numbers it shares with this module."""
    return backend.kernel("measure.cu", name, _MEASURE_DEFINES)

