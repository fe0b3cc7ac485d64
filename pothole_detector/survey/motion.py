"""Ego-motion on the road plane: each frame's road frame (origin on the road below the left
camera, x forward along the view, y left, z up), planar poses (x, y, yaw) of that frame in a
motion frame, and the motion between frames from odometry, /tf, GNSS or our stereo visual
odometry (features of the left image with their disparities, planar rigid motion by RANSAC).
No ROS: messages come in as plain series."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..calibration import StereoCalibration
from ..geodesy import enu_of, latlon_of
from ..stages.road_model import RoadModel

@dataclass(frozen=True)
class RoadFrame:
    """The road frame of one stereo frame: ``origin`` (m, left optical frame) is the road
    point below the camera; ``axes`` (3x3) has rows x forward, y left, z up (unit vectors in
    the left optical frame)."""

    origin: np.ndarray
    axes: np.ndarray

    def from_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points of the left optical frame (m) in this road frame (m)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T


def road_frame(road: RoadModel, calibration: StereoCalibration, width: int,
               height: int) -> RoadFrame:
    """The road frame of a fitted road: a plane fitted to the road surface that the model
    gives over the lower half of the image."""
    u, v = np.meshgrid(np.linspace(0.1 * width, 0.9 * width, 9),
                       np.linspace(0.5 * height, 0.95 * height, 6))
    disparity = np.asarray(road.at(np, u, v), dtype=np.float64).ravel()
    keep = disparity > 0
    if keep.sum() < 3:
        raise ValueError("the road model has no disparity in the lower half of the image")
    points = np.stack(calibration.back_project(u.ravel()[keep], v.ravel()[keep],
                                               disparity[keep]), axis=-1)
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre)[2][2]
    if normal[1] > 0:  # up is -y in the optical frame
        normal = -normal
    offset = -float(normal @ centre)  # plane: normal . p + offset = 0
    origin = -offset * normal
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    left = np.cross(normal, forward)
    return RoadFrame(origin, np.stack([forward, left, normal]))


@dataclass(frozen=True)
class Pose2:
    """A planar pose: position (m) and heading (rad) of a road frame in the motion frame."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) points of the road frame in the motion frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return points @ np.array([[c, s], [-s, c]]) + np.array([self.x, self.y])

    def compose(self, step: "Pose2") -> "Pose2":
        """This pose followed by ``step`` (given in this pose's frame)."""
        x, y = self.apply(np.array([[step.x, step.y]]))[0]
        return Pose2(float(x), float(y), _wrap(self.yaw + step.yaw))

    def inverse(self) -> "Pose2":
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2(-(c * self.x + s * self.y), s * self.x - c * self.y, -self.yaw)

    def between(self, later: "Pose2") -> "Pose2":
        """The step from this pose to ``later`` (in this pose's frame)."""
        return self.inverse().compose(later)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def fit_rigid_2d(source: np.ndarray, target: np.ndarray,
                 weights: np.ndarray | None = None) -> Pose2:
    """The rigid motion taking (N, 2) ``source`` points to ``target`` by least squares
    (Kabsch), weighted by ``weights`` (N,) where given (non-negative, not all 0)."""
    weights = np.full(len(source), 1.0 / len(source)) if weights is None \
        else weights / weights.sum()
    mean_s, mean_t = weights @ source, weights @ target
    h = (source - mean_s).T @ ((target - mean_t) * weights[:, None])
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(yaw), math.sin(yaw)
    shift = mean_t - np.array([[c, -s], [s, c]]) @ mean_s
    return Pose2(float(shift[0]), float(shift[1]), yaw)


def ransac_rigid_2d(source: np.ndarray, target: np.ndarray, tolerance_m: float,
                    hypotheses: int = 200, seed: int = 0) -> tuple[Pose2, np.ndarray]:
    """The planar rigid motion taking ``source`` to ``target`` ((N, 2), m) that most pairs
    agree with within ``tolerance_m``, refitted on them; and the inlier mask."""
    count = len(source)
    rng = np.random.default_rng(seed)
    pairs = rng.integers(0, count, size=(hypotheses, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    ds, dt = source[pairs[:, 1]] - source[pairs[:, 0]], target[pairs[:, 1]] - target[pairs[:, 0]]
    yaw = np.arctan2(ds[:, 0] * dt[:, 1] - ds[:, 1] * dt[:, 0],
                     ds[:, 0] * dt[:, 0] + ds[:, 1] * dt[:, 1])
    c, s = np.cos(yaw), np.sin(yaw)
    anchor_s, anchor_t = source[pairs[:, 0]], target[pairs[:, 0]]
    tx = anchor_t[:, 0] - (c * anchor_s[:, 0] - s * anchor_s[:, 1])
    ty = anchor_t[:, 1] - (s * anchor_s[:, 0] + c * anchor_s[:, 1])
    moved_x = c[:, None] * source[None, :, 0] - s[:, None] * source[None, :, 1] + tx[:, None]
    moved_y = s[:, None] * source[None, :, 0] + c[:, None] * source[None, :, 1] + ty[:, None]
    error = np.hypot(moved_x - target[None, :, 0], moved_y - target[None, :, 1])
    inliers = error < tolerance_m
    best = inliers[int(np.argmax(inliers.sum(axis=1)))]
    if best.sum() < 3:
        best = np.ones(count, dtype=bool)
    pose = fit_rigid_2d(source[best], target[best])
    return pose, best


class StereoOdometry:
    """Planar visual odometry of the left camera: corners of the previous left image tracked
    into the current one (pyramidal Lucas-Kanade, checked backwards), lifted to 3D with each
    frame's disparity, put into each frame's road frame and matched by a RANSAC planar rigid
    motion."""

    def __init__(self, max_features: int = 400, tolerance_m: float = 0.02,
                 track_width_px: int = 720) -> None:
        """``track_width_px``: wider images are tracked at half size (or smaller) for speed;
        the disparities are still read at full size."""
        self.max_features = max_features
        self.tolerance_m = tolerance_m
        self.track_width_px = track_width_px
        self._previous: tuple[np.ndarray, np.ndarray, RoadFrame] | None = None

    def reset(self) -> None:
        self._previous = None

    def step(self, gray: np.ndarray, disparity: np.ndarray, frame: RoadFrame,
             calibration: StereoCalibration) -> Pose2 | None:
        """The motion of the road frame since the previous call's frame (in the previous
        frame's road frame), or None on the first frame or when too few features agree.
        ``gray``: HxW uint8 left image; ``disparity``: HxW float px, NaN invalid."""
        height, width = gray.shape
        scale = 1
        while width // scale > self.track_width_px:
            scale *= 2
        small = gray
        for _ in range(scale.bit_length() - 1):
            small = cv2.pyrDown(small)
        previous, self._previous = self._previous, (small, disparity, frame)
        if previous is None:
            return None
        gray0, disparity0, frame0 = previous
        gray = small
        corners = cv2.goodFeaturesToTrack(gray0, self.max_features, 0.01, 7, blockSize=7)
        if corners is None or len(corners) < 8:
            return None
        lk = dict(winSize=(15, 15), maxLevel=3,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03))
        moved, found, _ = cv2.calcOpticalFlowPyrLK(gray0, gray, corners, None, **lk)
        back, found_back, _ = cv2.calcOpticalFlowPyrLK(gray, gray0, moved, None, **lk)
        good = (found.ravel() == 1) & (found_back.ravel() == 1) & (
            np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < 0.5)
        start = corners.reshape(-1, 2)[good] * scale + (scale - 1) / 2
        end = moved.reshape(-1, 2)[good] * scale + (scale - 1) / 2
        inside = (end[:, 0] >= 0) & (end[:, 0] <= width - 1) & (end[:, 1] >= 0) & (
            end[:, 1] <= height - 1)
        start, end = start[inside], end[inside]
        d0 = _sample(disparity0, start)
        d1 = _sample(disparity, end)
        valid = np.isfinite(d0) & np.isfinite(d1) & (d0 > 0) & (d1 > 0)
        if valid.sum() < 8:
            return None
        p0 = np.stack(calibration.back_project(start[valid, 0], start[valid, 1], d0[valid]), -1)
        p1 = np.stack(calibration.back_project(end[valid, 0], end[valid, 1], d1[valid]), -1)
        q0, q1 = frame0.from_camera(p0)[:, :2], frame.from_camera(p1)[:, :2]
        pose, inliers = ransac_rigid_2d(q1, q0, self.tolerance_m)
        return pose if inliers.sum() >= 8 else None


def _sample(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Values of ``image`` at the nearest pixels of (N, 2) (u, v) ``points``."""
    u = np.clip(np.rint(points[:, 0]).astype(int), 0, image.shape[1] - 1)
    v = np.clip(np.rint(points[:, 1]).astype(int), 0, image.shape[0] - 1)
    return image[v, u].astype(np.float64)


def interpolate_poses(stamps_ns: np.ndarray, poses: list[Pose2],
                      at_ns: int) -> Pose2 | None:
    """The pose at ``at_ns`` interpolated linearly between the series' neighbours (None
    outside the series by more than 0.5 s)."""
    if not poses:
        return None
    index = int(np.searchsorted(stamps_ns, at_ns))
    if index == 0 or index == len(poses):
        nearest = 0 if index == 0 else len(poses) - 1
        if abs(int(stamps_ns[nearest]) - at_ns) > 500_000_000:
            return None
        return poses[nearest]
    t0, t1 = int(stamps_ns[index - 1]), int(stamps_ns[index])
    w = (at_ns - t0) / max(t1 - t0, 1)
    a, b = poses[index - 1], poses[index]
    return Pose2(a.x + w * (b.x - a.x), a.y + w * (b.y - a.y),
                 _wrap(a.yaw + w * _wrap(b.yaw - a.yaw)))


def planar_pose(position: Any, orientation: Any) -> Pose2:
    """The planar pose of a geometry_msgs Point/Vector3 ``position`` (m; x, y kept) and
    Quaternion ``orientation`` (its heading about z)."""
    q = orientation
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    return Pose2(float(position.x), float(position.y), yaw)


# the least stretch of the drive (m) the fixes must cover to place it
MIN_SPAN_M = 0.5
# a fix takes part in a frame's alignment where its Gaussian weight of distance is above this
# (within 3.7 half-widths of the window); frames with none so close lie in a gap
WINDOW_REACH = 1e-3


@dataclass
class GnssFusion:
    """Odometry whose drift GNSS corrects along the drive: for each frame of the route, the
    rigid motion taking odometry positions near it to the GNSS track (east, north, m, from
    ``origin`` (lat, lon)); and the fixes' residuals after it (m; NaN for fixes outside the
    route's time) with the robust weight each kept (0: rejected as an outlier)."""

    route_xy: np.ndarray
    alignments: list[Pose2 | None]
    blends: list[tuple[int, int, float]]
    origin: np.ndarray
    residuals_m: np.ndarray
    kept: np.ndarray

    def map_at(self, frame: int, points: np.ndarray) -> np.ndarray:
        """(N, 2) odometry positions (m) in east, north (m) by the mapping of route frame
        ``frame`` (its alignment, or in a gap the blend of those about it)."""
        low, high, weight = self.blends[frame]
        mapped = self.alignments[low].apply(points)
        if weight == 0.0:
            return mapped
        return (1 - weight) * mapped + weight * self.alignments[high].apply(points)

    @cached_property
    def _route_tree(self) -> cKDTree:
        """A k-d tree of the route's positions, for the frame nearest to a point."""
        return cKDTree(self.route_xy)

    @cached_property
    def route_enu(self) -> np.ndarray:
        """The route's positions (N, 2) in east, north (m), each by its own frame's mapping."""
        return np.array([self.map_at(i, p)[0] for i, p in enumerate(self.route_xy)]
                        ).reshape(-1, 2)

    @cached_property
    def _route_enu_tree(self) -> cKDTree:
        """A k-d tree of the route's positions in east, north."""
        return cKDTree(self.route_enu)

    def to_enu(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) odometry positions (m) in east, north (m): each by the mapping of the route
        frame nearest to it."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        _, nearest = self._route_tree.query(xy)
        return np.array([self.map_at(int(i), point)[0]
                         for i, point in zip(nearest, xy)]).reshape(-1, 2)

    def from_enu(self, enu: np.ndarray) -> np.ndarray:
        """(N, 2) east, north positions (m) in the odometry's frame (m): each by the inverse
        of the alignment of the route frame nearest to it (in a gap, of the nearer fitted
        frame about it)."""
        enu = np.asarray(enu, dtype=np.float64).reshape(-1, 2)
        _, nearest = self._route_enu_tree.query(enu)
        placed = []
        for i, point in zip(nearest, enu):
            low, high, weight = self.blends[int(i)]
            placed.append(self.alignments[high if weight > 0.5 else low].inverse()
                          .apply(point)[0])
        return np.array(placed).reshape(-1, 2)

    def to_latlon(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) odometry positions (m) as (lat, lon) degrees."""
        return latlon_of(self.to_enu(xy), *self.origin)


def fuse_gnss(route_stamps_ns: np.ndarray, route_xy: np.ndarray, gnss_stamps_ns: np.ndarray,
              gnss_latlon: np.ndarray, gnss_sigma_m: np.ndarray, window_m: float,
              outlier_sigmas: float = 3.0, rounds: int = 3) -> GnssFusion | None:
    """Odometry (frame stamps, (N, 2) positions in its own frame, m) fused with GNSS fixes
    (stamps, (K, 2) lat/lon, (K,) horizontal sigma m, NaN where the fix gave none): for each
    frame, the rigid motion fitted by weighted least squares to the fixes within about
    ``window_m`` of travel around it (a drive shorter than that: all of it; Gaussian weights
    of half-width ``window_m`` / 2 in distance along the odometry's path, times the fix's
    1 / sigma^2), so that the odometry's drift of scale and heading is taken out along the
    drive rather than once for all of it.
    Rounds of Huber weights down-weight fixes more than ``outlier_sigmas`` sigmas off
    (three times as far: rejected). A frame whose window holds fixes along less than half of
    it (a gap in the fixes, or the drive's end) has no alignment of its own: it blends those
    of the nearest frames with one on either side by distance along the route, so that the
    odometry carries the drive through the gap. None where the fixes cover less than
    MIN_SPAN_M of the drive."""
    route_xy = np.asarray(route_xy, dtype=np.float64).reshape(-1, 2)
    times = np.asarray(route_stamps_ns, dtype=np.float64)
    stamps = np.asarray(gnss_stamps_ns, dtype=np.float64)
    inside = (stamps >= times[0]) & (stamps <= times[-1]) if len(times) else stamps < 0
    if len(route_xy) < 2 or inside.sum() < 2:
        return None
    origin = np.asarray(gnss_latlon[0], dtype=np.float64)
    enu = enu_of(gnss_latlon[:, 0], gnss_latlon[:, 1], *origin)
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(route_xy, axis=0),
                                                                axis=1))])
    odometry = np.stack([np.interp(stamps, times, route_xy[:, 0]),
                         np.interp(stamps, times, route_xy[:, 1])], axis=1)
    along = np.interp(stamps, times, travelled)
    sigma = np.asarray(gnss_sigma_m, dtype=np.float64)
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma,
                     np.nanmedian(np.where(sigma > 0, sigma, np.nan))
                     if np.any(np.isfinite(sigma) & (sigma > 0)) else 1.0)
    precision = np.where(inside, 1.0 / sigma ** 2, 0.0)
    robust = np.ones(len(stamps))
    span = float(np.ptp(along[inside]))
    if span < MIN_SPAN_M:
        return None
    half = min(window_m, span) / 2
    nearest = np.clip(np.searchsorted(times, stamps), 0, len(times) - 1)
    fusion = None
    for _ in range(max(rounds, 1)):
        alignments = []
        for position in travelled:
            closeness = np.exp(-0.5 * ((along - position) / half) ** 2)
            useful = (closeness > WINDOW_REACH) & (precision * robust > 0)
            weight = precision * robust * closeness
            spread = np.ptp(odometry[useful], axis=0).max() if useful.sum() >= 3 else 0.0
            alignments.append(fit_rigid_2d(odometry[useful], enu[useful], weight[useful])
                              if useful.sum() >= 3 and spread >= half else None)
        if all(a is None for a in alignments):
            return None
        fusion = GnssFusion(route_xy, alignments, _gap_blends(alignments, travelled), origin,
                            np.zeros(0), np.zeros(0))
        residual = np.array([np.linalg.norm(fusion.map_at(int(i), o)[0] - e)
                             for i, o, e in zip(nearest, odometry, enu)])
        limit = outlier_sigmas * sigma
        robust = np.where(residual <= limit, 1.0, limit / np.maximum(residual, 1e-12))
        robust = np.where(residual > 3 * limit, 0.0, robust)
    assert fusion is not None
    fusion.residuals_m = np.where(inside, residual, np.nan)
    fusion.kept = np.where(inside, robust, 0.0)
    return fusion


def _gap_blends(alignments: list[Pose2 | None], travelled: np.ndarray
                ) -> list[tuple[int, int, float]]:
    """Per frame, how its mapping is made: (i, j, w) maps a point by the alignments of frames
    i and j blended as (1 - w) A_i(p) + w A_j(p); a frame with its own alignment is (k, k, 0),
    one in a gap blends the nearest ones with an alignment on either side by distance along
    the route (``travelled``, m), one past the route's aligned ends takes the nearest."""
    present = np.array([i for i, a in enumerate(alignments) if a is not None])
    blends = []
    for index, alignment in enumerate(alignments):
        if alignment is not None:
            blends.append((index, index, 0.0))
            continue
        after = int(np.searchsorted(present, index))
        if after == 0 or after == len(present):
            nearest = int(present[min(after, len(present) - 1)])
            blends.append((nearest, nearest, 0.0))
            continue
        low, high = int(present[after - 1]), int(present[after])
        span = travelled[high] - travelled[low]
        weight = (travelled[index] - travelled[low]) / span if span > 0 else 0.0
        blends.append((low, high, float(weight)))
    return blends
