"""Pothole ids that stay with a physical pothole: each frame's potholes are put on the road
plane (the frame's road frame, carried into a motion frame by the ego-motion where it is
known) and join the tracked pothole nearest to them. The survey and the live node use the
same tracker."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import cv2
import numpy as np

from ..calibration import StereoCalibration
from ..stages.measure import window_of
from .motion import Pose2, RoadFrame

# the largest id the node publishes: the label image (pothole_labels) is mono16
MAX_ID = 65535
# how far (px) a simplified outline may depart from the labels' boundary
OUTLINE_TOLERANCE_PX = 1.0


@dataclass(frozen=True)
class Sighting:
    """One pothole in one frame: its centroid in the left optical frame and on the road
    (road frame x forward, y left; m), whether it lies inside the observed range, its
    measurements, its bounding box (x0, y0, x1, y1 px), whether it lies whole in the image
    (its box off the image border) and where its footprint on the road reaches
    (``extent_m``: least and largest forward, least and largest left coordinate in the road
    frame, m; NaN where not measured) and its outline there (``outline_m``: the footprint's
    boundary as (forward, left) points, m; empty where not measured)."""

    stamp_ns: int
    camera_xyz: tuple[float, float, float]
    road_xy: tuple[float, float]
    observed: bool
    max_depth_m: float
    mean_depth_m: float
    area_m2: float
    volume_m3: float
    bbox_px: tuple[int, int, int, int]
    whole: bool = True
    extent_m: tuple[float, float, float, float] = (math.nan,) * 4
    outline_m: tuple[tuple[float, float], ...] = ()

    @property
    def length_m(self) -> float:
        """Its length on the road along the road frame's forward axis (the direction of
        travel of a camera looking ahead), m; NaN where its footprint was not measured."""
        return self.extent_m[1] - self.extent_m[0]

    @property
    def width_m(self) -> float:
        """Its width on the road across the forward axis, m; NaN where not measured."""
        return self.extent_m[3] - self.extent_m[2]


def on_road(cols: np.ndarray, rows: np.ndarray, plane: RoadFrame,
            calibration: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Where the rays of pixels (``cols``, ``rows``, px) meet the road plane of ``plane``:
    float64 (M, 2) (forward, left) m of those whose ray meets it ahead, and the bool (N,) mask
    of which do."""
    rays = np.stack([(cols - calibration.cx) / calibration.f,
                     (rows - calibration.cy) / calibration.f, np.ones(len(cols))], axis=1)
    normal = plane.axes[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = (plane.origin @ normal) / (rays @ normal)
    ahead = np.isfinite(reach) & (reach > 0)
    return plane.from_camera(rays[ahead] * reach[ahead, None])[:, :2], ahead


def footprints(labels: np.ndarray, boxes: Sequence[tuple[slice, slice] | None],
               plane: RoadFrame, calibration: StereoCalibration,
               origin: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, list[np.ndarray]]:
    """Per pothole label 1..count of the int ``labels`` (the image's, or a window of it whose
    first pixel is the image's (row, column) ``origin``), read within its box (``boxes``:
    count (rows, columns) slices of ``labels`` that hold every pixel of labels 1, 2, ..., as
    ndimage.find_objects gives them or Pothole.window; None: no pixel), its footprint on the
    road plane of ``plane`` (each pixel's ray meeting the plane: the opening the pothole makes in
    the road, free of the disparity noise):

    - where it reaches: float64 (count, 4), least and largest forward, least and largest left
      coordinate (m); NaN for a label without a pixel whose ray meets the plane ahead. The
      map from the image to the plane is projective, so over the pixels ahead these extremes
      lie on the corners of their convex hull: only those are projected (all the label's
      pixels where its region reaches past the horizon);
    - its outline: the boundary of its largest region (OpenCV's contour, simplified to within
      OUTLINE_TOLERANCE_PX), float64 (N, 2) (forward, left) points, m; empty where fewer than
      three meet the plane ahead."""
    extents = np.full((len(boxes), 4), np.nan)
    outlines: list[np.ndarray] = []
    for label, box in enumerate(boxes, 1):
        mask = (labels[box] == label).astype(np.uint8) if box is not None else None
        if mask is None or not mask.any():
            outlines.append(np.empty((0, 2)))
            continue
        offset = (box[1].start + origin[1], box[0].start + origin[0])
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE,
                                       offset=offset)
        corners = cv2.convexHull(np.concatenate(contours)).reshape(-1, 2).astype(np.float64)
        reach, ahead = on_road(corners[:, 0], corners[:, 1], plane, calibration)
        if ahead.any() and not ahead.all():
            rows, cols = np.nonzero(mask)
            reach, _ = on_road((cols + offset[0]).astype(np.float64),
                               (rows + offset[1]).astype(np.float64), plane, calibration)
        if len(reach):
            extents[label - 1] = (reach[:, 0].min(), reach[:, 0].max(), reach[:, 1].min(),
                                  reach[:, 1].max())
        boundary = cv2.approxPolyDP(max(contours, key=cv2.contourArea), OUTLINE_TOLERANCE_PX,
                                    True).reshape(-1, 2).astype(np.float64)
        points, _ = on_road(boundary[:, 0], boundary[:, 1], plane, calibration)
        outlines.append(points if len(points) >= 3 else np.empty((0, 2)))
    return extents, outlines


def sightings_of(stamp_ns: int, result: Any, plane: RoadFrame, width: int, height: int,
                 calibration: StereoCalibration | None = None) -> tuple[Sighting, ...]:
    """The sightings of a PipelineResult's potholes, in its order, on the road frame
    ``plane`` of a ``width`` x ``height`` image (a centroid that is not finite gives a NaN
    position, which matches no track); with the result's ``calibration``, their footprints'
    extents and outlines (:func:`footprints`, from the labels read back, each within its
    pothole's box; only the window that holds them all is read back)."""
    near, far = result.observed_range_m
    extents = outlines = None
    if calibration is not None and result.potholes:
        windows = {p.label: p.window((height, width)) for p in result.potholes}
        around = window_of(result.potholes, (height, width))
        top, left = around[0].start, around[1].start
        labels = result.host("labels", around)
        boxes = [None if box is None else (slice(box[0].start - top, box[0].stop - top),
                                           slice(box[1].start - left, box[1].stop - left))
                 for box in (windows.get(label) for label in range(
                     1, len(result.potholes) + 1))]
        extents, outlines = footprints(labels, boxes, plane, calibration, (top, left))
    made = []
    for pothole in result.potholes:
        centre = np.asarray(pothole.centroid_cam_m, dtype=np.float64)
        forward, left, _ = plane.from_camera(centre[None, :])[0]
        made.append(Sighting(
            stamp_ns, tuple(float(v) for v in centre), (float(forward), float(left)),
            bool(near <= forward <= far), float(pothole.max_depth_m),
            float(pothole.mean_depth_m), float(pothole.area_m2), float(pothole.volume_m3),
            tuple(int(v) for v in pothole.bbox_px), _off_border(pothole.bbox_px, width, height),
            (math.nan,) * 4 if extents is None
            else tuple(float(v) for v in extents[pothole.label - 1]),
            () if outlines is None
            else tuple(map(tuple, outlines[pothole.label - 1].tolist()))))
    return tuple(made)


def radius_of(area_m2: float) -> float:
    """The radius (m) of a disc of ``area_m2``."""
    return math.sqrt(max(area_m2, 0.0) / math.pi)


def pieces(sightings: Sequence[Sighting]) -> list[list[int]]:
    """The frame's ``sightings`` grouped into the depressions they are pieces of: two belong
    together where their discs on the road plane (each a disc of its area about its centroid)
    touch, and groups chain. Each group's indices in order, the groups by their first."""
    def touch(i: int, j: int) -> bool:
        a, b = sightings[i], sightings[j]
        return math.dist(a.road_xy, b.road_xy) <= radius_of(a.area_m2) + radius_of(b.area_m2)

    return linked_groups(len(sightings), touch)


def linked_groups(count: int, joined: Callable[[int, int], bool]) -> list[list[int]]:
    """Indices 0..``count`` - 1 grouped where ``joined(i, j)`` (i < j) links them, links
    chaining (union-find); each group's indices in order, the groups by their first."""
    parent = list(range(count))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(count):
        for j in range(i + 1, count):
            if joined(i, j):
                parent[max(root(i), root(j))] = min(root(i), root(j))
    groups: dict[int, list[int]] = {}
    for i in range(count):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())


def combined(parts: Sequence[Sighting]) -> Sighting:
    """One sighting of the depression ``parts`` (sightings of one frame) are pieces of: areas
    and volumes add up, the largest depth is the deepest piece's, the mean depth and the
    positions are weighted by area, the box and the footprint's extent hold every piece's,
    the outline is the convex hull of theirs."""
    if len(parts) == 1:
        return parts[0]
    weights = np.array([max(p.area_m2, 0.0) for p in parts])
    weights = weights / weights.sum() if weights.sum() > 0 else np.full(len(parts),
                                                                         1 / len(parts))

    def weighted(values: Any) -> tuple[float, ...]:
        return tuple(float(v) for v in weights @ np.asarray(values, dtype=np.float64))

    boxes = np.array([p.bbox_px for p in parts])
    reach = np.array([p.extent_m for p in parts])
    return Sighting(
        parts[0].stamp_ns, weighted([p.camera_xyz for p in parts]),
        weighted([p.road_xy for p in parts]), any(p.observed for p in parts),
        max(p.max_depth_m for p in parts), float(weights @ [p.mean_depth_m for p in parts]),
        sum(p.area_m2 for p in parts), sum(p.volume_m3 for p in parts),
        (int(boxes[:, 0].min()), int(boxes[:, 1].min()), int(boxes[:, 2].max()),
         int(boxes[:, 3].max())), all(p.whole for p in parts),
        (float(reach[:, 0].min()), float(reach[:, 1].max()), float(reach[:, 2].min()),
         float(reach[:, 3].max())), tuple(map(tuple, hull([p.outline_m for p in parts]))))


def hull(outlines: Sequence[Any]) -> np.ndarray:
    """The convex hull (float64 (N, 2), N >= 3, or empty) of the points of ``outlines``
    (sequences of 2D points): the outline of pieces taken together."""
    points = [np.asarray(o, dtype=np.float64).reshape(-1, 2) for o in outlines if len(o)]
    if not points:
        return np.empty((0, 2))
    together = np.concatenate(points)
    if len(together) < 3:
        return np.empty((0, 2))
    return cv2.convexHull(together.astype(np.float32)).reshape(-1, 2).astype(np.float64)


def _off_border(bbox_px: Any, width: int, height: int, margin_px: int = 2) -> bool:
    x0, y0, x1, y1 = (int(v) for v in bbox_px)
    return (x0 >= margin_px and y0 >= margin_px and x1 < width - margin_px
            and y1 < height - margin_px)


@dataclass
class Track:
    """One physical pothole: its id, sightings and their positions in the motion frame (m),
    the frame it was last seen in, and each sighting's outline in the motion frame (float64
    (N, 2) m, empty where not measured)."""

    id: int
    sightings: list[Sighting] = field(default_factory=list)
    positions: list[np.ndarray] = field(default_factory=list)
    last_frame: int = 0
    outlines: list[np.ndarray] = field(default_factory=list)
    _areas: list[float] = field(default_factory=list, repr=False, compare=False)
    _unknown_areas: int = field(default=0, repr=False, compare=False)

    @property
    def position(self) -> np.ndarray:
        """Its position (m): the median of its sightings'."""
        return np.median(np.asarray(self.positions), axis=0)

    @property
    def radius_m(self) -> float:
        """The radius (m) of a disc of its median area (NaN where an area is not known). The
        areas are kept in order as sightings are appended, so that a pothole seen for long (a
        vehicle standing beside it) costs the tracker no more a frame."""
        areas = self._areas
        for sighting in self.sightings[len(areas) + self._unknown_areas:]:
            if math.isnan(sighting.area_m2):
                self._unknown_areas += 1
            else:
                bisect.insort(areas, sighting.area_m2)
        count = len(areas)
        if self._unknown_areas or not count:
            return radius_of(math.nan)
        middle = count // 2
        return radius_of(areas[middle] if count % 2 else (areas[middle - 1] + areas[middle]) / 2)

    def best(self) -> Sighting:
        """The nearest sighting that lies whole in the image inside the observed range (else
        the nearest whole one, else the nearest)."""
        candidates = ([s for s in self.sightings if s.observed and s.whole]
                      or [s for s in self.sightings if s.whole] or self.sightings)
        return min(candidates, key=lambda s: s.road_xy[0])


class PotholeTracker:
    """Tracks potholes frame after frame on the road plane. A sighting joins the track whose
    latest position is nearest, within ``match_distance_m`` or the sum of their radii, each
    track at most once a frame (nearest pairs first); the others start tracks with the next
    id (counting to ``max_id``, then from 1 again). Tracks not seen for ``forget_frames``
    frames take no more sightings. Without ego-motion, give the identity pose: the potholes
    then move on the road frame by the vehicle's motion between frames. ``tracks`` keeps
    every track when ``keep_history`` (the survey), else only those in view (the node)."""

    def __init__(self, match_distance_m: float, forget_frames: int,
                 max_id: int | None = None, keep_history: bool = True) -> None:
        self.match_distance_m = match_distance_m
        self.forget_frames = forget_frames
        self.max_id = max_id
        self.keep_history = keep_history
        self.tracks: list[Track] = []
        self._active: list[Track] = []
        self._frame = 0
        self._next = 1

    def reset(self) -> None:
        """Forget the tracks in view (a gap in the input, a new drive); ids count on."""
        self._active = []

    def skip(self) -> None:
        """A frame without a pose or without a road: tracks age by one frame."""
        self._frame += 1

    def update(self, sightings: Sequence[Sighting], pose: Pose2) -> list[int]:
        """The id of each of this frame's ``sightings`` (road-frame positions carried into
        the motion frame by ``pose``). Pieces of one depression (:func:`pieces`) take one id
        and join their track as one sighting (:func:`combined`)."""
        self._frame += 1
        self._active = [t for t in self._active
                        if self._frame - t.last_frame <= self.forget_frames]
        if not sightings:
            return []
        groups = pieces(sightings)
        ids = self._update([combined([sightings[i] for i in group]) for group in groups],
                           pose)
        given = [0] * len(sightings)
        for group, track_id in zip(groups, ids):
            for i in group:
                given[i] = track_id
        return given

    def _update(self, sightings: Sequence[Sighting], pose: Pose2) -> list[int]:
        """:meth:`update` of one sighting per depression."""
        positions = pose.apply(np.array([s.road_xy for s in sightings]))
        candidates = []
        radii = [existing.radius_m for existing in self._active]
        for i, (sighting, position) in enumerate(zip(sightings, positions)):
            radius = radius_of(sighting.area_m2)
            for j, existing in enumerate(self._active):
                gap = float(np.linalg.norm(existing.positions[-1] - position))
                if gap < max(self.match_distance_m, radii[j] + radius):
                    candidates.append((gap, i, j))
        joined: dict[int, Track] = {}
        taken: set[int] = set()
        for _, i, j in sorted(candidates):
            if i not in joined and j not in taken:
                joined[i] = self._active[j]
                taken.add(j)
        ids = []
        for i, (sighting, position) in enumerate(zip(sightings, positions)):
            target = joined.get(i)
            if target is None:
                target = Track(self._next)
                self._next = self._next + 1 if self.max_id is None else \
                    self._next % self.max_id + 1
                if self.keep_history:
                    self.tracks.append(target)
                self._active.append(target)
            target.sightings.append(sighting)
            target.positions.append(position)
            target.outlines.append(pose.apply(np.asarray(sighting.outline_m).reshape(-1, 2))
                                   if sighting.outline_m else np.empty((0, 2)))
            target.last_frame = self._frame
            ids.append(target.id)
        return ids


def merge_overlapping(tracks: Sequence[Track]) -> list[Track]:
    """The tracks of a drive with those that overlap on the road joined: two whose discs
    (each of its median area about its position in the motion frame) overlap are one
    depression seen as two (pieces tracked apart, a track lost and started again); joins
    chain. A joined track keeps the first one's id and holds every sighting, those of one
    frame combined (:func:`combined`), in time order; the tracks in order of their first
    sighting."""
    positions = [t.position for t in tracks]
    radii = [t.radius_m for t in tracks]
    finite = [bool(np.all(np.isfinite(p))) for p in positions]

    def overlap(i: int, j: int) -> bool:
        return finite[i] and finite[j] and float(
            np.linalg.norm(positions[i] - positions[j])) < radii[i] + radii[j]

    merged = [joined([tracks[i] for i in indices])
              for indices in linked_groups(len(tracks), overlap)]
    return sorted(merged, key=lambda t: (t.sightings[0].stamp_ns, t.id))


def joined(group: Sequence[Track]) -> Track:
    """The tracks of ``group`` as one: the least id, the latest last frame, every sighting,
    those of one frame combined (:func:`combined`, positions weighted by area, outlines by
    their hull), in time order; a group of one is its track."""
    if len(group) == 1:
        return group[0]
    by_stamp: dict[int, list[tuple[Sighting, np.ndarray, np.ndarray]]] = {}
    for member in group:
        outlines = member.outlines or [np.empty((0, 2))] * len(member.sightings)
        for sighting, position, outline in zip(member.sightings, member.positions, outlines):
            by_stamp.setdefault(sighting.stamp_ns, []).append((sighting, position, outline))
    together = Track(min(t.id for t in group), last_frame=max(t.last_frame for t in group))
    for stamp in sorted(by_stamp):
        parts = by_stamp[stamp]
        weights = np.array([max(s.area_m2, 0.0) for s, _, _ in parts]) + 1e-12
        together.sightings.append(combined([s for s, _, _ in parts]))
        together.positions.append(np.average([p for _, p, _ in parts], axis=0,
                                             weights=weights))
        together.outlines.append(hull([o for _, _, o in parts]))
    return together
