"""ROS messages <-> NumPy: images, camera info, disparity, point clouds, potholes, markers."""

from __future__ import annotations

import array
import math
from typing import Any, Sequence

import cv2
import numpy as np

from ..backend import array_module, to_host
from ..calibration import StereoCalibration
from ..errors import InputError
from ..recordings import messages
from ..recordings.images import array_to_image, decode_raw, with_bytes
from ..recordings.messages import message
from ..stages.measure import Pothole, depth_below_road
from ..stages.road_model import RoadModel

Duration = message("builtin_interfaces/msg/Duration")
Point = message("geometry_msgs/msg/Point")
PointCloud2 = message("sensor_msgs/msg/PointCloud2")
PointField = message("sensor_msgs/msg/PointField")
RegionOfInterest = message("sensor_msgs/msg/RegionOfInterest")
ColorRGBA = message("std_msgs/msg/ColorRGBA")
Header = message("std_msgs/msg/Header")
DisparityImage = message("stereo_msgs/msg/DisparityImage")
Marker = message("visualization_msgs/msg/Marker")
MarkerArray = message("visualization_msgs/msg/MarkerArray")
PotholeMsg = message("pothole_detector_msgs/msg/Pothole")
PotholeArray = message("pothole_detector_msgs/msg/PotholeArray")
OccupancyGrid = message("nav_msgs/msg/OccupancyGrid")
MapMetaData = message("nav_msgs/msg/MapMetaData")
Pose = message("geometry_msgs/msg/Pose")

SUBPIXEL_STEP_PX = 1.0 / 16.0
POINT_FIELDS = (("x", PointField.FLOAT32), ("y", PointField.FLOAT32), ("z", PointField.FLOAT32),
                ("depth_below_road", PointField.FLOAT32), ("label", PointField.UINT32))
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("depth_below_road", "<f4"),
                        ("label", "<u4")])


def disparity_message(disparity: np.ndarray, calibration: StereoCalibration,
                      disparity_range: tuple[float, float], header: Header) -> DisparityImage:
    """stereo_msgs/DisparityImage of a float32 HxW map (px, NaN invalid); invalid pixels get
    ``min_disparity - 1`` (outside the valid range), valid_window bounds the valid pixels."""
    low, high = disparity_range
    valid = np.isfinite(disparity)
    image = np.where(valid, disparity, np.float32(low - 1.0)).astype(np.float32, copy=False)
    window = RegionOfInterest()
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    if rows.size:
        window = RegionOfInterest(x_offset=int(cols[0]), y_offset=int(rows[0]),
                                  width=int(cols[-1] - cols[0] + 1),
                                  height=int(rows[-1] - rows[0] + 1))
    return DisparityImage(header=header, image=array_to_image(image, "32FC1", header),
                          f=float(calibration.f), t=float(calibration.baseline),
                          valid_window=window, min_disparity=float(low),
                          max_disparity=float(high), delta_d=SUBPIXEL_STEP_PX)


def disparity_from_message(msg: DisparityImage) -> np.ndarray:
    """The float32 HxW map of a DisparityImage with NaN outside [min, max]_disparity."""
    values = decode_raw(msg.image, allowed=("32FC1",)).astype(np.float32)
    values[(values < msg.min_disparity) | (values > msg.max_disparity)] = np.nan
    return values


def pothole_points(labels: np.ndarray, disparity: np.ndarray, road: RoadModel,
                   calibration: StereoCalibration,
                   window: tuple[slice, slice] | None = None) -> np.ndarray:
    """Structured array (N,) of POINT_DTYPE: x, y, z (m, left optical frame), depth below the
    road (m) and label of every pothole pixel with a valid disparity (looked for within the
    (rows, columns) ``window`` of the images where given: one that holds every pothole
    pixel, measure.window_of)."""
    rows, columns = window if window is not None else (slice(0, None), slice(0, None))
    v, u = np.nonzero(labels[rows, columns] > 0)
    v, u = v + rows.start, u + columns.start
    d = disparity[v, u]
    keep = np.isfinite(d) & (d > 0)
    u, v, d = u[keep], v[keep], d[keep].astype(np.float64)
    points = np.empty(u.size, dtype=POINT_DTYPE)
    points["x"], points["y"], points["z"] = calibration.back_project(u, v, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        points["depth_below_road"] = depth_below_road(np, u, v, d, road, calibration)[0]
    points["label"] = labels[v, u]
    return points


# the organized road cloud (points2): stereo_image_proc's x, y, z and rgb, then ours
CLOUD_FIELDS = (("x", PointField.FLOAT32), ("y", PointField.FLOAT32), ("z", PointField.FLOAT32),
                ("rgb", PointField.FLOAT32), ("depth_below_road", PointField.FLOAT32),
                ("label", PointField.UINT32))
CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4"),
                        ("depth_below_road", "<f4"), ("label", "<u4")])
CLOUD_INDEX = {name: index for index, (name, _) in enumerate(CLOUD_FIELDS)}


def road_cloud(left: np.ndarray, disparity: Any, labels: np.ndarray, road: RoadModel,
               calibration: StereoCalibration) -> np.ndarray:
    """The organized cloud of the left view (structured HxW CLOUD_DTYPE): x, y, z (m, left
    optical frame; NaN where the disparity is invalid), rgb (0x00RRGGBB as float32, as
    stereo_image_proc packs it; grey images give r = g = b), depth below the road (m, NaN where
    not measured) and the pothole label (0 = road). ``disparity`` (float32 HxW, px) NumPy or
    CuPy: on the GPU the points and depths are worked out on the device and read back once
    (after the work already queued on the current stream); ``left`` and ``labels`` are host
    arrays."""
    xp = array_module(disparity)
    height, width = disparity.shape
    v = xp.arange(height)[:, None]
    u = xp.arange(width)[None, :]
    measured = xp.where(xp.isfinite(disparity) & (disparity > 0), disparity,
                        xp.float32(np.nan)).astype(xp.float32, copy=False)
    fields = xp.empty((height, width, len(CLOUD_FIELDS)), xp.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        fields[..., 0], fields[..., 1], fields[..., 2] = calibration.back_project(
            u, v, measured.astype(xp.float64))
        fields[..., CLOUD_INDEX["depth_below_road"]] = depth_below_road(
            xp, u, v, measured, road, calibration)[0]
    cloud = to_host(fields).view(CLOUD_DTYPE)[..., 0]
    colour = left.astype(np.uint32)
    if left.dtype == np.uint16:
        colour >>= 8
    packed = (colour * 0x010101 if colour.ndim == 2
              else (colour[..., 0] << 16) | (colour[..., 1] << 8) | colour[..., 2])
    cloud["rgb"] = packed.astype("<u4", copy=False).view("<f4")
    cloud["label"] = labels
    return cloud


def organized_cloud_message(cloud: np.ndarray, header: Header) -> PointCloud2:
    """sensor_msgs/PointCloud2 of a structured HxW CLOUD_DTYPE array: organized (height H,
    width W), little endian, not dense (NaN points)."""
    fields = [PointField(name=name, offset=CLOUD_DTYPE.fields[name][1], datatype=kind, count=1)
              for name, kind in CLOUD_FIELDS]
    height, width = cloud.shape
    return with_bytes(PointCloud2, cloud, header=header, height=height, width=width,
                      fields=fields, is_bigendian=False, point_step=CLOUD_DTYPE.itemsize,
                      row_step=CLOUD_DTYPE.itemsize * width, is_dense=False)


def organized_cloud_to_array(msg: PointCloud2) -> np.ndarray:
    """The structured HxW CLOUD_DTYPE array of a :func:`organized_cloud_message`."""
    names = [f.name for f in msg.fields]
    if names != [name for name, _ in CLOUD_FIELDS] or msg.point_step != CLOUD_DTYPE.itemsize:
        raise InputError(f"point cloud fields {names} are not the road cloud's")
    return np.frombuffer(bytes(msg.data), dtype=CLOUD_DTYPE).reshape(msg.height,
                                                                    msg.width).copy()


def pointcloud_message(points: np.ndarray, header: Header) -> PointCloud2:
    """sensor_msgs/PointCloud2 (unorganized, little endian) of a POINT_DTYPE array."""
    fields = [PointField(name=name, offset=POINT_DTYPE.fields[name][1], datatype=kind, count=1)
              for name, kind in POINT_FIELDS]
    return with_bytes(PointCloud2, points, header=header, height=1, width=int(points.size),
                      fields=fields, is_bigendian=False, point_step=POINT_DTYPE.itemsize,
                      row_step=POINT_DTYPE.itemsize * int(points.size), is_dense=True)


def pointcloud_to_array(msg: PointCloud2) -> np.ndarray:
    """The POINT_DTYPE array of a PointCloud2 written by :func:`pointcloud_message`."""
    names = [f.name for f in msg.fields]
    if names != [name for name, _ in POINT_FIELDS] or msg.point_step != POINT_DTYPE.itemsize:
        raise InputError(f"point cloud fields {names} are not pothole points")
    return np.frombuffer(bytes(msg.data), dtype=POINT_DTYPE).copy()


def potholes_message(potholes: Sequence[Pothole], road: RoadModel | None, header: Header,
                     observed_range_m: tuple[float, float] = (math.nan, math.nan)
                     ) -> PotholeArray:
    """pothole_detector_msgs/PotholeArray of measured potholes, the frame's road model and the
    observed range of the road (near, far: m along the road; NaN where none was observed).
    Status NOT_OBSERVED where no road was observed and no pothole found beyond it, else
    PROCESSED."""
    seen = any(math.isfinite(value) for value in observed_range_m) or len(potholes) > 0
    msg = PotholeArray(header=header, observed_near_m=float(observed_range_m[0]),
                       observed_far_m=float(observed_range_m[1]),
                       status=PotholeArray.PROCESSED if seen else PotholeArray.NOT_OBSERVED)
    if road is not None:
        msg.a0, msg.a1 = float(road.a0), float(road.a1)
        msg.roll_deg = math.degrees(road.roll_rad)
        msg.inlier_fraction = float(road.inlier_fraction)
    msg.potholes = [
        PotholeMsg(label=p.label, pixels=p.pixels, area_m2=p.area_m2, max_depth_m=p.max_depth_m,
                   mean_depth_m=p.mean_depth_m, volume_m3=p.volume_m3,
                   centroid=Point(x=float(p.centroid_cam_m[0]), y=float(p.centroid_cam_m[1]),
                                  z=float(p.centroid_cam_m[2])),
                   bbox_px=np.asarray(p.bbox_px, dtype=np.uint32))
        for p in potholes
    ]
    return msg


def failed_potholes_message(header: Header, reason: str) -> PotholeArray:
    """The PotholeArray of a stereo set that could not be processed: status FAILED, why."""
    return PotholeArray(header=header, status=PotholeArray.FAILED, reason=reason,
                        observed_near_m=math.nan, observed_far_m=math.nan)


def road_point(u: np.ndarray, v: np.ndarray, road: RoadModel,
               calibration: StereoCalibration) -> np.ndarray:
    """(N, 3) points (m, left optical frame) of the road surface seen at pixels ``u``, ``v``."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    disparity = np.asarray(road.at(np, u, v), dtype=np.float64)
    return np.stack(calibration.back_project(u, v, disparity), axis=-1)


def markers_message(labels: np.ndarray, potholes: Sequence[Pothole], road: RoadModel | None,
                    calibration: StereoCalibration, header: Header,
                    max_outline_points: int = 64) -> MarkerArray:
    """visualization_msgs/MarkerArray: DELETEALL first (old potholes vanish), then per pothole
    its outline on the road surface (LINE_STRIP) and a text label with depth and area."""
    markers = [Marker(header=header, action=Marker.DELETEALL)]
    if road is None:
        return MarkerArray(markers=markers)
    lifetime = Duration(sec=0, nanosec=0)
    for pothole in potholes:
        rows, cols = pothole.window(labels.shape)
        mask = (labels[rows, cols] == pothole.label).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE,
                                       offset=(cols.start, rows.start))
        if not contours:
            continue
        outline = max(contours, key=cv2.contourArea)[:, 0, :]
        stride = max(1, math.ceil(len(outline) / max_outline_points))
        outline = np.concatenate([outline[::stride], outline[:1]])
        corners = road_point(outline[:, 0], outline[:, 1], road, calibration)
        line = Marker(header=header, ns="pothole_outline", id=pothole.label,
                      type=Marker.LINE_STRIP, action=Marker.ADD, lifetime=lifetime,
                      color=ColorRGBA(r=1.0, g=0.2, b=0.1, a=1.0),
                      points=[Point(x=float(x), y=float(y), z=float(z)) for x, y, z in corners])
        line.pose.orientation.w = 1.0
        line.scale.x = 0.01
        text = Marker(header=header, ns="pothole_label", id=pothole.label,
                      type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, lifetime=lifetime,
                      color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
                      text=f"#{pothole.label} {pothole.max_depth_m * 100:.1f} cm "
                           f"{pothole.area_m2 * 1e4:.0f} cm2")
        centroid = pothole.centroid_cam_m
        text.pose.position = Point(x=float(centroid[0]), y=float(centroid[1]),
                                   z=float(centroid[2]))
        text.pose.orientation.w = 1.0
        text.scale.z = 0.04
        markers += [line, text]
    return MarkerArray(markers=markers)


# the road map's cloud: a point per seen cell at its centre, z the road's height there
MAP_FIELDS = (("x", PointField.FLOAT32), ("y", PointField.FLOAT32), ("z", PointField.FLOAT32),
              ("depth_below_road", PointField.FLOAT32), ("sigma", PointField.FLOAT32),
              ("views", PointField.UINT32), ("pothole_id", PointField.UINT32))
MAP_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("depth_below_road", "<f4"),
                      ("sigma", "<f4"), ("views", "<u4"), ("pothole_id", "<u4")])
# OccupancyGrid values: unseen, road, pothole
UNSEEN, ROAD, POTHOLE = -1, 0, 100


def map_cloud_message(view: Any, header: Header) -> PointCloud2:
    """sensor_msgs/PointCloud2 (unorganized, MAP_DTYPE) of a road map's seen cells (``view``: a
    survey.roadmap.MapView): x, y their
    centres in the map frame, z the road's height there (m, up: the negated height below the
    frames' roads), the depth below the local road level (m), the fused height's standard
    deviation (m), the views and the pothole (0 = none, else 1-based in ``view.potholes``)."""
    rows, cols = np.nonzero(view.views > 0)
    cloud = np.zeros(len(rows), MAP_DTYPE)
    cloud["x"] = view.origin[0] + (cols + 0.5) * view.cell_m
    cloud["y"] = view.origin[1] + (rows + 0.5) * view.cell_m
    cloud["z"] = -view.height[rows, cols]
    cloud["depth_below_road"] = view.depth[rows, cols]
    cloud["sigma"] = view.sigma[rows, cols]
    cloud["views"] = view.views[rows, cols]
    cloud["pothole_id"] = view.label[rows, cols]
    fields = [PointField(name=name, offset=MAP_DTYPE.fields[name][1], datatype=kind, count=1)
              for name, kind in MAP_FIELDS]
    return with_bytes(PointCloud2, cloud, header=header, height=1, width=len(cloud),
                      fields=fields, is_bigendian=False, point_step=MAP_DTYPE.itemsize,
                      row_step=MAP_DTYPE.itemsize * len(cloud), is_dense=False)


def occupancy_grid_message(view: Any, header: Header) -> OccupancyGrid:
    """nav_msgs/OccupancyGrid of a road map (a survey.roadmap.MapView) for planners: POTHOLE
    (100) on a pothole's cells, ROAD (0) on the other seen cells, UNSEEN (-1) elsewhere; cell
    [0, 0] at ``view.origin``, rows along y."""
    grid = np.where(view.label > 0, POTHOLE, np.where(view.views > 0, ROAD, UNSEEN))
    height, width = grid.shape
    origin = Pose()
    origin.position.x, origin.position.y = float(view.origin[0]), float(view.origin[1])
    origin.orientation.w = 1.0
    info = MapMetaData(map_load_time=header.stamp, resolution=float(view.cell_m),
                       width=width, height=height, origin=origin)
    cells = np.ascontiguousarray(grid, dtype=np.int8).reshape(-1)
    data: array.array | np.ndarray = cells.copy()
    if messages.ROS:
        data = array.array("b")
        data.frombytes(cells.tobytes())
    return OccupancyGrid(header=header, info=info, data=data)
