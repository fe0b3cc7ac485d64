"""The road survey: recorded drives in, one entry per physical pothole out. Each frame's
potholes are put on the road plane (the frame's road frame), carried into one motion frame
by the ego-motion (odometry, /tf or GNSS in the bag, else our stereo visual odometry) and
tracked; each frame's road goes into the fused road map (roadmap.py). An entry is a
depression of the map with the tracks on it, measured from all the views that saw it (a
track where the map saw no road keeps its best view: the nearest sighting inside the
observed range), with the spread over its sightings. Bags split into chunks of frames for
parallel work (Ray); the chunks' frames are merged before tracking. No ROS: bags are read
with rosbags."""

from __future__ import annotations

import csv
import datetime
import itertools
import json
import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, NamedTuple, Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..backend import get_backend
from ..calibration import StereoCalibration
from ..errors import InputError, PotholeError
from ..geodesy import enu_of, latlon_of
from .motion import (GnssFusion, Pose2, RoadFrame, StereoOdometry, fuse_gnss,
                     interpolate_poses, planar_pose, road_frame)
from ..recordings import bags, readahead
from ..recordings.messages import stamp_ns
from ..recordings.writing import GNSS_TYPE, ODOMETRY_TYPE
from ..replay import FailureTally, ProcessSummary, frame_results
from ..recordings.topics import StereoTopics, find_stereo_topics
from ..stages.matching import host_threads, set_host_threads, to_gray8
from ..params import Config
from .roadmap import (MapPothole, RoadMap, RoadPatch, merged, near_potholes, result_patches,
                      road_map, sample_pixel_sets)
from .tracking import (PotholeTracker, Sighting, Track, joined, linked_groups, merge_overlapping,
                       sightings_of)

TF_TYPE = "tf2_msgs/msg/TFMessage"
SEVERITIES = ("low", "moderate", "high")
CSV_COLUMNS = ("pothole_id", "bag", "first_stamp_ns", "last_stamp_ns", "sightings",
               "best_stamp_ns", "first_time_utc", "last_time_utc", "best_time_utc", "x_m",
               "y_m", "z_m", "odom_x_m", "odom_y_m", "lat", "lon", "max_depth_m",
               "mean_depth_m", "area_m2", "volume_m3", "length_m", "width_m", "diameter_m",
               "severity", "severity_standard", "map_views", "max_depth_sigma_m")
# ASTM D6433's pothole severity (asphalt): rows by largest depth (m, up to), columns by average
# diameter (m, up to); potholes wider than the last column are classed by depth alone
ASTM_DEPTHS_M = (0.025, 0.050, math.inf)
ASTM_DIAMETERS_M = (0.200, 0.450, 0.750)
ASTM_TABLE = (("low", "low", "moderate"),
              ("low", "moderate", "high"),
              ("moderate", "moderate", "high"))
ASTM_WIDE_SHALLOW_M = 0.025


def severity(max_depth_m: float, config: Config, diameter_m: float = math.nan) -> str:
    """The severity class (low, moderate, high) of a pothole of largest depth ``max_depth_m``
    and average diameter ``diameter_m`` (m) by ``severity_standard``: the FHWA LTPP depths
    (``severity_moderate_depth_m``, ``severity_high_depth_m``), or ASTM D6433's pothole table
    (depth up to 25 mm, up to 50 mm, deeper; diameter up to 200 mm, 450 mm, 750 mm; wider:
    moderate up to 25 mm deep, else high). Under ASTM, one of unknown diameter is classed by
    the table's narrowest column."""
    if config.severity_standard == "astm_d6433":
        if diameter_m > ASTM_DIAMETERS_M[-1]:
            return "moderate" if max_depth_m <= ASTM_WIDE_SHALLOW_M else "high"
        row = next(i for i, limit in enumerate(ASTM_DEPTHS_M) if max_depth_m <= limit)
        column = next((i for i, limit in enumerate(ASTM_DIAMETERS_M) if diameter_m <= limit),
                      0)
        return ASTM_TABLE[row][column]
    if max_depth_m > config.severity_high_depth_m:
        return "high"
    if max_depth_m > config.severity_moderate_depth_m:
        return "moderate"
    return "low"


def utc_time(stamp_ns: int) -> str:
    """A time stamp (ns since the epoch) in ISO 8601 UTC, to the millisecond."""
    moment = datetime.datetime.fromtimestamp(stamp_ns / 1e9, tz=datetime.timezone.utc)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass(frozen=True)
class FrameCamera:
    """How one frame's left camera saw the road: its road frame (motion.RoadFrame: ``origin``,
    the road point below the camera, m, and ``axes``, rows forward, left, up, in the left
    optical frame), focal length and principal point (px) and image size (px)."""

    origin: tuple[float, float, float]
    axes: tuple[tuple[float, float, float], ...]
    f: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def of(cls, plane: RoadFrame, calibration: StereoCalibration, width: int,
           height: int) -> "FrameCamera":
        return cls(tuple(float(v) for v in plane.origin),  # type: ignore[arg-type]
                   tuple(tuple(float(v) for v in row) for row in plane.axes),  # type: ignore
                   calibration.f, calibration.cx, calibration.cy, width, height)

    def project(self, road_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road points (N, 2) (forward, left, m, on the road plane) as (N, 3) points of the left
        optical frame (m) and (N, 2) pixels (u, v; NaN behind the camera)."""
        axes = np.asarray(self.axes)
        points = np.asarray(self.origin) + np.asarray(road_xy).reshape(-1, 2) @ axes[:2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(points[:, 2] > 0, points[:, 2], np.nan)
            pixels = np.stack([self.f * points[:, 0] / depth + self.cx,
                               self.f * points[:, 1] / depth + self.cy], axis=1)
        return points, pixels


@dataclass(frozen=True)
class FrameObservation:
    """What the survey keeps of one stereo frame: its potholes, the observed range (near, far,
    m along the road; NaN when none), the visual-odometry step from the previous frame (None
    on the first frame, when it failed or when the bag has odometry), how its camera saw the
    road (None when the frame failed), when the frame failed, why, and its road samples for
    the maps (None without a map): at map_cell_m around its potholes, at map_overview_cell_m
    over all its observed road."""

    stamp_ns: int
    sightings: tuple[Sighting, ...]
    observed_range_m: tuple[float, float]
    step: Pose2 | None
    failure: str = ""
    camera: FrameCamera | None = None
    patch: RoadPatch | None = None
    overview: RoadPatch | None = None


@dataclass(frozen=True)
class DriveTopics:
    """The topics a survey reads: the stereo camera's and, where the bag has them, motion
    (odometry or /tf) and GNSS."""

    stereo: StereoTopics
    odometry: str | None = None
    tf: str | None = None
    gnss: str | None = None
    base_frame: str = "base_link"

    def motion_topics(self) -> tuple[str, ...]:
        """The motion and GNSS topics the bag has."""
        return tuple(topic for topic in (self.odometry, self.tf, self.gnss) if topic)


def find_drive_topics(topics: dict[str, str], odometry: str | None = None,
                      gnss: str | None = None, base_frame: str = "base_link",
                      **stereo: str | None) -> DriveTopics:
    """The topics of a drive (``topics``: name -> type): stereo as ``process`` finds them,
    odometry and GNSS as named or the only topic of their type, /tf when it exists."""

    def only(given: str | None, msgtype: str, option: str) -> str | None:
        if given is not None:
            if topics.get(given) != msgtype:
                raise InputError(f"the bag has no {msgtype} topic {given}")
            return given
        found = [t for t, k in topics.items() if k == msgtype]
        if len(found) > 1:
            raise InputError(f"the bag has several {msgtype} topics {found}; name one with "
                             f"{option}")
        return found[0] if found else None

    return DriveTopics(
        find_stereo_topics(topics, **stereo),
        only(odometry, ODOMETRY_TYPE, "--odometry-topic"),
        "/tf" if topics.get("/tf") == TF_TYPE else None,
        only(gnss, GNSS_TYPE, "--gnss-topic"), base_frame)


def observe(bag: str | Path, topics: DriveTopics, config: Config,
            span: bags.LogSpan | None = None,
            progress: Callable[[int, int], None] | None = None) -> ChunkResult:
    """Run the pipeline and, where the bag has no odometry messages, visual odometry on the
    frames of ``bag``, or of a span of it (the frames of its lead before it run too, for the
    odometry, and are not returned); and read its motion messages (those logged in the
    span), in the same pass over the bag. A bag damaged part way keeps the frames before the
    damage, and the damage counts as a failed frame after them."""
    backend = get_backend(config.backend)
    processes = readahead.processes_for(config.read_processes, backend.name, host_threads())
    if processes > 0:
        readahead.start(processes)
    with bags.reading(bag) as reader:
        odometry = StereoOdometry()
        has_odometry = bool(topics.odometry) and bags.message_count(reader, topics.odometry) > 0
        observations: list[FrameObservation] = []
        motion_messages: list[tuple[str, int, Any]] = []
        results = frame_results(
            reader, topics.stereo, config, backend, ProcessSummary(), progress, span,
            config.read_threads, topics.motion_topics(), motion_messages, processes)
        for frame, outcome in _until_damaged(results, observations, span):
            kept = span is None or frame.logged_ns >= span.start_ns
            try:
                if isinstance(outcome, PotholeError):
                    raise outcome
                height, width = outcome.disparity.shape
                plane = road_frame(outcome.road, frame.calibration, width, height)
            except (PotholeError, ValueError) as exc:
                odometry.reset()
                if kept:
                    observations.append(FrameObservation(frame.stamp, (),
                                                         (math.nan, math.nan), None, str(exc)))
                continue
            step = None if has_odometry else odometry.step(
                to_gray8(frame.left_view()), outcome.host("disparity"), plane,
                frame.calibration)
            if kept:
                patch = overview = None
                if config.map_cell_m > 0:
                    patch, overview = frame_patches(outcome, plane, frame.calibration, config)
                observations.append(FrameObservation(
                    frame.stamp, sightings_of(frame.stamp, outcome, plane, width, height,
                                              frame.calibration),
                    tuple(float(v) for v in outcome.observed_range_m), step,
                    camera=FrameCamera.of(plane, frame.calibration, width, height),
                    patch=patch, overview=overview))
    return observations, motion_samples(motion_messages, topics)


def frame_patches(result: Any, plane: RoadFrame, calibration: StereoCalibration,
                  config: Config) -> tuple[RoadPatch, RoadPatch]:
    """A frame's road samples for the survey's maps: at map_cell_m around its potholes, at
    map_overview_cell_m over all its observed road (roadmap.result_patches)."""
    shape = result.disparity.shape
    fine, coarse = sample_pixel_sets(shape, result.road, calibration,
                                     (config.map_cell_m, config.map_overview_cell_m))
    fine = fine[near_potholes(fine, shape[1], [p.bbox_px for p in result.potholes])]
    fine_patch, overview = result_patches(
        result, [(fine, config.map_cell_m), (coarse, config.map_overview_cell_m)], plane,
        calibration)
    return fine_patch, overview


def _until_damaged(results: Iterable[tuple[bags.BagFrame, Any]],
                   observations: list[FrameObservation], span: bags.LogSpan | None
                   ) -> Iterator[tuple[bags.BagFrame, Any]]:
    """The (frame, outcome) of ``results`` until damage to the bag stops them (InputError);
    the damage is then noted in ``observations`` as a failed frame after the last one."""
    last = span.start_ns if span is not None else 0
    try:
        for frame, outcome in results:
            last = frame.stamp
            yield frame, outcome
    except InputError as exc:
        observations.append(FrameObservation(last + 1, (), (math.nan, math.nan), None,
                                             str(exc)))


@dataclass
class MotionSeries:
    """Poses of the road frame from the bag itself: odometry or /tf (planar x, y, yaw of
    ``base_frame``), and GNSS fixes (lat, lon, deg; horizontal sigma, m, NaN unknown)."""

    stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    poses: list[Pose2] = field(default_factory=list)
    source: str = "visual odometry"
    gnss_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    gnss_latlon: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    gnss_sigma_m: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class MotionSamples:
    """The motion messages of a bag or of a span of it, as read: odometry and /tf poses of
    ``base_frame`` and GNSS fixes, each as (stamp ns, value) pairs."""

    odometry: list[tuple[int, Pose2]] = field(default_factory=list)
    tf: list[tuple[int, Pose2]] = field(default_factory=list)
    gnss: list[tuple[int, tuple[float, float]]] = field(default_factory=list)


def motion_samples(messages: Iterable[tuple[str, int, Any]], topics: DriveTopics
                   ) -> MotionSamples:
    """The odometry, /tf and GNSS samples of (topic, log time, message) motion messages."""
    samples = MotionSamples()
    for topic, _, msg in messages:
        if topic == topics.odometry:
            samples.odometry.append((stamp_ns(msg.header), planar_pose(
                msg.pose.pose.position, msg.pose.pose.orientation)))
        elif topic == topics.tf:
            samples.tf += [(stamp_ns(transform.header), planar_pose(
                transform.transform.translation, transform.transform.rotation))
                for transform in msg.transforms
                if transform.child_frame_id.strip("/") == topics.base_frame]
        elif topic == topics.gnss and msg.status.status >= 0 and math.isfinite(msg.latitude):
            samples.gnss.append((stamp_ns(msg.header),
                                 (float(msg.latitude), float(msg.longitude), _fix_sigma(msg))))
    return samples


def _fix_sigma(fix: Any) -> float:
    """A NavSatFix's horizontal position sigma (m): the root mean of its east and north
    variances; NaN where its covariance is unknown."""
    covariance = np.asarray(fix.position_covariance, dtype=np.float64)
    if int(fix.position_covariance_type) == 0 or covariance.size < 5:
        return math.nan
    variance = (covariance[0] + covariance[4]) / 2
    return math.sqrt(variance) if math.isfinite(variance) and variance > 0 else math.nan


def motion_series(parts: Iterable[MotionSamples], topics: DriveTopics) -> MotionSeries:
    """The motion and GNSS series of a bag from its samples (read whole or by span): the
    odometry, else /tf; GNSS fixes."""
    series = MotionSeries()
    odometry, tf, gnss = [], [], []
    for part in parts:
        odometry += part.odometry
        tf += part.tf
        gnss += part.gnss
    poses = odometry or tf
    if odometry:
        series.source = f"odometry ({topics.odometry})"
    elif tf:
        series.source = f"/tf ({topics.base_frame})"
    if poses:
        poses.sort(key=lambda sample: sample[0])
        series.stamps_ns = np.array([stamp for stamp, _ in poses], dtype=np.int64)
        series.poses = [pose for _, pose in poses]
    if gnss:
        gnss.sort(key=lambda sample: sample[0])
        series.gnss_stamps_ns = np.array([stamp for stamp, _ in gnss], dtype=np.int64)
        fixes = np.array([fix for _, fix in gnss], dtype=np.float64)
        series.gnss_latlon, series.gnss_sigma_m = fixes[:, :2], fixes[:, 2]
        if not poses:
            series.source = f"GNSS ({topics.gnss})"
    return series


def frame_poses(observations: Sequence[FrameObservation], motion: MotionSeries
                ) -> list[Pose2 | None]:
    """The pose of each frame's road frame in the motion frame: from the bag's odometry or
    /tf, else from GNSS (heading along the track), else chained visual-odometry steps (a
    missing step repeats the last one)."""
    stamps = np.array([o.stamp_ns for o in observations], dtype=np.int64)
    if motion.poses:
        return [interpolate_poses(motion.stamps_ns, motion.poses, int(s)) for s in stamps]
    if len(motion.gnss_latlon) >= 2:
        enu = enu_of(motion.gnss_latlon[:, 0], motion.gnss_latlon[:, 1],
                     *motion.gnss_latlon[0])
        headings = np.arctan2(*np.gradient(enu, axis=0).T[::-1])
        gnss_poses = [Pose2(float(e), float(n), float(h)) for (e, n), h in zip(enu, headings)]
        return [interpolate_poses(motion.gnss_stamps_ns, gnss_poses, int(s)) for s in stamps]
    poses: list[Pose2 | None] = []
    pose, last_step = Pose2(), Pose2()
    for index, observation in enumerate(observations):
        if index:
            last_step = observation.step or last_step
            pose = pose.compose(last_step)
        poses.append(pose)
    turn = Pose2(0.0, 0.0, -_heading_error(observations))
    return [turn.compose(p) for p in poses]


def _heading_error(observations: Sequence[FrameObservation]) -> float:
    """The heading (rad) of the drive's median forward axis in the first road frame: the
    camera is fixed on the vehicle, so a frame's forward axis in the camera differs from the
    median by its road fit's error, and visual odometry would carry the first frame's into
    every position of the drive."""
    frames = [np.asarray(o.camera.axes) for o in observations if o.camera is not None]
    if len(frames) < 3 or observations[0].camera is None:
        return 0.0
    forward = np.median([f[0] for f in frames], axis=0)
    first = frames[0]
    forward -= (forward @ first[2]) * first[2]
    return math.atan2(float(forward @ first[1]), float(forward @ first[0]))


def track(observations: Sequence[FrameObservation], poses: Sequence[Pose2 | None],
          config: Config) -> list[Track]:
    """Every pothole tracked over the frames (tracking.PotholeTracker), also those seen once."""
    tracker = PotholeTracker(config.track_match_distance_m, config.track_forget_frames)
    for observation, pose in zip(observations, poses):
        if pose is None:
            tracker.skip()
        else:
            tracker.update(observation.sightings, pose)
    return tracker.tracks


@dataclass(frozen=True)
class SurveyPothole:
    """One row of the survey (CSV_COLUMNS), the spread of its measurements over its sightings
    (min, max of the largest depth, m, and of the area, m2), its box in the best view, its
    outline on the road (the map's, else the best view's): ``outline_xy`` float64 (N, 2) in
    the motion frame (m), ``outline_latlon`` (N, 2) degrees where the drive has GNSS (both
    empty where not measured) and the largest depth the best view alone gave (m)."""

    row: dict[str, Any]
    depth_spread_m: tuple[float, float]
    area_spread_m2: tuple[float, float]
    bbox_px: tuple[int, int, int, int]
    outline_xy: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    outline_latlon: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    best_view_depth_m: float = math.nan


@dataclass
class DriveSurvey:
    """The survey of one bag: its potholes, the route (motion-frame positions of the frames),
    the GNSS route (lat, lon) where the bag has GNSS, the motion source, the observed length of
    road (m), the frame counts, how many tracked potholes were left out (seen in fewer than
    ``min_sightings`` frames, or on road the map saw without a depression), the topics it was
    read from, the frames that failed: (stamp ns, seconds into the drive, motion-frame x, y (m;
    NaN where unknown), why), and why the bag could not be read at all, if so; where the bag
    has GNSS, the fixes' residuals after the fusion with the odometry (fixes, rejected,
    median_m, p95_m, max_m); the fused map of the whole road (None without one) and, where it
    lies in east, north about a GNSS origin, that origin (lat, lon)."""

    bag: Path
    potholes: list[SurveyPothole]
    route_xy: np.ndarray
    route_latlon: np.ndarray | None
    motion_source: str
    observed_length_m: float
    frames: int
    left_out: int = 0
    topics: DriveTopics | None = None
    failures: list[tuple[int, float, float, float, str]] = field(default_factory=list)
    error: str = ""
    gnss_residuals: dict[str, Any] | None = None
    roadmap: RoadMap | None = None
    map_origin_latlon: tuple[float, float] | None = None

    @classmethod
    def unreadable(cls, bag: str | Path, error: str) -> "DriveSurvey":
        """The survey of a bag that could not be read at all, and why."""
        return cls(Path(bag), [], np.zeros((0, 2)), None, "none", 0.0, 0, error=error)

    @property
    def failed(self) -> int:
        return len(self.failures)

    def failure_tally(self) -> FailureTally:
        """The failed frames counted by kind of reason."""
        tally = FailureTally()
        for stamp, _, _, _, reason in self.failures:
            tally.add(stamp, reason)
        return tally


def assemble(bag: str | Path, observations: Sequence[FrameObservation], motion: MotionSeries,
             config: Config, first_id: int = 1, topics: DriveTopics | None = None
             ) -> DriveSurvey:
    """Merge chunk observations (a frame processed by two chunks counts once, the one with a
    visual-odometry step kept), then poses, tracking, the fused road map and the report
    rows."""
    by_stamp: dict[int, FrameObservation] = {}
    for observation in observations:
        kept = by_stamp.get(observation.stamp_ns)
        if kept is None or (kept.step is None and observation.step is not None):
            by_stamp[observation.stamp_ns] = observation
    frames = [by_stamp[s] for s in sorted(by_stamp)]
    poses = frame_poses(frames, motion)
    tracked_all = merge_overlapping(track(frames, poses, config))
    fusion = _gnss_fusion(frames, poses, motion, config)
    roadmap, overview = fused_maps(frames, poses, fusion, config)
    route = np.array([[p.x, p.y] for p in poses if p is not None]).reshape(-1, 2)
    place = MapFrame(fusion, route)
    entries = map_entries(tracked_all, roadmap, place, config)
    entries = sorted(entries + map_only_entries(overview, tracked_all, entries, frames, poses,
                                                place, config),
                     key=lambda entry: entry[1].sightings[0].stamp_ns)
    rows = [survey_pothole(first_id + offset, bag, together, found, place, config)
            for offset, (_, together, found) in enumerate(entries)]
    start = frames[0].stamp_ns if frames else 0
    failures = [(f.stamp_ns, (f.stamp_ns - start) / 1e9, pose.x if pose else math.nan,
                 pose.y if pose else math.nan, f.failure)
                for f, pose in zip(frames, poses) if f.failure]
    return DriveSurvey(Path(bag), rows, route,
                       fusion.to_latlon(route) if fusion is not None and len(route) else None,
                       motion.source, _observed_length(frames, poses), len(frames),
                       len(tracked_all) - sum(len(tracks) for tracks, _, _ in entries), topics,
                       failures, gnss_residuals=_residual_summary(fusion), roadmap=overview,
                       map_origin_latlon=tuple(float(v) for v in fusion.origin)
                       if fusion is not None else None)


@dataclass(frozen=True)
class MapFrame:
    """The frame of a drive's road map: east, north (m) about the GNSS origin where the drive
    has GNSS fused with its motion, else the motion frame; and the route in it."""

    fusion: GnssFusion | None
    route_xy: np.ndarray

    def of_motion(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) motion-frame positions (m) in the map frame (m)."""
        return self.fusion.to_enu(xy) if self.fusion is not None else np.asarray(xy)

    def to_motion(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) map-frame positions (m) in the motion frame (m)."""
        return self.fusion.from_enu(xy) if self.fusion is not None else np.asarray(xy)

    def to_latlon(self, xy: np.ndarray) -> np.ndarray | None:
        """(N, 2) map-frame positions as (lat, lon) degrees; None without GNSS."""
        return latlon_of(xy, *self.fusion.origin) if self.fusion is not None else None

    @cached_property
    def route(self) -> np.ndarray:
        """The route (N, 2) in the map frame (m)."""
        return self.fusion.route_enu if self.fusion is not None else np.asarray(self.route_xy)

    @cached_property
    def _route_tree(self) -> cKDTree | None:
        return cKDTree(self.route) if len(self.route) >= 2 else None

    def heading_at(self, xy: np.ndarray) -> np.ndarray:
        """The unit direction of travel (2,) in the map frame at the route point nearest to
        ``xy`` (m, map frame); the map's x axis without a route."""
        if self._route_tree is None:
            return np.array([1.0, 0.0])
        nearest = int(self._route_tree.query(xy)[1])
        low, high = max(0, nearest - 2), min(len(self.route) - 1, nearest + 2)
        step = self.route[high] - self.route[low]
        length = float(np.linalg.norm(step))
        return step / length if length > 0 else np.array([1.0, 0.0])


def fused_maps(frames: Sequence[FrameObservation], poses: Sequence[Pose2 | None],
               fusion: GnssFusion | None, config: Config
               ) -> tuple[RoadMap | None, RoadMap | None]:
    """The drive's road maps (roadmap.RoadMap): of the potholes (map_cell_m, the road around
    them) and of the whole road (map_overview_cell_m). Each placed frame's road samples are
    carried by its pose into the motion frame and, where GNSS is fused, by the frame's
    alignment into east, north. None where map_cell_m is 0 or no frame has samples."""
    if config.map_cell_m <= 0:
        return None, None
    potholes = road_map(config)
    whole = road_map(config.replace(map_cell_m=config.map_overview_cell_m))
    placed = 0
    for frame, pose in zip(frames, poses):
        if pose is None:
            continue
        index, placed = placed, placed + 1
        for roadmap, patch in ((potholes, frame.patch), (whole, frame.overview)):
            if patch is None or not len(patch):
                continue
            xy = pose.apply(patch.xy)
            if fusion is not None:
                xy = fusion.map_at(index, xy)
            roadmap.add(xy, patch.depth, patch.sigma)
    return (potholes if potholes.tiles else None), (whole if whole.tiles else None)


def map_entries(tracks: Sequence[Track], roadmap: RoadMap | None, place: MapFrame,
                config: Config) -> list[tuple[list[Track], Track, MapPothole | None]]:
    """The survey's entries, in the order first seen, each as (its tracks, those tracks
    joined (tracking.joined), its depression of the map or None): each depression with the
    tracks that lie on it (within track_match_distance_m of its outline), where they were seen
    in min_sightings frames together; and each track of min_sightings on road the map did
    not see twice. A track on road the map saw, with no depression under it, is left out:
    its views together do not show it. Without a map, each track of min_sightings."""
    usable = [t for t in tracks if np.all(np.isfinite(t.position))]
    if roadmap is None:
        return [([t], t, None) for t in usable if len(t.sightings) >= config.min_sightings]
    found = roadmap.potholes()
    positions = place.of_motion(np.array([t.position for t in usable]).reshape(-1, 2))
    on: list[list[Track]] = [[] for _ in found]
    unseen: list[Track] = []
    centres = np.array([p.xy for p in found]).reshape(-1, 2)
    reach = max((float(np.linalg.norm(p.outline - p.xy, axis=1).max()) for p in found),
                default=0.0) + config.track_match_distance_m
    near = cKDTree(centres).query_ball_point(positions, reach) if len(found) else \
        [[] for _ in usable]
    for tracked, xy, candidates in zip(usable, positions, near):
        gaps = {i: _gap(found[i].outline, xy) for i in sorted(candidates)}
        nearest = min(gaps, key=gaps.__getitem__) if gaps else -1
        if nearest >= 0 and gaps[nearest] <= config.track_match_distance_m:
            on[nearest].append(tracked)
        elif roadmap.views_at(xy[None, :])[0] < 2:
            unseen.append(tracked)
    entries = [(group, joined(group), pothole) for group, pothole in zip(on, found) if group]
    entries = [entry for entry in entries if len(entry[1].sightings) >= config.min_sightings]
    entries += [([t], t, None) for t in unseen if len(t.sightings) >= config.min_sightings]
    return sorted(entries, key=lambda entry: entry[1].sightings[0].stamp_ns)


def map_only_entries(overview: RoadMap | None, tracks: Sequence[Track],
                     entries: Sequence[tuple[list[Track], Track, MapPothole | None]],
                     frames: Sequence[FrameObservation], poses: Sequence[Pose2 | None],
                     place: MapFrame, config: Config) -> list[tuple[list[Track], Track,
                                                                    MapPothole]]:
    """Entries for the potholes that the views together show better than any one: the
    depressions of the whole road's map (``overview``; each cell deeper than
    threshold_noise_sigmas of the noise fused over every view that saw it) farther than
    track_match_distance_m from every entry's tracks and depression, pieces within that
    distance of each other joined (roadmap.merged), with seen road all around (MapPothole
    .enclosed), seen by at least min_sightings frames
    (:func:`map_sightings`, with the sightings of the tracks too short for an entry of their
    own that lie on it in place of their frames'), as (those tracks, a track of the views,
    the depression)."""
    if overview is None:
        return []
    reach = config.track_match_distance_m
    entered = {id(t) for group, _, _ in entries for t in group}
    spare = [t for t in tracks if id(t) not in entered and np.all(np.isfinite(t.position))]
    entered_xy = place.of_motion(np.array([t.position for group, _, _ in entries for t in group
                                           if np.all(np.isfinite(t.position))]).reshape(-1, 2))
    taken = list(entered_xy) + [found.outline for _, _, found in entries if found is not None]
    free = [d for d in overview.potholes() if all(_gap(d.outline, shape) > reach
                                                  for shape in taken)]
    spare_xy = place.of_motion(np.array([t.position for t in spare]).reshape(-1, 2))
    made = []
    for group in linked_groups(len(free), lambda i, j: _gap(free[i].outline, free[j].outline)
                               <= reach):
        depression = merged([free[i] for i in group])
        if not depression.enclosed:
            continue
        own = [t for t, xy in zip(spare, spare_xy) if _gap(depression.outline, xy) <= reach]
        measured = {s.stamp_ns: s for t in own for s in t.sightings}
        views = [measured.pop(s.stamp_ns, s)
                 for s in map_sightings(depression, frames, poses, place)]
        views = sorted(views + list(measured.values()), key=lambda s: s.stamp_ns)
        if len(views) < config.min_sightings or depression.views < config.min_sightings:
            continue
        centre = place.to_motion(np.asarray(depression.xy)[None, :])[0]
        outline = place.to_motion(depression.outline)
        made.append((own, Track(0, views, [centre] * len(views),
                                outlines=[outline] * len(views)), depression))
    return made


def map_sightings(depression: MapPothole, frames: Sequence[FrameObservation],
                  poses: Sequence[Pose2 | None], place: MapFrame) -> list[Sighting]:
    """The frames that saw a depression of the whole road's map: those whose road samples for
    it (``overview``) hold a cell at its centroid; as sightings placed by the frame's pose and
    camera (FrameCamera.project), ``observed`` inside the observed range, with the box of the
    outline in the image (clipped to it; ``whole`` where the outline lies inside) and no
    measures of their own (NaN: the map measures it)."""
    centre = place.to_motion(np.asarray(depression.xy)[None, :])
    outline = place.to_motion(depression.outline)
    seen = []
    for frame, pose in zip(frames, poses):
        camera, patch = frame.camera, frame.overview
        if pose is None or camera is None or patch is None or not len(patch):
            continue
        into_road = pose.inverse()
        road_centre = into_road.apply(centre)[0]
        cell = np.floor(road_centre / patch.cell_m)
        if not (patch.cells == cell).all(axis=1).any():
            continue
        points, pixels = camera.project(np.vstack([road_centre[None, :],
                                                   into_road.apply(outline)]))
        size = np.array([camera.width - 1, camera.height - 1])
        if not (np.isfinite(pixels).all() and (pixels[0] >= 0).all()
                and (pixels[0] <= size).all()):
            continue
        low, high = pixels[1:].min(axis=0), pixels[1:].max(axis=0)
        whole = bool((low >= 0).all() and (high <= size).all())
        low, high = np.clip(np.floor(low), 0, size), np.clip(np.ceil(high), 0, size)
        nan = math.nan
        near, far = frame.observed_range_m
        seen.append(Sighting(frame.stamp_ns, tuple(float(v) for v in points[0]),
                             (float(road_centre[0]), float(road_centre[1])),
                             bool(near <= road_centre[0] <= far), nan, nan, nan, nan,
                             (int(low[0]), int(low[1]), int(high[0]), int(high[1])), whole))
    return seen


def _gap(outline: np.ndarray, other: np.ndarray) -> float:
    """The distance (m) between a closed ``outline`` (N, 2) and ``other``: a point (2,) or
    another closed outline (M, 2); 0 where they overlap. Between two outlines it is the least
    distance from a vertex of one to the other (cv2.pointPolygonTest), where the least distance
    between two polygons lies."""
    other = np.asarray(other, dtype=np.float64)
    pairs = [(outline, other.reshape(-1, 2))]
    if other.ndim == 2:
        pairs.append((other, np.asarray(outline, dtype=np.float64).reshape(-1, 2)))
    return min(max(0.0, -cv2.pointPolygonTest(
        np.asarray(shape, dtype=np.float32).reshape(-1, 1, 2), (float(x), float(y)), True))
        for shape, points in pairs for x, y in points)


def survey_pothole(pothole_id: int, bag: str | Path, together: Track,
                   found: MapPothole | None, place: MapFrame, config: Config) -> SurveyPothole:
    """One entry: times, sightings and the best view from its tracks ``together``; depth, area,
    volume, length, width and outline from the map's depression ``found`` (all the views that
    saw it; its outline runs through its edge cells' centres, so its length and width are one
    cell more than the outline's), or from the best view where the map has none."""
    best = together.best()
    depths = [s.max_depth_m for s in together.sightings if math.isfinite(s.max_depth_m)] \
        or [found.max_depth_m if found is not None else math.nan]
    areas = [s.area_m2 for s in together.sightings if math.isfinite(s.area_m2)] \
        or [found.area_m2 if found is not None else math.nan]
    first, last = together.sightings[0].stamp_ns, together.sightings[-1].stamp_ns
    if found is not None:
        xy_map = np.array(found.xy)
        odom = place.to_motion(xy_map[None, :])[0]
        outline_map = found.outline
        outline = place.to_motion(outline_map)
        along = place.heading_at(xy_map)
        across = np.array([-along[1], along[0]])
        length = float(np.ptp(outline_map @ along)) + found.cell_m
        width = float(np.ptp(outline_map @ across)) + found.cell_m
        measures = (found.max_depth_m, found.mean_depth_m, found.area_m2, found.volume_m3,
                    length, width)
        views, sigma = found.views, found.max_depth_sigma_m
    else:
        odom = together.position
        xy_map = place.of_motion(odom[None, :])[0]
        outline = together.outlines[together.sightings.index(best)] if together.outlines \
            else np.empty((0, 2))
        outline_map = place.of_motion(outline) if len(outline) else np.empty((0, 2))
        measures = (best.max_depth_m, best.mean_depth_m, best.area_m2, best.volume_m3,
                    best.length_m, best.width_m)
        views, sigma = 1, math.nan
    max_depth, mean_depth, area, volume, length, width = (float(v) for v in measures)
    latlon = place.to_latlon(xy_map[None, :])
    outline_latlon = place.to_latlon(outline_map) if len(outline_map) else None
    row = {
        "pothole_id": pothole_id, "bag": Path(bag).name,
        "first_stamp_ns": first, "last_stamp_ns": last,
        "sightings": len(together.sightings), "best_stamp_ns": best.stamp_ns,
        "first_time_utc": utc_time(first), "last_time_utc": utc_time(last),
        "best_time_utc": utc_time(best.stamp_ns),
        "x_m": best.camera_xyz[0], "y_m": best.camera_xyz[1], "z_m": best.camera_xyz[2],
        "odom_x_m": float(odom[0]), "odom_y_m": float(odom[1]),
        "lat": float(latlon[0, 0]) if latlon is not None else None,
        "lon": float(latlon[0, 1]) if latlon is not None else None,
        "max_depth_m": max_depth, "mean_depth_m": mean_depth,
        "area_m2": area, "volume_m3": volume, "length_m": length, "width_m": width,
        "diameter_m": 2 * math.sqrt(max(area, 0.0) / math.pi),
        "severity": severity(max_depth, config, (length + width) / 2),
        "severity_standard": config.severity_standard,
        "map_views": views, "max_depth_sigma_m": float(sigma),
    }
    return SurveyPothole(row, (min(depths), max(depths)), (min(areas), max(areas)),
                         best.bbox_px, np.asarray(outline, dtype=np.float64).reshape(-1, 2),
                         np.asarray(outline_latlon if outline_latlon is not None
                                    else np.empty((0, 2))), best.max_depth_m)


def _residual_summary(fusion: GnssFusion | None) -> dict[str, Any] | None:
    """The GNSS fixes' residuals after the fusion: fixes used, rejected as outliers, median,
    95th percentile and largest residual of those used (m); None without GNSS."""
    if fusion is None:
        return None
    inside = np.isfinite(fusion.residuals_m)
    used = fusion.residuals_m[inside & (fusion.kept > 0)]
    return {"fixes": int(inside.sum()), "rejected": int((inside & (fusion.kept == 0)).sum()),
            "median_m": float(np.median(used)) if len(used) else None,
            "p95_m": float(np.percentile(used, 95)) if len(used) else None,
            "max_m": float(used.max()) if len(used) else None}


def _gnss_fusion(frames: Sequence[FrameObservation], poses: Sequence[Pose2 | None],
                 motion: MotionSeries, config: Config) -> GnssFusion | None:
    """The frames' motion-frame route fused with the GNSS track (motion.fuse_gnss, over
    ``gnss_window_m``); None without GNSS or with too short a track."""
    if len(motion.gnss_latlon) < 2:
        return None
    placed = [(frame.stamp_ns, (pose.x, pose.y)) for frame, pose in zip(frames, poses)
              if pose is not None]
    if len(placed) < 2:
        return None
    return fuse_gnss(np.array([stamp for stamp, _ in placed], dtype=np.int64),
                     np.array([xy for _, xy in placed]), motion.gnss_stamps_ns,
                     motion.gnss_latlon, motion.gnss_sigma_m, config.gnss_window_m)


def _observed_length(frames: Sequence[FrameObservation], poses: Sequence[Pose2 | None]
                     ) -> float:
    """Length (m) of road inside some frame's observed range, along the route."""
    travelled, intervals = 0.0, []
    previous = None
    for frame, pose in zip(frames, poses):
        if pose is None:
            continue
        if previous is not None:
            travelled += math.hypot(pose.x - previous.x, pose.y - previous.y)
        previous = pose
        near, far = frame.observed_range_m
        if math.isfinite(near) and math.isfinite(far) and far > near:
            intervals.append((travelled + near, travelled + far))
    length, end = 0.0, -math.inf
    for start, stop in sorted(intervals):
        if stop > end:
            length += stop - max(start, end)
            end = stop
    return length


def chunk_spans(bag: str | Path, topics: DriveTopics, config: Config
                ) -> tuple[int, list[bags.LogSpan]]:
    """The left images in ``bag`` (an upper bound of its stereo frames) and its chunks: its
    log time split evenly into spans of about ``chunk_frames`` frames, each read with a lead of
    ``chunk_overlap_frames`` + 2 frames (at the bag's mean rate) and the sync tolerance. A
    chunk seeks to its span: no frame before it is read."""
    with bags.reading(bag) as reader:
        count = bags.message_count(reader, topics.stereo.left)
        start, end = (reader.start_time, reader.end_time) if count else (0, 0)
        period_ns = bags.mean_period_ns(reader, topics.stereo.left) if count else 0.0
    pieces = max(1, math.ceil(count / config.chunk_frames))
    lead_ns = math.ceil(period_ns * (config.chunk_overlap_frames + 2)
                        + config.approximate_sync_tolerance_seconds * 1e9)
    bounds = [start + (end + 1 - start) * k // pieces for k in range(pieces + 1)]
    return count, [bags.LogSpan(first, stop, lead_ns)
                   for first, stop in zip(bounds, bounds[1:])]


def drive_topics(bag: str | Path, **names: Any) -> DriveTopics:
    """The :class:`DriveTopics` of ``bag``; ``names`` as :func:`find_drive_topics` takes."""
    return find_drive_topics(bags.topics_of(bag), **names)


class Plan(NamedTuple):
    """One bag of a survey: its path, topics, chunks (:func:`chunk_spans`) and left images (an
    upper bound of its stereo frames)."""

    bag: Path
    topics: DriveTopics
    spans: list[bags.LogSpan]
    left_images: int


ChunkResult = tuple[list[FrameObservation], MotionSamples]
# runs the chunks of every plan with the config, reporting (done, total) to the progress
# callback; yields each plan's chunks' results (in chunk order), plan after plan, as soon as
# that plan's chunks are all observed, so that a survey assembles a bag while the chunks of the
# bags after it are observed
ChunkRunner = Callable[[Sequence[Plan], Config, Callable[[int, int], None] | None],
                       Iterator[list[ChunkResult]]]


def in_plan_order(counts: Sequence[int], finished: Iterable[int]) -> Iterator[int]:
    """The plans (indices into ``counts``, each plan's number of chunks, the chunks numbered
    plan after plan), in order, each as soon as all its chunks are among the chunk indices
    ``finished`` yields (in the order they finish): what a ChunkRunner gives its caller."""
    owner = np.repeat(np.arange(len(counts)), counts)
    left = list(counts)
    plan = 0
    for chunk in itertools.chain([None], finished):
        if chunk is not None:
            left[owner[chunk]] -= 1
        while plan < len(counts) and left[plan] == 0:
            yield plan
            plan += 1


def observe_chunk(bag: str, topics: DriveTopics, values: dict[str, Any],
                  span: bags.LogSpan) -> ChunkResult:
    """:func:`observe` of one chunk with the parameter values ``values``: a task for worker
    processes and Ray."""
    return observe(bag, topics, Config(values), span)


def observe_in_processes(plans: Sequence[Plan], config: Config, jobs: int,
                         progress: Callable[[int, int], None] | None = None
                         ) -> Iterator[list[ChunkResult]]:
    """:func:`observe_chunk` of every (bag, topics, chunk spans) plan, a task per chunk in
    ``jobs`` worker processes on this machine (started afresh, each with its own pipeline on the
    configured backend: several share one GPU); per bag, in chunk order, each bag as soon as
    its chunks are done (the processes work on while the caller takes it)."""
    values = config.as_dict()
    threads = max(1, (os.cpu_count() or 1) // jobs)
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"),
                             initializer=set_host_threads, initargs=(threads,)) as pool:
        futures = [[pool.submit(observe_chunk, str(bag), topics, values, span)
                    for span in spans] for bag, topics, spans, _ in plans]
        flat = [future for per_bag in futures for future in per_bag]
        number = {future: index for index, future in enumerate(flat)}

        def finished() -> Iterator[int]:
            for done, future in enumerate(as_completed(flat), 1):
                if progress is not None:
                    progress(done, len(flat))
                yield number[future]

        try:
            for plan in in_plan_order([len(per_bag) for per_bag in futures], finished()):
                yield [future.result() for future in futures[plan]]
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise


def observe_here(plans: Sequence[Plan], config: Config,
                 progress: Callable[[int, int], None] | None = None
                 ) -> Iterator[list[ChunkResult]]:
    """:func:`observe` of every plan's chunks, one after the other in this process; per bag,
    in chunk order. ``progress(done, total)`` counts frames."""
    total = sum(plan.left_images for plan in plans)
    done = 0
    for bag, topics, spans, _ in plans:
        per_bag: list[ChunkResult] = []
        for span in spans:
            def step(index: int, _: int, base: int = done) -> None:
                if progress is not None:
                    progress(min(base + index, total), total)
            observed, samples = observe(bag, topics, config, span, step)
            per_bag.append((observed, samples))
            done += len(observed)
        yield per_bag
    if progress is not None:
        progress(total, total)


def chunk_runner(jobs: int) -> ChunkRunner:
    """The ChunkRunner of a survey on this machine: :func:`observe_here` for one job, else
    :func:`observe_in_processes` in ``jobs`` worker processes."""
    if jobs <= 1:
        return observe_here
    return lambda plans, config, progress: observe_in_processes(plans, config, jobs, progress)


def survey(bags: Iterable[str | Path], config: Config,
           progress: Callable[[int, int], None] | None = None, jobs: int = 1,
           chunks: ChunkRunner | None = None, **names: Any) -> list[DriveSurvey]:
    """Survey every bag (one id sequence over all of them). Every chunk of every bag is
    observed by the ChunkRunner ``chunks`` (fleet.ray_chunks: on Ray's workers); without one,
    with ``jobs`` > 1, each as a task of one of ``jobs`` worker processes here
    (:func:`observe_in_processes`), else one after the other here (:func:`observe_here`);
    each bag's observations are assembled here (:func:`assemble`) as soon as they are all
    there, while the bags after it are observed."""
    plans: list[Plan] = []
    unreadable: dict[int, DriveSurvey] = {}
    for index, bag in enumerate(bags):
        try:
            topics = drive_topics(bag, **names)
            left_images, spans = chunk_spans(bag, topics, config)
        except PotholeError as exc:
            unreadable[index] = DriveSurvey.unreadable(bag, str(exc))
            continue
        plans.append(Plan(Path(bag), topics, spans, left_images))
    chunked = iter((chunks or chunk_runner(jobs))(plans, config, progress))
    surveys, next_id = [], 1
    try:
        for (bag, topics, _, _), per_bag in zip(plans, chunked):
            observations = [o for observed, _ in per_bag for o in observed]
            motion = motion_series((samples for _, samples in per_bag), topics)
            drive = assemble(bag, observations, motion, config, next_id, topics)
            next_id += len(drive.potholes)
            surveys.append(drive)
        for _ in chunked:  # the runner's end: its last progress, its workers stopped
            pass
    finally:
        close = getattr(chunked, "close", None)
        if close is not None:
            close()
    for index in sorted(unreadable):
        surveys.insert(index, unreadable[index])
    return surveys


def write_summary(surveys: Sequence[DriveSurvey], path: str | Path) -> dict[str, Any]:
    """summary.json beside survey.csv: per bag the topics, motion source, frames processed
    and failed, the failures by kind of reason (count, first reason, first stamp) and each
    failed frame (stamp, seconds into the drive, motion-frame x, y), or why the bag could not
    be read; and the totals. Returns the document."""
    def finite(value: float) -> float | None:
        return float(value) if math.isfinite(value) else None

    drives = []
    for drive in surveys:
        drives.append({
            "bag": str(drive.bag), "error": drive.error or None,
            "topics": None if drive.topics is None else drive.topics.stereo.describe(),
            "motion_source": drive.motion_source, "frames": drive.frames,
            "processed": drive.frames - drive.failed, "failed": drive.failed,
            "potholes": len(drive.potholes), "gnss_residuals": drive.gnss_residuals,
            "failures_by_reason": [{"count": count, "reason": reason, "first_stamp_ns": stamp}
                                   for count, reason, stamp in drive.failure_tally().rows()],
            "failed_frames": [{"stamp_ns": stamp, "seconds": round(seconds, 3),
                               "odom_x_m": finite(x), "odom_y_m": finite(y), "reason": reason}
                              for stamp, seconds, x, y, reason in drive.failures],
        })
    document = {
        "bags": len(surveys), "unreadable_bags": sum(bool(d.error) for d in surveys),
        "frames": sum(d.frames for d in surveys),
        "processed": sum(d.frames - d.failed for d in surveys),
        "failed": sum(d.failed for d in surveys),
        "potholes": sum(len(d.potholes) for d in surveys), "drives": drives,
    }
    Path(path).write_text(json.dumps(document, indent=1) + "\n")
    return document


def write_csv(surveys: Sequence[DriveSurvey], path: str | Path) -> None:
    """survey.csv: one row per physical pothole, the columns of CSV_COLUMNS."""
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for drive in surveys:
            for pothole in drive.potholes:
                writer.writerow({k: _csv_value(v) for k, v in pothole.row.items()})


def _csv_value(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.9g}"
    return value


def write_geojson(surveys: Sequence[DriveSurvey], path: str | Path) -> bool:
    """survey.geojson: a point per pothole with GNSS position and, where measured, a polygon
    of its outline on the road, the row as the properties of both; False (nothing written)
    when no bag has GNSS."""
    features = []
    for drive in surveys:
        for pothole in drive.potholes:
            if pothole.row["lat"] is None:
                continue
            features.append({"type": "Feature",
                             "geometry": {"type": "Point",
                                          "coordinates": [pothole.row["lon"],
                                                          pothole.row["lat"]]},
                             "properties": pothole.row})
            if len(pothole.outline_latlon) >= 3:
                ring = [[float(lon), float(lat)] for lat, lon in pothole.outline_latlon]
                features.append({"type": "Feature",
                                 "geometry": {"type": "Polygon",
                                              "coordinates": [ring + ring[:1]]},
                                 "properties": pothole.row})
    if not features:
        return False
    Path(path).write_text(json.dumps({"type": "FeatureCollection", "features": features},
                                     indent=1))
    return True


def best_view_picture(bag: str | Path, topics: DriveTopics, stamp: int,
                      bbox_px: tuple[int, int, int, int], config: Config,
                      size_px: int = 240) -> np.ndarray:
    """The left image at ``stamp`` (ns), in the rectified frame the results are in, cropped
    about ``bbox_px`` (with a margin of half its size), the box drawn, scaled to at most
    ``size_px``: HxWx3 uint8 RGB."""
    image = bags.left_view_at(bag, topics.stereo, stamp, config)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = np.ascontiguousarray(image[..., :3]).astype(np.uint8)
    x0, y0, x1, y1 = bbox_px
    margin_x, margin_y = max(8, (x1 - x0) // 2), max(8, (y1 - y0) // 2)
    height, width = image.shape[:2]
    left, top = max(0, x0 - margin_x), max(0, y0 - margin_y)
    right, bottom = min(width, x1 + margin_x + 1), min(height, y1 + margin_y + 1)
    crop = image[top:bottom, left:right].copy()
    cv2.rectangle(crop, (x0 - left, y0 - top), (x1 - left, y1 - top), (255, 60, 30), 2)
    scale = size_px / max(crop.shape[:2])
    if scale < 1:
        crop = cv2.resize(crop, (max(1, round(crop.shape[1] * scale)),
                                 max(1, round(crop.shape[0] * scale))),
                          interpolation=cv2.INTER_AREA)
    return crop
