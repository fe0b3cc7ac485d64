from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages.measure import (depth_below_road, keep_large, measure_potholes,
                                             potholes_from_sums, road_normal)
from pothole_detector.stages.road_model import fit_road


def test_analytic_bowl_depth_area_volume(bowl_sample):
    truth = bowl_sample.potholes[0]
    disparity = bowl_sample.disparity
    labels = bowl_sample.labels.astype(np.int32)
    road = fit_road(np, np.where(labels > 0, np.nan, disparity))
    (pothole,) = measure_potholes(CPU, labels, 1, disparity, road, bowl_sample.calibration)
    assert abs(pothole.max_depth_m - truth.depth_m) / truth.depth_m < 0.05
    assert abs(pothole.area_m2 - truth.area_m2) / truth.area_m2 < 0.05
    assert abs(pothole.volume_m3 - truth.volume_m3) / truth.volume_m3 < 0.10
    assert abs(pothole.mean_depth_m - truth.depth_m / 2) / (truth.depth_m / 2) < 0.10
    centroid = bowl_sample.centroid_cam_m(0)
    assert np.linalg.norm(np.array(pothole.centroid_cam_m) - centroid) < 0.02
    assert pothole.pixels == int((labels == 1).sum())
    rows, cols = np.nonzero(labels == 1)
    assert pothole.bbox_px == (cols.min(), rows.min(), cols.max(), rows.max())


def test_road_points_have_zero_depth(flat_sample):
    road = fit_road(np, flat_sample.disparity)
    height, width = flat_sample.disparity.shape
    v, u = np.mgrid[0:height, 0:width]
    depth, footprint = depth_below_road(np, u, v, flat_sample.disparity, road,
                                        flat_sample.calibration)
    assert np.nanmax(np.abs(depth)) < 1e-3
    assert (footprint > 0).all()
    normal = road_normal(road, flat_sample.calibration)
    assert abs(np.linalg.norm(normal) - 1) < 1e-9 and normal[2] > 0


def test_keep_large_drops_small_potholes_and_renumbers(demo_sample):
    disparity = demo_sample.disparity.astype(np.float32)
    road = fit_road(np, disparity, stride=2)
    labels = demo_sample.labels.astype(np.int32)
    potholes = measure_potholes(CPU, labels, int(labels.max()), disparity, road,
                                demo_sample.calibration)
    smallest = min(potholes, key=lambda p: p.area_m2)
    kept, keep = keep_large(potholes, smallest.area_m2 * 1.0001)
    assert len(kept) == len(potholes) - 1 and [p.label for p in kept] == list(
        range(1, len(kept) + 1))
    assert not keep[0] and not keep[smallest.label] and keep.sum() == len(kept)
    assert [p.pixels for p in kept] == [p.pixels for p in potholes if p is not smallest]


def test_potholes_from_sums_decode_the_device_table():
    sums = np.array([[10.0, 0.02, 0.01, 0.0005, 0.1, 0.2, 1.5]])
    depth_bits = np.array([0.07], np.float32).view(np.int32)
    extremes = np.array([[depth_bits[0], 3, 4, 9, 12]], np.int32)
    (pothole,) = potholes_from_sums(sums, extremes)
    assert pothole.pixels == 10 and pothole.bbox_px == (3, 4, 9, 12)
    assert np.isclose(pothole.max_depth_m, 0.07) and np.isclose(pothole.mean_depth_m, 0.05)
    assert np.isclose(pothole.volume_m3, 0.05 * 0.02)
    np.testing.assert_allclose(pothole.centroid_cam_m, (10.0, 20.0, 150.0))
    negative = np.array([-0.5], np.float32).view(np.int32) ^ np.int32(0x7FFFFFFF)
    (flat,) = potholes_from_sums(sums, np.array([[negative[0], 0, 0, 1, 1]], np.int32))
    assert np.isclose(flat.max_depth_m, -0.5)
