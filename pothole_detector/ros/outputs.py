"""A pipeline result as the output messages, for the live node and the bag tools alike (rclpy's
messages where ROS is installed, else the rosbags typestore's)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Collection, Sequence

import numpy as np

from ..calibration import StereoCalibration
from ..imageio import overlay
from ..method import PipelineResult
from ..recordings.images import array_to_image
from ..stages.measure import window_of
from . import conversions

# output topic (relative) -> ROS message type
OUTPUT_TYPES = {
    "disparity": "stereo_msgs/msg/DisparityImage",
    "disparity_transformed": "sensor_msgs/msg/Image",
    "pothole_labels": "sensor_msgs/msg/Image",
    "pothole_points": "sensor_msgs/msg/PointCloud2",
    "points2": "sensor_msgs/msg/PointCloud2",
    "potholes": "pothole_detector_msgs/msg/PotholeArray",
    "pothole_markers": "visualization_msgs/msg/MarkerArray",
    "overlay": "sensor_msgs/msg/Image",
}
# outputs made only on request (the node: while somebody subscribes); potholes always
ON_REQUEST = tuple(name for name in OUTPUT_TYPES if name != "potholes")
# what `process` writes into bags: all but the organized road cloud, which is for live mapping
# stacks (24 bytes a pixel: 5.5 MB a frame at 640x360)
OFFLINE_OUTPUTS = tuple(name for name in OUTPUT_TYPES if name != "points2")


@dataclass
class Outputs:
    """The messages made for one result, by output name, and the overlay picture (HxWx3 uint8
    RGB) when it was drawn."""

    messages: dict[str, Any] = field(default_factory=dict)
    overlay: np.ndarray | None = None


def output_messages(result: PipelineResult, left: np.ndarray, calibration: StereoCalibration,
                    header: Any, wanted: Collection[str] = ON_REQUEST,
                    ids: Sequence[int] | None = None) -> Outputs:
    """``potholes`` and the outputs named in ``wanted`` for ``result`` of the pair whose left
    image (host, HxW or HxWx3) is ``left``, each stamped with ``header``; with ``ids``
    (tracking.PotholeTracker), pothole k is named ``ids[k - 1]`` in every message. Only the
    arrays these messages need are copied to the host, each once."""
    unknown = set(wanted) - set(OUTPUT_TYPES)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)}; choose from {list(OUTPUT_TYPES)}")
    host: dict[str, np.ndarray] = {}

    renamed = ids is not None and bool(result.potholes)
    potholes = ([replace(p, label=given) for p, given in zip(result.potholes, ids)]
                if renamed else result.potholes)

    def array(name: str) -> np.ndarray:
        if name not in host:
            host[name] = result.host(name)
            if name == "labels" and renamed:
                host[name] = relabel(host[name], result.potholes, ids)
        return host[name]
    made = Outputs()
    messages = made.messages
    messages["potholes"] = conversions.potholes_message(potholes, result.road, header,
                                                        result.observed_range_m)
    if "disparity" in wanted:
        messages["disparity"] = conversions.disparity_message(
            array("disparity"), calibration, result.disparity_range, header)
    if "disparity_transformed" in wanted:
        messages["disparity_transformed"] = array_to_image(
            array("transformed"), "32FC1", header)
    if "pothole_labels" in wanted:
        messages["pothole_labels"] = array_to_image(
            array("labels").astype(np.uint16), "mono16", header)
    if "pothole_points" in wanted:
        points = conversions.pothole_points(array("labels"), array("disparity"), result.road,
                                            calibration,
                                            window_of(result.potholes, result.labels.shape))
        messages["pothole_points"] = conversions.pointcloud_message(points, header)
    if "points2" in wanted:
        messages["points2"] = conversions.organized_cloud_message(
            conversions.road_cloud(left, result.disparity, array("labels"), result.road,
                                   calibration), header)
    if "pothole_markers" in wanted:
        messages["pothole_markers"] = conversions.markers_message(
            array("labels"), potholes, result.road, calibration, header)
    if "overlay" in wanted:
        made.overlay = overlay(left, array("labels"), potholes, array("observed"),
                               array("searched"))
        messages["overlay"] = array_to_image(made.overlay, "rgb8", header)
    return made


def failure_messages(header: Any, reason: str) -> dict[str, Any]:
    """The messages of a stereo set that could not be processed: ``potholes`` with status
    FAILED and ``reason``, so that subscribers can tell a failed set from a lost message."""
    return {"potholes": conversions.failed_potholes_message(header, reason)}


def relabel(labels: np.ndarray, potholes: Sequence[Any], ids: Sequence[int]) -> np.ndarray:
    """``labels`` (int HxW, 0 = road, k = the pothole of label k) with each of ``potholes``
    renamed to its entry of ``ids``."""
    table = np.zeros(max((p.label for p in potholes), default=0) + 1, dtype=np.int64)
    for pothole, given in zip(potholes, ids):
        table[pothole.label] = given
    inside = (labels > 0) & (labels < table.size)
    return np.where(inside, table[np.where(inside, labels, 0)], 0).astype(labels.dtype)
