"""Pixel-level refinement (stages/refine.py): rims next to a pothole's superpixels join it."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from pothole_detector.backend import CPU
from pothole_detector.stages.refine import (RIM_REACH_PX, SMOOTHING_PX, extend_occluded,
                                            radius, refine_labels, smooth)
from pothole_detector.stages.road_model import RoadModel
from pothole_detector.stages.transform import transform_disparity

# a road at 32 px everywhere with delta_DT 32: the transformed disparity is the disparity
FLAT = RoadModel(np.float64(32.0), np.float64(0.0), 0.0)


def _scene():
    """Two superpixels (left half 0, right half 1) of a 20x40 map; pothole 1 is labelled at
    columns 8-11 of rows 5-14 of a depression 2 px deep at columns 4-11 of rows 3-16; the road
    (32 px) dips 1 px at columns 12-17 beside it and at 28-33."""
    disparity = np.full((20, 40), 32.0, np.float32)
    disparity[:, 12:18] = 31.0
    disparity[:, 28:34] = 31.0
    disparity[3:17, 4:12] = 30.0
    labels = np.zeros((20, 40), np.int32)
    labels[5:15, 8:12] = 1
    superpixel_labels = np.zeros((20, 40), np.int32)
    superpixel_labels[:, 20:] = 1
    return disparity, labels, superpixel_labels


def _refine(labels, disparity, superpixel_labels, drops, observed, fraction=0.25):
    filled, _ = smooth(CPU, disparity)
    return refine_labels(CPU, labels, filled, FLAT, 32.0, superpixel_labels, np.array(drops),
                         np.array(observed), 4, fraction)


def test_pixels_below_the_road_within_the_radius_join_the_pothole():
    disparity, labels, superpixel_labels = _scene()
    refined = _refine(labels, disparity, superpixel_labels, [2.0, 2.0], [True, True])
    assert refined.dtype == np.int32
    assert np.array_equal(refined[labels > 0], labels[labels > 0])
    grown = (refined == 1) & (labels == 0)
    # within 4 px of the pothole, where the smoothed disparity lies 0.5 px (a quarter of 2) below
    # the road: the rest of the depression left of it, the dip right of it
    rows, cols = np.nonzero(grown)
    assert grown[6:14, 4:8].all() and cols.min() == 4 and cols.max() == 15
    assert rows.min() >= 1 and rows.max() <= 18
    assert not refined[:, 28:34].any()  # the dip far from the pothole stays road


def test_refinement_keeps_to_observed_road_and_deep_enough_pixels():
    disparity, labels, superpixel_labels = _scene()
    unobserved = _refine(labels, disparity, superpixel_labels, [2.0, 2.0], [False, True])
    assert np.array_equal(unobserved, labels)
    shallow = _refine(labels, disparity, superpixel_labels, [8.0, 8.0], [True, True])
    assert np.array_equal(shallow, labels)  # 1 px is less than a quarter of 8
    filled, _ = smooth(CPU, disparity)
    off = refine_labels(CPU, labels, filled, FLAT, 32.0, superpixel_labels,
                        np.array([2.0, 2.0]), np.array([True, True]), 4, 0.0)
    assert off is labels
    assert radius(32) == 16 and radius(10) == 5


def test_road_level_pixels_of_a_potholes_superpixels_leave_it():
    """A square pothole 2 px deep (rows and columns 10-19 of a 30x30 road at 32 px) whose label
    reaches 4 px past its rim, as a superpixel that straddles the rim would: along its straight
    edges the outline lies within two pixels of the rim (the 7x7 mean one pixel out has come
    3 of 7 of the way down, more than half of the 5 of 7 two pixels further in; three pixels
    out 1 of 7, less than half of 3 of 7); its corners, where the mean takes in more road,
    come out rounded; the rest of the label leaves. A pixel with no valid disparity within the
    square keeps its label."""
    disparity = np.full((30, 30), 32.0, np.float32)
    disparity[10:20, 10:20] = 30.0
    disparity[0:7, 0:7] = np.nan
    labels = np.zeros((30, 30), np.int32)
    labels[6:24, 6:24] = 1
    labels[2, 2] = 2
    refined = _refine(labels, disparity, np.zeros((30, 30), np.int32), [0.4], [True])
    assert (refined[12:18, 12:18] == 1).all() and refined[2, 2] == 2
    assert (refined[15, 9:21] == 1).all() and (refined[9:21, 15] == 1).all()
    assert refined[15, 7] == refined[15, 22] == refined[7, 15] == refined[22, 15] == 0
    assert refined[10, 10] == refined[19, 19] == 0
    assert not (refined[3:] == 1)[:, :8].any() and not refined[:, 22:].any()
    assert not refined[3:8].any() and not refined[22:].any()


def test_a_rim_that_slopes_down_loses_at_most_its_outer_reach():
    """A bowl whose rim falls 0.25 px a column over 8 columns, then a 2 px deep floor: the
    labels take the whole slope; at most its outer RIM_REACH_PX columns, less than half as deep
    as the rim that far inside, leave; the rest stays."""
    depth = np.clip(0.25 * (np.arange(40) - 9.5), 0.0, 2.0)
    disparity = np.tile((32.0 - np.minimum(depth, depth[::-1])).astype(np.float32), (30, 1))
    labels = np.zeros((30, 40), np.int32)
    labels[:, 10:30] = 1
    refined = _refine(labels, disparity, np.zeros((30, 40), np.int32), [0.4], [True])
    kept = np.flatnonzero(refined[15] == 1)
    assert 10 < kept.min() <= 10 + RIM_REACH_PX and 29 - RIM_REACH_PX <= kept.max() < 29
    assert (refined[:, 10 + RIM_REACH_PX:30 - RIM_REACH_PX] == 1).all()


def test_smooth_averages_the_valid_neighbours():
    size, half = 2 * SMOOTHING_PX + 1, SMOOTHING_PX // 2
    values = np.arange(size * size, dtype=np.float32).reshape(size, size)
    values[0, 0] = np.nan
    filled, smoothed = smooth(CPU, values)
    assert np.isnan(smoothed[0, 0]) and smoothed.dtype == filled.dtype == np.float32
    centre = SMOOTHING_PX
    assert smoothed[centre, centre] == pytest.approx(values[centre, centre])  # a linear ramp
    square = values[:half + 2, :half + 2]  # the square about (1, 1), clipped at the border
    assert smoothed[1, 1] == pytest.approx(square[np.isfinite(square)].mean(), rel=1e-6)
    square = values[:half + 1, :half + 1]
    assert filled[0, 0] == pytest.approx(square[np.isfinite(square)].mean())
    assert np.array_equal(filled[1:], smoothed[1:]) and np.isfinite(filled).all()
    assert np.isnan(smooth(CPU, np.full((6, 6), np.nan, np.float32))[0]).all()


def test_the_strip_only_the_left_camera_sees_beside_a_right_rim_joins_the_pothole():
    """A floor at 26 px in a road at 32 px: left of the right rim the left camera sees 6 px
    that the right camera does not (the matcher gives them the road's 32 px). Rows 2-5: the
    labels stop at column 19, columns 20-25 join. Row 6: a second pothole at column 23 stops
    the strip at 22. Row 7: columns 24-29 lie in an unobserved superpixel. Row 8: the run's
    end lies within a smoothing square of the border, no floor to read: nothing joins."""
    disparity = np.full((12, 40), 32.0, np.float32)
    disparity[2:9, 8:20] = 26.0
    disparity[8, 0:3] = 26.0
    labels = np.zeros((12, 40), np.int32)
    labels[2:8, 8:20] = 1
    labels[6, 23:33] = 2                # as deep as the road reads there: no strip
    labels[8, 0:2] = 3
    superpixel_labels = np.zeros((12, 40), np.int32)
    superpixel_labels[7, 24:30] = 1
    filled, smoothed = smooth(CPU, np.where(labels > 0, disparity, 32.0).astype(np.float32))
    filled[2:9, 8:20] = 26.0
    out = extend_occluded(CPU, labels, filled, smoothed, FLAT, superpixel_labels,
                          np.array([True, False]))
    assert out.dtype == np.int32
    assert (out[2:6, 20:26] == 1).all() and not out[2:6, 26:].any()
    assert (out[6, 20:23] == 1).all() and (out[6, 23:33] == 2).all() and not out[6, 33:].any()
    assert (out[7, 20:24] == 1).all() and not out[7, 24:].any()
    assert (out[8] == labels[8]).all() and (out[:2] == 0).all() and (out[9:] == 0).all()
    joined = (out > 0) & (labels == 0)
    assert np.isnan(smoothed[joined]).all() and np.isfinite(smoothed[~joined]).all()


def extend_occluded_reference(labels, filled, smoothed, road, superpixel_labels, observed):
    """The array form extend_occluded's kernel replaces."""
    height, width = labels.shape
    labelled = labels > 0
    cols = np.arange(width)
    last = np.maximum.accumulate(np.where(labelled, cols[None, :], -1), axis=1)
    ends = np.nonzero(labelled[:, :-1] & ~labelled[:, 1:])
    inside = ends[1] - (SMOOTHING_PX - 1)
    floor = np.where(inside >= 0, filled[ends[0], np.maximum(inside, 0)], np.nan)
    step = road.at(np, (ends[1] + 1).astype(np.float64), ends[0].astype(np.float64)) - floor
    strip = np.full((height, width), np.nan)
    strip[ends] = step
    end = np.maximum(last, 0)
    joins = ~labelled & (last >= 0) \
        & (cols[None, :] - last <= np.take_along_axis(strip, end, axis=1)) \
        & np.take(observed, superpixel_labels)
    smoothed[joins] = np.nan
    return np.where(joins, np.take_along_axis(labels, end, axis=1), labels).astype(np.int32)


def test_the_strips_are_the_array_forms():
    rng = np.random.default_rng(6)
    height, width = 60, 90
    road = RoadModel(np.float64(20.0), np.float64(0.2), 0.01)
    disparity = (road.disparity(np, height, width)
                 - 6.0 * (rng.random((height, width)) < 0.3)).astype(np.float32)
    labels = (rng.random((height // 6, width // 6)) < 0.3).repeat(6, 0).repeat(6, 1).astype(
        np.int32) * rng.integers(1, 5, (height, width)).astype(np.int32)
    superpixel_labels = (np.arange(height)[:, None] // 15 * 6
                         + np.arange(width)[None, :] // 15).astype(np.int32)
    observed = rng.random(24) < 0.8
    filled, smoothed = smooth(CPU, disparity)
    want_smoothed = smoothed.copy()
    want = extend_occluded_reference(labels, filled, want_smoothed, road, superpixel_labels,
                                     observed)
    got = extend_occluded(CPU, labels, filled, smoothed, road, superpixel_labels, observed)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(smoothed, want_smoothed)
    assert (got != labels).sum() > 20


def refine_labels_reference(labels, filled, road, road_level, superpixel_labels, drops,
                            observed, radius_px, fraction):
    """The array form refine_labels' bounding-box pass replaced: the whole map."""
    below = np.float32(road_level) - transform_disparity(CPU, filled, road, road_level)
    deepest = scipy.ndimage.maximum_filter(np.where(np.isnan(below), -np.inf, below),
                                           size=2 * RIM_REACH_PX + 1, mode="nearest")
    off_step = below < np.float32(0.5) * deepest
    deep = (below > fraction * np.take(drops, superpixel_labels)) \
        & np.take(observed, superpixel_labels) & ~off_step
    near = scipy.ndimage.maximum_filter(labels, size=2 * radius_px + 1, mode="constant")
    return np.where(labels > 0, np.where(off_step, 0, labels),
                    np.where(deep, near, 0)).astype(np.int32)


@pytest.mark.parametrize("box", [(slice(0, 0), slice(0, 0)), (slice(20, 30), slice(40, 55)),
                                 (slice(0, 4), slice(80, 90)), (slice(50, 60), slice(0, 90))])
def test_growth_is_the_whole_map_forms(box):
    rng = np.random.default_rng(7)
    height, width = 60, 90
    road = RoadModel(np.float64(20.0), np.float64(0.2), 0.01)
    disparity = (road.disparity(np, height, width) - rng.normal(0.8, 1.0, (height, width))
                 ).astype(np.float32)
    labels = np.zeros((height, width), np.int32)
    labels[box] = rng.integers(0, 3, labels[box].shape)
    superpixel_labels = (np.arange(height)[:, None] // 15 * 6
                         + np.arange(width)[None, :] // 15).astype(np.int32)
    drops, observed = rng.uniform(0.5, 2.0, 24), rng.random(24) < 0.8
    filled, _ = smooth(CPU, disparity)
    args = (filled, road, 20.0, superpixel_labels, drops, observed, 6, 0.25)
    want = refine_labels_reference(labels, *args)
    np.testing.assert_array_equal(refine_labels(CPU, labels, *args), want)
    assert labels.any() == (want > labels).any()
