from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import CPU
from pothole_detector.stages.components import far_corners
from pothole_detector.stages.measure import (MEASURE_SUMS, Extreme, Pothole, Sum,
                                             depth_below_road, keep_large, measure,
                                             measure_potholes, potholes_from_sums, reportable,
                                             road_normal, under_opening, window_of)
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
    count = int(labels.max())
    sums, extremes = measure(CPU, labels, count, disparity, road, demo_sample.calibration)
    potholes = potholes_from_sums(sums[1:], extremes[1:])
    smallest = min(potholes, key=lambda p: p.area_m2)
    kept, keep = keep_large(sums[1:], extremes[1:], smallest.area_m2 * 1.0001)
    assert len(kept) == len(potholes) - 1 and [p.label for p in kept] == list(
        range(1, len(kept) + 1))
    assert not keep[0] and not keep[smallest.label] and keep.sum() == len(kept)
    assert [p.pixels for p in kept] == [p.pixels for p in potholes if p is not smallest]


def test_a_pothole_in_a_far_corner_stays_only_on_mostly_significant_superpixels(demo_sample):
    """Three potholes reach into the top-left corner region: the one of which 3 of 4 pixels
    lie on significant superpixels stays, the half-significant one goes and so does one
    without any; one away from the corners stays regardless."""
    disparity = demo_sample.disparity.astype(np.float32)
    road = fit_road(np, disparity, stride=2)
    height, width = disparity.shape
    superpixels = (np.arange(height)[:, None] // 8) * 1000 + np.arange(width)[None, :] // 8
    superpixels = superpixels.astype(np.int32)
    significant = np.zeros(int(superpixels.max()) + 1, bool)
    labels = np.zeros((height, width), np.int32)
    labels[0:16, 0:16] = 1                 # superpixels 0, 1, 1000, 1001: 3 significant
    significant[[0, 1, 1000]] = True
    labels[0:16, 24:40] = 2                # 3, 4, 1003, 1004: 2 significant
    significant[[3, 4]] = True
    labels[16:32, 0:16] = 3                # none significant
    labels[height - 40:height - 24, 60:76] = 4
    valid = np.isfinite(disparity)
    corners = far_corners(CPU, np.ones_like(valid), 40 / min(height, width))
    assert corners.side == 40
    sums, extremes = measure(CPU, labels, 4, disparity, road, demo_sample.calibration,
                             corners=corners, superpixel_labels=superpixels,
                             significant=significant)
    assert list(sums[1:, Sum.PIXELS]) == [256] * 4
    assert list(sums[1:, Sum.CORNER]) == [256, 256, 256, 0]
    assert list(sums[1:, Sum.SIGNIFICANT]) == [192, 128, 0, 0]
    deep = np.ones((4, MEASURE_SUMS))     # otherwise a possible report
    counts = [Sum.PIXELS, Sum.CORNER, Sum.SIGNIFICANT]
    deep[:, counts] = sums[1:, counts]
    assert list(reportable(deep, 0.0)) == [True, False, False, True]


def test_potholes_from_sums_decode_the_device_table():
    sums = np.zeros((1, MEASURE_SUMS))
    for column, value in ((Sum.PIXELS, 10.0), (Sum.AREA, 0.02), (Sum.VALID_AREA, 0.01),
                          (Sum.FLOOR, 0.008), (Sum.DEPTH_FLOOR, 0.0004), (Sum.X, 0.1),
                          (Sum.Y, 0.2), (Sum.Z, 1.5)):
        sums[0, column] = value
    depth_bits = np.array([0.07], np.float32).view(np.int32)
    extremes = np.zeros((1, len(Extreme)), np.int32)
    for column, value in ((Extreme.LARGEST_DEPTH, depth_bits[0]), (Extreme.U_MIN, 3),
                          (Extreme.V_MIN, 4), (Extreme.U_MAX, 9), (Extreme.V_MAX, 12)):
        extremes[0, column] = value
    (pothole,) = potholes_from_sums(sums, extremes)
    assert pothole.pixels == 10 and pothole.bbox_px == (3, 4, 9, 12)
    assert np.isclose(pothole.max_depth_m, 0.07) and np.isclose(pothole.mean_depth_m, 0.05)
    assert np.isclose(pothole.volume_m3, 0.05 * 0.02)
    np.testing.assert_allclose(pothole.centroid_cam_m, (10.0, 20.0, 150.0))
    negative = np.array([-0.5], np.float32).view(np.int32) ^ np.int32(0x7FFFFFFF)
    extremes[0, Extreme.LARGEST_DEPTH] = negative[0]
    (flat,) = potholes_from_sums(sums, extremes)
    assert np.isclose(flat.max_depth_m, -0.5)


def _grazing(pitch_deg: float, ahead_m: float):
    from pothole_detector.evaluation.synthetic import PotholeShape, Scene, render
    hole = PotholeShape(0.1, ahead_m, 0.4, 0.3, 0.08, 15.0)
    sample = render(Scene(width=640, height=480, focal_px=500.0, baseline_m=0.12,
                          camera_height_m=1.0, pitch_deg=pitch_deg, potholes=(hole,)))
    disparity = sample.disparity.astype(np.float32)
    labels = sample.labels.astype(np.int32)
    road = fit_road(np, np.where(labels > 0, np.nan, disparity), rounds=2)
    return hole, sample, disparity, labels, road


def test_a_pothole_seen_at_a_grazing_angle_measures_like_its_shape():
    """A vehicle rig (1 m high, pitched 15 deg) and a bowl 3 m ahead, seen at about 18 deg:
    area, depth and volume from the exact disparities within the targets of the truth."""
    hole, sample, disparity, labels, road = _grazing(15.0, 3.0)
    (pothole,) = measure_potholes(CPU, labels, 1, disparity, road, sample.calibration)
    assert pothole.area_m2 == pytest.approx(hole.area_m2, rel=0.05)
    assert pothole.max_depth_m == pytest.approx(hole.depth_m, rel=0.05)
    assert pothole.volume_m3 == pytest.approx(hole.volume_m3, rel=0.15)
    np.testing.assert_allclose(pothole.centroid_cam_m, sample.centroid_cam_m(0), atol=0.12)


def test_only_points_under_the_opening_make_the_largest_depth():
    """The bowl 3 m ahead: with exact disparities all but its rim pixels' points lie under its
    opening, also where the image is cut through it; its 4 farthest rows matched 20 % short
    put their points far beyond the far rim, deeper than the bowl, and those are left out."""
    hole, sample, disparity, labels, road = _grazing(15.0, 3.0)
    calibration, normal = sample.calibration, road_normal(road, sample.calibration)

    def opening(labels: np.ndarray, disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows, cols = np.nonzero(labels)
        depth, _ = depth_below_road(np, cols, rows, disparity[rows, cols], road, calibration)
        return rows, under_opening(np, labels, rows, cols, labels[rows, cols], depth,
                                   disparity, normal, calibration)

    rows, exact = opening(labels, disparity)
    assert exact.mean() > 0.99
    far = rows < rows.min() + 4
    mismatched = disparity.copy()
    mismatched[labels > 0] = np.where(far, 0.8, 1.0) * disparity[labels > 0]
    _, wrong = opening(labels, mismatched)
    assert not wrong[far].any() and wrong[~far].mean() > 0.99
    (pothole,) = measure_potholes(CPU, labels, 1, mismatched, road, calibration)
    assert pothole.max_depth_m == pytest.approx(hole.depth_m, rel=0.02)
    columns = np.nonzero(labels.any(axis=0))[0]
    cut = (columns.min() + columns.max()) // 2 + 1
    _, half = opening(labels[:, :cut].copy(), disparity[:, :cut].copy())
    assert half.mean() > 0.99


def test_a_far_pothole_whose_bottom_is_hidden_still_makes_a_sane_report():
    """9 m ahead at 12 deg the near rim hides the bowl's bottom: the area on the road still
    comes out (every ray into the bowl crosses the road plane inside it), the depth is what
    can be seen, positive and finite; rows above the horizon in its label change nothing."""
    hole, sample, disparity, labels, road = _grazing(12.0, 9.0)
    (pothole,) = measure_potholes(CPU, labels, 1, disparity, road, sample.calibration)
    assert pothole.area_m2 == pytest.approx(hole.area_m2, rel=0.15)
    assert 0 < pothole.max_depth_m <= hole.depth_m * 1.05
    assert 0 < pothole.volume_m3 <= hole.volume_m3 * 1.2
    with_sky = labels.copy()
    with_sky[:5] = 1  # rays that never meet the road plane in front of the camera
    assert road.at(np, 320.0, 2.0) < 0
    (widened,) = measure_potholes(CPU, with_sky, 1, disparity, road, sample.calibration)
    assert widened.area_m2 == pytest.approx(pothole.area_m2)
    assert np.isfinite([widened.mean_depth_m, widened.volume_m3, *widened.centroid_cam_m]).all()


def test_depths_above_the_road_count_as_zero_and_reports_need_finite_positive_numbers():
    hole, sample, disparity, labels, road = _grazing(15.0, 3.0)
    raised = np.where(labels > 0, disparity + 3.0, disparity).astype(np.float32)
    depth, footprint = depth_below_road(np, *np.nonzero(labels.T > 0), raised.T[labels.T > 0],
                                        road, sample.calibration)
    assert depth.min() == 0.0 and (footprint > 0).all()
    assert measure_potholes(CPU, labels, 1, raised, road, sample.calibration)[0].volume_m3 == 0
    raised_sums, raised_extremes = measure(CPU, labels, 1, raised, road, sample.calibration)
    assert keep_large(raised_sums[1:], raised_extremes[1:], 0.0)[0] == []
    sums = np.ones((4, MEASURE_SUMS))
    sums[1, Sum.DEPTH_FLOOR] = 0.0     # no depth below the road
    sums[2, Sum.X] = np.inf            # a non-finite sum
    sums[3, Sum.AREA] = 1e-5           # smaller than the area asked for
    assert list(reportable(sums, 1e-4)) == [True, False, False, False]


def test_reports_need_a_depth_between_the_bounds_and_no_deeper_than_wide():
    sums = np.ones((5, MEASURE_SUMS))
    sums[:, Sum.AREA] = 0.04           # 20 cm wide
    sums[:, Sum.FLOOR] = 0.04
    sums[:, Sum.DEPTH_FLOOR] = sums[:, Sum.FLOOR] * np.array([0.05, 0.005, 0.15, 0.25, 0.6])
    assert list(reportable(sums, 1e-4, 0.008, 0.5)) == [True, False, True, False, False]


def test_floor_area_is_the_footprint_on_the_road_and_nothing_at_the_border():
    from pothole_detector.stages.measure import surface_patches
    hole, sample, disparity, labels, road = _grazing(15.0, 3.0)
    height, width = disparity.shape
    v, u = np.mgrid[0:height, 0:width]
    from scipy import ndimage
    # the road away from the pothole, nearer than about 25 m
    road_pixels = ~ndimage.binary_dilation(labels > 0) & (np.nan_to_num(disparity) > 2.5)
    normal = road_normal(road, sample.calibration)
    floor, _ = surface_patches(np, u[road_pixels], v[road_pixels], disparity, normal,
                               sample.calibration)
    _, footprint = depth_below_road(np, u[road_pixels], v[road_pixels],
                                    disparity[road_pixels], road, sample.calibration)
    inner = floor > 0
    assert inner.mean() > 0.99
    np.testing.assert_allclose(floor[inner], footprint[inner], rtol=0.02)
    border, _ = surface_patches(np, np.array([0, width - 1, 5]), np.array([5, 5, 0]),
                                disparity, normal, sample.calibration)
    assert (border == 0).all()


def test_a_flat_floored_pothole_at_a_grazing_angle_has_its_floor_depth():
    """Steep walls, 5 m ahead of a camera 1 m up pitched 12 deg: the far wall is seen face on
    and the near part of the floor is hidden, yet the mean depth over the floor the camera
    sees, and so the volume, come out within 5 % of the shape's."""
    from pothole_detector.evaluation.synthetic import PotholeShape, Scene, render
    hole = PotholeShape(0.1, 5.0, 0.4, 0.3, 0.08, 15.0, wall_power=12.0)
    sample = render(Scene(width=640, height=480, focal_px=500.0, baseline_m=0.12,
                          camera_height_m=1.0, pitch_deg=12.0, potholes=(hole,)))
    disparity = sample.disparity.astype(np.float32)
    labels = sample.labels.astype(np.int32)
    road = fit_road(np, np.where(labels > 0, np.nan, disparity), rounds=2)
    (pothole,) = measure_potholes(CPU, labels, 1, disparity, road, sample.calibration)
    assert pothole.mean_depth_m == pytest.approx(hole.mean_depth_m, rel=0.05)
    assert pothole.volume_m3 == pytest.approx(hole.volume_m3, rel=0.05)


def test_a_hidden_floor_takes_the_depth_halfway_to_the_floor_seen_beyond_it():
    """One column of a pothole on a flat road (disparity 0.5 v px): the edge-on pixel at row
    40 sees 1 cm deep, the floor 2 and 5 rows farther up 3 and 4 cm, a pixel 7 rows up (out of
    reach) 9 cm and one of another pothole 6 cm; pixels not edge-on keep their depth."""
    from pothole_detector.calibration import StereoCalibration
    from pothole_detector.stages.measure import (HIDDEN_FLOOR_BLEND, HIDDEN_FLOOR_ROWS,
                                                 hidden_floor_depth)
    from pothole_detector.stages.road_model import RoadModel
    assert HIDDEN_FLOOR_ROWS == 7
    calibration = StereoCalibration.from_focal_baseline(500.0, 0.1, 80, 60)
    road = RoadModel(a0=0.0, a1=0.5, roll_rad=0.0)
    labels = np.zeros((60, 80), np.int32)
    labels[30:45, 10] = 1
    labels[34, 10] = 2
    depth_m = np.zeros((60, 80))
    depth_m[[38, 35, 34, 33], 10] = [0.03, 0.04, 0.06, 0.09]
    v, u = np.mgrid[30:45, 0:80].astype(np.float64)
    normal = road_normal(road, calibration)
    incidence = normal[0] * (u - calibration.cx) / calibration.f \
        + normal[1] * (v - calibration.cy) / calibration.f + normal[2]
    road_d = road.at(np, u, v)
    disparity = np.full((60, 80), np.nan, np.float32)
    disparity[30:45] = calibration.fb / (calibration.fb / road_d + depth_m[30:45] / incidence)
    rows, cols = np.nonzero(labels)
    label = labels[rows, cols]
    depth, _ = depth_below_road(np, cols, rows, disparity[rows, cols], road, calibration)
    np.testing.assert_allclose(depth, depth_m[rows, cols], atol=1e-6)
    depth = np.where(rows == 40, np.float32(0.01), depth).astype(np.float32)
    edge_on = rows == 40
    estimate = hidden_floor_depth(np, labels, rows, cols, label, depth, edge_on, disparity,
                                  road, calibration)
    at = int(np.nonzero(edge_on)[0][0])
    assert estimate[at] == pytest.approx(0.01 + HIDDEN_FLOOR_BLEND * (0.04 - 0.01), rel=1e-4)
    np.testing.assert_array_equal(np.delete(estimate, at), np.delete(depth, at))
    assert hidden_floor_depth(np, labels, rows, cols, label, depth, np.zeros_like(edge_on),
                              disparity, road, calibration) is depth


def test_the_near_rim_hides_floor_seen_edge_on_and_the_volume_estimate_takes_it_in(
        monkeypatch, near_rim_sample):
    """From the pipeline's smoothed disparities of a pothole whose near rim hides floor: the
    patches that the near rim's step is spread over are seen edge-on (the road away from the
    pothole is not), and estimating the floor behind them brings the volume nearer the
    shape's than the depths seen do; depth and area stay as they were."""
    from scipy import ndimage

    from pothole_detector.stages import measure
    from pothole_detector.stages.refine import SMOOTHING_PX, smooth
    sample = near_rim_sample
    labels = sample.labels.astype(np.int32)
    road = fit_road(np, np.where(labels > 0, np.nan, sample.disparity), rounds=2)
    _, smoothed = smooth(CPU, sample.disparity.astype(np.float32))
    v, u = np.mgrid[0:labels.shape[0], 0:labels.shape[1]]
    _, edge_on = measure.surface_patches(np, u, v, smoothed,
                                         road_normal(road, sample.calibration),
                                         sample.calibration)
    far_road = ~ndimage.binary_dilation(labels > 0, iterations=SMOOTHING_PX)
    far_road &= ndimage.binary_erosion(np.ones_like(far_road), iterations=SMOOTHING_PX)
    hidden_rows = np.nonzero(edge_on & (labels > 0))[0]
    rows = np.nonzero((labels > 0).any(axis=1))[0]
    assert hidden_rows.size > 100 and not (edge_on & far_road).any()
    assert np.median(hidden_rows) > (rows[0] + rows[-1]) / 2  # the near half of the pothole
    (estimated,) = measure.measure_potholes(CPU, labels, 1, smoothed, road, sample.calibration)
    monkeypatch.setattr(measure, "HIDDEN_FLOOR_BLEND", 0.0)
    (seen,) = measure.measure_potholes(CPU, labels, 1, smoothed, road, sample.calibration)
    assert seen.volume_m3 < estimated.volume_m3 < sample.potholes[0].volume_m3
    assert estimated.max_depth_m == seen.max_depth_m and estimated.area_m2 == seen.area_m2


def test_the_extremes_are_each_label_s_box_and_deepest_point_as_ndimage_finds_them(demo_sample):
    """Labels with a gap (a label without pixels: zeros, as ndimage gives) and the demo's
    potholes: the box columns are each label's least and greatest column and row, the largest
    depth column the float32 bits of the greatest depth under the opening."""
    from scipy import ndimage

    disparity = demo_sample.disparity.astype(np.float32)
    road = fit_road(np, disparity, stride=2)
    labels = demo_sample.labels.astype(np.int32)
    count = int(labels.max())
    labels[labels == 2] = 0
    _, extremes = measure(CPU, labels, count, disparity, road, demo_sample.calibration)
    index = np.arange(1, count + 1)
    rows, cols = np.mgrid[0:labels.shape[0], 0:labels.shape[1]]
    for column, function, values in ((Extreme.U_MIN, ndimage.minimum, cols),
                                     (Extreme.V_MIN, ndimage.minimum, rows),
                                     (Extreme.U_MAX, ndimage.maximum, cols),
                                     (Extreme.V_MAX, ndimage.maximum, rows)):
        np.testing.assert_array_equal(extremes[1:, column], function(values, labels, index))
    assert (extremes[2, :] == 0).all() and (extremes[1, Extreme.LARGEST_DEPTH] > 0)


def test_the_window_of_potholes_holds_each_ones_window_and_is_empty_without_any():
    def pothole(label: int, bbox: tuple[int, int, int, int]) -> Pothole:
        return Pothole(label, 10, 0.01, 0.02, 0.01, 0.0001, (0.0, 0.0, 3.0), bbox)

    shape = (40, 60)
    first, second = pothole(1, (10, 5, 20, 8)), pothole(2, (0, 30, 4, 39))
    assert window_of([first], shape) == first.window(shape) == (slice(4, 10), slice(9, 22))
    assert window_of([first, second], shape) == (slice(4, 40), slice(0, 22))
    empty = np.zeros(shape)[window_of([], shape)]
    assert empty.size == 0
