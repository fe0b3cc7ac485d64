from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages.measure import depth_below_road, measure_potholes, road_normal
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
