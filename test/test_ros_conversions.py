from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pothole_detector_msgs.msg")

from std_msgs.msg import Header  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from pothole_detector.ros import conversions  # noqa: E402
from pothole_detector.calibration import StereoCalibration  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.stages.measure import window_of  # noqa: E402

HEADER = Header(frame_id="cam")
RNG = np.random.default_rng(3)


def test_disparity_message_marks_invalid_outside_range():
    disparity = np.full((6, 8), 20.5, np.float32)
    disparity[:, :2] = np.nan
    disparity[5, 7] = np.nan
    cal = StereoCalibration(700.0, 0.12, 4.0, 3.0)
    msg = conversions.disparity_message(disparity, cal, (10.0, 90.0), HEADER)
    assert (msg.min_disparity, msg.max_disparity, msg.f, msg.t) == (10.0, 90.0, 700.0, 0.12)
    assert msg.delta_d == pytest.approx(1 / 16)
    window = msg.valid_window
    assert (window.x_offset, window.y_offset, window.width, window.height) == (2, 0, 6, 6)
    np.testing.assert_array_equal(conversions.disparity_from_message(msg), disparity)


def test_points_markers_and_potholes_of_a_real_detection(demo_sample):
    result = Pipeline(Config(), demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    assert result.potholes
    points = conversions.pothole_points(result.labels, result.disparity, result.road,
                                        demo_sample.calibration)
    cloud = conversions.pointcloud_to_array(conversions.pointcloud_message(points, HEADER))
    np.testing.assert_array_equal(cloud, points)
    window = window_of(result.potholes, result.labels.shape)
    assert result.labels[window].size < result.labels.size / 2
    np.testing.assert_array_equal(conversions.pothole_points(
        result.labels, result.disparity, result.road, demo_sample.calibration, window), points)
    assert set(np.unique(cloud["label"])) == {p.label for p in result.potholes}
    for pothole in result.potholes:
        own = cloud[cloud["label"] == pothole.label]
        # the report measures the smoothed disparity; the points are the raw pixels
        assert np.nanmax(own["depth_below_road"]) == pytest.approx(pothole.max_depth_m, rel=0.15)
        assert own["z"].mean() == pytest.approx(pothole.centroid_cam_m[2], rel=0.05)
    markers = conversions.markers_message(result.labels, result.potholes, result.road,
                                          demo_sample.calibration, HEADER).markers
    assert markers[0].action == Marker.DELETEALL
    assert len(markers) == 1 + 2 * len(result.potholes)
    outline = markers[1]
    assert outline.type == Marker.LINE_STRIP and outline.points[0] == outline.points[-1]
    road = demo_sample.calibration.fb / result.road.at(np, np.array([0.0]), np.array([0.0]))
    assert all(0.2 < p.z < 3 * road[0] for p in outline.points)
    for pothole, line in zip(result.potholes, markers[1::2]):
        # traced in the pothole's box: the whole image's outline, thinned to 64 points
        whole = (result.labels == pothole.label).astype(np.uint8)
        contours, _ = cv2.findContours(whole, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        traced = max(contours, key=cv2.contourArea)[:, 0, :]
        traced = traced[::max(1, math.ceil(len(traced) / 64))]
        expected = conversions.road_point(traced[:, 0], traced[:, 1], result.road,
                                          demo_sample.calibration)
        np.testing.assert_allclose([[p.x, p.y, p.z] for p in line.points[:-1]], expected,
                                   rtol=1e-12)
    array = conversions.potholes_message(result.potholes, result.road, HEADER,
                                         result.observed_range_m)
    assert (array.observed_near_m, array.observed_far_m) == result.observed_range_m
    assert array.status == array.PROCESSED
    unobserved = conversions.potholes_message([], None, HEADER)
    assert math.isnan(unobserved.observed_far_m) and unobserved.status == unobserved.NOT_OBSERVED
    beyond = conversions.potholes_message(result.potholes, result.road, HEADER)
    assert math.isnan(beyond.observed_far_m) and beyond.status == beyond.PROCESSED
    failed = conversions.failed_potholes_message(HEADER, "no road plane")
    assert (failed.status, failed.reason, list(failed.potholes)) == (failed.FAILED,
                                                                     "no road plane", [])
    assert array.header.frame_id == "cam"
    assert [p.label for p in array.potholes] == [p.label for p in result.potholes]
    assert array.potholes[0].area_m2 == pytest.approx(result.potholes[0].area_m2)
    assert list(array.potholes[0].bbox_px) == list(result.potholes[0].bbox_px)
    assert array.roll_deg == pytest.approx(math.degrees(result.road.roll_rad))


def test_the_organized_road_cloud_known_answer():
    from pothole_detector.calibration import StereoCalibration
    from pothole_detector.stages.road_model import RoadModel
    calibration = StereoCalibration.from_focal_baseline(100.0, 0.1, 4, 3, 1.5, 1.0)
    disparity = np.full((3, 4), 10.0, np.float32)
    disparity[0, 0] = np.nan
    labels = np.zeros((3, 4), np.int32)
    labels[2, 3] = 7
    left = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    road = RoadModel(np.float64(10.0), np.float64(0.0), 0.0)  # a wall 1 m ahead: depth 0
    cloud = conversions.road_cloud(left, disparity, labels, road, calibration)
    assert cloud.shape == (3, 4) and np.isnan(cloud["z"][0, 0]) and np.isnan(cloud["x"][0, 0])
    assert cloud["z"][1, 1] == pytest.approx(1.0)
    assert cloud["x"][2, 3] == pytest.approx(0.015) and cloud["y"][2, 3] == pytest.approx(0.01)
    grey = int(left[2, 3])
    assert cloud["rgb"][2, 3:4].view("<u4")[0] == (grey << 16) | (grey << 8) | grey
    assert cloud["label"][2, 3] == 7 and cloud["depth_below_road"][1, 1] == pytest.approx(0.0)
    msg = conversions.organized_cloud_message(cloud, HEADER)
    assert (msg.height, msg.width, msg.point_step, msg.is_dense) == (3, 4, 24, False)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb", "depth_below_road", "label"]
    back = conversions.organized_cloud_to_array(msg)
    np.testing.assert_array_equal(back.view(np.uint8), cloud.view(np.uint8))
    rgb = np.zeros((3, 4, 3), np.uint8)
    rgb[..., 0] = 255
    red = conversions.road_cloud(rgb, disparity, labels, road, calibration)
    assert red["rgb"][1, 1:2].view("<u4")[0] == 0xFF0000
