from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages.threshold import (_tables, histogram_range, histogram_threshold,
                                               neighbour_mean, select_superpixels)


def two_level_map():
    rng = np.random.default_rng(2)
    image = rng.normal(32.0, 0.5, (120, 160)).astype(np.float32)
    image[30:70, 40:100] = rng.normal(20.0, 0.5, (40, 60))
    return image


def brute_force_threshold(g1, g2, candidates):
    best = None
    for t in candidates:
        low = (g1 < t) & (g2 < t)
        high = (g1 >= t) & (g2 >= t)
        if low.sum() == 0 or high.sum() == 0:
            continue
        e2 = sum(((np.stack([g1[m], g2[m]]) - np.array([[g1[m].mean()], [g2[m].mean()]])) ** 2
                  ).sum() for m in (low, high))
        if best is None or e2 < best[0]:
            best = (e2, t)
    return best[1]


def test_neighbour_mean_known_answer():
    image = np.arange(9, dtype=np.float32).reshape(3, 3)
    image[0, 0] = np.nan
    result = neighbour_mean(image)
    assert result[1, 1] == np.float32((1 + 2 + 3 + 5 + 6 + 7 + 8) / 7)
    assert result[0, 0] == np.float32((1 + 3 + 4) / 3)


def test_threshold_splits_pothole_from_road_and_reports_road_mean():
    image = two_level_map()
    t_r, road_mean = histogram_threshold(CPU, image, 0.25, 32.0)
    assert 21.0 < t_r < 31.0
    assert abs(road_mean - 32.0) < 0.1


def test_cumulative_search_equals_brute_force():
    image = two_level_map()
    image[60:80, 10:30] = 26.0
    t_r, _ = histogram_threshold(CPU, image, 0.5, 32.0)
    g2 = neighbour_mean(image)
    candidates = np.arange(15.0, 35.0, 0.5)
    assert abs(brute_force_threshold(image, g2, candidates) - t_r) <= 0.5


def neighbour_mean_reference(image):
    """The array form neighbour_mean's kernel replaces: the same float32 sums in order."""
    valid = np.isfinite(image)
    values = np.pad(np.where(valid, image, 0).astype(np.float32), 1)
    counts = np.pad(valid.astype(np.float32), 1)
    height, width = image.shape
    total = np.zeros((height, width), dtype=np.float32)
    number = np.zeros((height, width), dtype=np.float32)
    for dv in (0, 1, 2):
        for du in (0, 1, 2):
            if dv == 1 and du == 1:
                continue
            total += values[dv:dv + height, du:du + width]
            number += counts[dv:dv + height, du:du + width]
    return np.where(number > 0, total / np.maximum(number, 1), np.nan).astype(np.float32)


def test_neighbour_mean_is_the_array_forms():
    rng = np.random.default_rng(4)
    image = rng.normal(30.0, 5.0, (61, 83)).astype(np.float32)
    image[rng.random(image.shape) < 0.3] = np.nan
    image[:4, :4] = np.nan
    np.testing.assert_array_equal(neighbour_mean(image), neighbour_mean_reference(image))


def tables_reference(transformed, lo, bin_px, n_bins):
    """The array form of the threshold search's tables: bin pairs, then np.bincount."""
    g1 = transformed
    g2 = neighbour_mean_reference(transformed)
    i1 = np.floor((g1 - lo) / bin_px)
    i2 = np.floor((g2 - lo) / bin_px)
    keep = (np.isfinite(i1) & np.isfinite(i2) & (i1 >= 0) & (i2 >= 0) & (i1 < n_bins)
            & (i2 < n_bins)).ravel()
    a, b = g1.astype(np.float64).ravel(), g2.astype(np.float64).ravel()
    high = np.where(keep, np.maximum(i1, i2).ravel(), n_bins).astype(np.int64)
    low = np.where(keep, np.minimum(i1, i2).ravel(), n_bins).astype(np.int64)
    return tuple(np.stack([np.bincount(index, weights=w, minlength=n_bins + 1)[:n_bins]
                           for w in (None, a, b, a * a + b * b)]) for index in (high, low))


def test_the_tables_are_bincounts():
    image = two_level_map()
    image[np.random.default_rng(5).random(image.shape) < 0.1] = np.nan
    image[:5] = 200.0  # outside the histogram's range
    lo, n_bins = histogram_range(0.25, 32.0)
    for got, want in zip(_tables(image, lo, 0.25, n_bins),
                         tables_reference(image, lo, 0.25, n_bins)):
        np.testing.assert_array_equal(got, want)


def test_one_cluster_gives_nan():
    t_r, road_mean = histogram_threshold(CPU, np.full((20, 20), 32.0, np.float32), 0.25, 32.0)
    assert np.isnan(t_r) and np.isnan(road_mean)


def test_selection_needs_low_mean_and_valid_pixels():
    means = np.array([20.0, 31.0, np.nan, 20.0], np.float32)
    valid = np.array([1.0, 1.0, 0.0, 0.0], np.float32)
    np.testing.assert_array_equal(select_superpixels(np, means, valid, 29.6, 0.0),
                                  [True, False, False, False])


def test_the_observed_range_is_the_distance_ahead_along_the_road():
    """A camera 1.2 m above a flat road, pitched 12 deg down, every superpixel whose ray meets
    the road observed (pixel mode, a 0.1 px drop): the range spans the distances ahead, from
    the point below the camera, of the nearest and farthest of their cell centres, the ray's
    meeting with the road worked out in the road's frame; the cells at the side of the farthest
    row lie farther from that point than the range's end but no farther ahead."""
    from pothole_detector.calibration import StereoCalibration
    from pothole_detector.stages import road_model, superpixels
    from pothole_detector.stages.threshold import observation

    calibration = StereoCalibration.from_focal_baseline(800.0, 0.3, 1280, 720)
    height_m, pitch = 1.2, np.radians(12.0)
    f, cy, fb = calibration.f, calibration.cy, calibration.fb
    road = road_model.RoadModel(np.float64(fb / height_m * (np.sin(pitch)
                                                            - np.cos(pitch) * cy / f)),
                                np.float64(fb / f / height_m * np.cos(pitch)),
                                0.0)
    report = np.zeros(road_model.ROAD_REPORT)
    report[road_model.FIT_LAYOUT["FIT_PLANAR_SIGMA"]] = 0.05
    shape, region, downsample = (720, 1280), 32, 2
    found = np.empty(2)
    observed, _ = observation(CPU, shape, region, downsample, road.kernel_params(), report,
                              calibration, 0.0, 0.1, 3.0, observed_range=found)
    u, v = superpixels.cell_centres(np, shape, region, downsample)
    ray_down = (v - cy) / f * np.cos(pitch) + np.sin(pitch)
    ahead = height_m / ray_down * (np.cos(pitch) - (v - cy) / f * np.sin(pitch))
    seen = (ray_down > 0) & (road.at(np, u, v) > 0.1)
    assert np.array_equal(observed, seen) and 0.3 < seen.mean() < 0.9
    np.testing.assert_allclose(found, [ahead[seen].min(), ahead[seen].max()], rtol=1e-9)
    across = (u - calibration.cx) / f * height_m / ray_down
    assert np.hypot(ahead, across)[seen].max() > 1.05 * found[1]


def test_the_threshold_follows_the_noise_of_each_superpixel():
    """With a noise per superpixel, each one's threshold depth is the one its own noise
    resolves: the same drops as the fit's sigma where the noise equals it, deeper thresholds
    and a shorter observed range where it is larger."""
    from pothole_detector.calibration import StereoCalibration
    from pothole_detector.stages import road_model, superpixels
    from pothole_detector.stages.threshold import observation

    calibration = StereoCalibration.from_focal_baseline(800.0, 0.3, 1280, 720)
    height_m, pitch = 1.2, np.radians(12.0)
    f, cy, fb = calibration.f, calibration.cy, calibration.fb
    road = road_model.RoadModel(np.float64(fb / height_m * (np.sin(pitch)
                                                            - np.cos(pitch) * cy / f)),
                                np.float64(fb / f / height_m * np.cos(pitch)), 0.0)
    report = np.zeros(road_model.ROAD_REPORT)
    report[road_model.FIT_LAYOUT["FIT_PLANAR_SIGMA"]] = 0.2
    shape, region, downsample = (720, 1280), 32, 2
    args = (CPU, shape, region, downsample, road.kernel_params(), report, calibration, 0.004,
            0.0, 3.0, 0.03)
    count = superpixels.grid_count(shape, region, downsample)
    fit_range, same_range, noisy_range = np.empty(2), np.empty(2), np.empty(2)
    observed, drops = observation(*args, fit_range)
    same, same_drops = observation(*args, same_range, np.full(count, 0.2))
    noisy, noisy_drops = observation(*args, noisy_range, np.full(count, 0.4))
    np.testing.assert_array_equal(same, observed)
    np.testing.assert_allclose(same_drops, drops)
    np.testing.assert_array_equal(same_range, fit_range)
    assert noisy.sum() < observed.sum() and not (noisy & ~observed).any()
    assert noisy_range[1] < fit_range[1]
    resolved = noisy & (noisy_drops > drops * 1.01)
    assert resolved.any()
