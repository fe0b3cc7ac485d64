from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.calibration import StereoCalibration
from pothole_detector.stages import local_road, road_model, superpixels
from pothole_detector.stages.road_model import RoadModel

DELTA = 32.0
SHAPE = (240, 320)
REGION, DOWNSAMPLE = 16, 2


def flat_road():
    """A camera 1 m above a flat road, looking down 35 deg: its model's kernel parameters."""
    calibration = StereoCalibration(f=300.0, baseline=0.1, cx=160.0, cy=120.0)
    pitch = np.deg2rad(35.0)
    # d = f B / Z on the plane n . P = h, n = (0, cos, sin): d = B (cos (v - cy) / f + sin) f / h
    a1 = calibration.baseline * np.cos(pitch)
    a0 = calibration.baseline * np.sin(pitch) * calibration.f - a1 * calibration.cy
    road = RoadModel(a0=a0, a1=a1, roll_rad=0.0, curvature=(0.0,) * 6, inlier_fraction=1.0,
                     sigma_px=0.2, kind="planar")
    return calibration, road.kernel_params()


def grid(count):
    height, width = SHAPE[0] // DOWNSAMPLE, SHAPE[1] // DOWNSAMPLE
    step = superpixels.grid_step(REGION, DOWNSAMPLE)
    return -(-height // step), -(-width // step)


FIT_SIGMA = 0.37


def fit_report():
    """A road fit report (road_model.FIT_LAYOUT) whose planar robust sigma is FIT_SIGMA."""
    report = np.zeros(road_model.FIT_LAYOUT["ROAD_REPORT"])
    report[road_model.FIT_LAYOUT["FIT_PLANAR_SIGMA"]] = FIT_SIGMA
    return report


def run_with_noise(means, usable=None, drops=0.5, radius_m=1.5):
    calibration, params = flat_road()
    count = superpixels.grid_count(SHAPE, REGION, DOWNSAMPLE)
    usable = np.ones(count, bool) if usable is None else usable
    return local_road.offsets(CPU, means.astype(np.float32), usable, np.full(count, drops),
                              SHAPE, REGION, DOWNSAMPLE, params, calibration, DELTA, radius_m,
                              fit_report())


def run(means, usable=None, drops=0.5, radius_m=1.5):
    return run_with_noise(means, usable, drops, radius_m)[0]


def test_a_road_that_tilts_away_from_the_model_is_followed_and_a_pothole_left_out():
    count = superpixels.grid_count(SHAPE, REGION, DOWNSAMPLE)
    rows, cols = grid(count)
    i, j = np.mgrid[0:rows, 0:cols]
    tilt = 0.08 * (j - cols / 2)  # the road falls to the right, 0.08 px per cell: a camber
    residual = tilt.copy()
    residual[5:8, 3:6] += 2.0  # a pothole 2 px below the road
    found = run(DELTA - residual.ravel()).reshape(rows, cols)
    np.testing.assert_allclose(found, tilt, atol=1e-5)  # means are float32
    below_local = residual - found
    assert abs(below_local[6, 4] - 2.0) < 1e-5 and np.abs(below_local[0]).max() < 1e-5


def test_without_road_around_it_a_superpixel_keeps_the_model():
    count = superpixels.grid_count(SHAPE, REGION, DOWNSAMPLE)
    found = run(np.full(count, DELTA - 3.0), usable=np.zeros(count, bool))
    np.testing.assert_array_equal(found, 0.0)


def test_the_window_reaches_the_radius_on_the_road():
    """A step in the road 1 px deep, 20 cells wide: with a window much smaller than it, the
    cells far inside it take its level; with one far larger, the plane of the whole view."""
    count = superpixels.grid_count(SHAPE, REGION, DOWNSAMPLE)
    rows, cols = grid(count)
    residual = np.zeros((rows, cols))
    residual[:, :10] = 0.3
    small = run(DELTA - residual.ravel(), radius_m=0.05, drops=1.0).reshape(rows, cols)
    assert np.allclose(small[:, 2], 0.3) and np.allclose(small[:, -2], 0.0)
    large = run(DELTA - residual.ravel(), radius_m=50.0, drops=1.0).reshape(rows, cols)
    assert np.ptp(large[:, 2]) < 1e-9 and 0.2 < large[0, 2] < 0.4 and large[0, 2] > large[0, -2]


def test_the_noise_is_the_spread_of_the_road_about_its_local_surface():
    """Superpixel means scattered by 0.1 px about a cambered road, with a pothole: the noise is
    0.1 px wherever the window holds road (the camber and the pothole left out of it); with no
    road around, the road fit's sigma."""
    count = superpixels.grid_count(SHAPE, REGION, DOWNSAMPLE)
    rows, cols = grid(count)
    i, j = np.mgrid[0:rows, 0:cols]
    scatter = np.random.default_rng(3).normal(0.0, 0.1, (rows, cols))
    residual = 0.08 * (j - cols / 2) + scatter
    residual[5:8, 3:6] += 2.0
    _, noise = run_with_noise(DELTA - residual.ravel())
    assert noise.shape == (count,)
    assert np.all(np.abs(noise - 0.1) < 0.03)
    _, none = run_with_noise(DELTA - residual.ravel(), usable=np.zeros(count, bool))
    np.testing.assert_array_equal(none, FIT_SIGMA)


def test_local_tests_measure_each_superpixel_from_the_road_around_it():
    """Threshold drop 0.4 px, noise 0.1 px. Bumps (4 sigmas): 0.5 px above the road is one;
    where the local road itself lies 0.3 px higher, 0.2 px above it is not; a dip is not.
    Depressed (a quarter of the drop, 0.1 px, below the local road) and significant (twice
    the drop): 0.5 px below is depressed only; 1.2 px below where the local road lies 0.2
    px lower is both; 0.95 px below it is depressed only. Unsearched and NaN means are
    none."""
    means = DELTA + np.array([0.0, 0.5, 0.5, -0.5, 0.5, np.nan, -1.2, -0.95], np.float32)
    reference = np.array([0.0, 0.0, -0.3, 0.0, 0.0, 0.0, 0.2, 0.2])
    noise = np.full(8, 0.1)
    drop = np.full(8, 0.4)
    searched = np.array([True, True, True, True, False, True, True, True])
    found = local_road.local_tests(CPU, means, reference, noise, drop, searched, DELTA, 0.25,
                                   2.0, 4.0)
    np.testing.assert_array_equal(found.bumps, [0, 1, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(found.depressed, [0, 0, 0, 1, 0, 0, 1, 1])
    np.testing.assert_array_equal(found.significant, [0, 0, 0, 0, 0, 0, 1, 0])
    np.testing.assert_allclose(found.drop, drop + reference)
    plain = local_road.local_tests(CPU, means, reference, noise, 0.4, searched, DELTA, 0.25,
                                   0.0, 0.0)
    assert plain.significant is None and plain.bumps is None
    np.testing.assert_array_equal(plain.depressed, found.depressed)


def test_pixel_offsets_interpolate_between_cell_centres():
    count = superpixels.grid_count(SHAPE, REGION, DOWNSAMPLE)
    rows, cols = grid(count)
    cell_px = superpixels.grid_step(REGION, DOWNSAMPLE) * DOWNSAMPLE
    values = np.tile(np.arange(cols, dtype=float), rows)
    found = local_road.pixel_offsets(CPU, values, SHAPE, REGION, DOWNSAMPLE)
    assert found.shape == SHAPE and found.dtype == np.float32
    u = np.arange(SHAPE[1])
    expected = np.clip((u + 0.5) / cell_px - 0.5, 0, cols - 1)
    np.testing.assert_allclose(found[37], expected, atol=1e-5)
    constant = local_road.pixel_offsets(CPU, np.full(count, 0.7), SHAPE, REGION, DOWNSAMPLE)
    np.testing.assert_allclose(constant, 0.7, atol=1e-6)


def test_the_flat_road_fixture_is_one_metre_below_the_camera():
    calibration, params = flat_road()
    assert abs(float(road_model.params_height(np, params, calibration)) - 1.0) < 1e-12
