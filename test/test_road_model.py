from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.errors import NoRoadError
from pothole_detector.stages.road_model import (ROAD_PARAMS, ROAD_REPORT, RoadModel, fit_road,
                                                 model_from_report, moments, solve_roll)
from pothole_detector.evaluation.synthetic import Scene, render


def plane(height=120, width=200, a0=40.0, a1=0.3, roll_deg=2.5):
    model = RoadModel(a0, a1, math.radians(roll_deg))
    return model, model.disparity(np, height, width)


def test_roll_of_an_analytic_plane_is_exact():
    _, disparity = plane()
    model = fit_road(np, disparity, rounds=0)
    assert abs(model.roll_deg - 2.5) < 1e-6
    assert abs(model.a0 - 40.0) < 1e-4 and abs(model.a1 - 0.3) < 1e-6


def test_roll_of_a_rendered_rolled_road_within_002_deg():
    scene = Scene(width=320, height=180, focal_px=214.0, camera_height_m=0.6, pitch_deg=55.0,
                  roll_deg=2.5, supersample=1)
    model = fit_road(np, render(scene).disparity, rounds=2)
    assert abs(model.roll_deg - 2.5) < 0.02


def test_nine_moments_match_least_squares_plane():
    rng = np.random.default_rng(1)
    _, disparity = plane(roll_deg=-4.0)
    noisy = disparity + rng.normal(0, 0.5, disparity.shape).astype(np.float32)
    height, width = noisy.shape
    u = np.arange(width, dtype=np.float64)[None, :]
    v = np.arange(height, dtype=np.float64)[:, None]
    a0, a1, phi, _ = solve_roll(moments(np, noisy, np.ones_like(noisy, bool), u, v))
    uu, vv = np.meshgrid(u.ravel(), v.ravel())
    design = np.stack([np.ones(uu.size), uu.ravel(), vv.ravel()], axis=1)
    p0, pu, pv = np.linalg.lstsq(design, noisy.ravel().astype(np.float64), rcond=None)[0]
    assert math.isclose(a1 * math.cos(phi), pv, rel_tol=1e-9)
    assert math.isclose(-a1 * math.sin(phi), pu, rel_tol=1e-7)
    assert math.isclose(a0, p0, rel_tol=1e-9)


def test_robust_rounds_ignore_a_pothole_and_nans():
    _, disparity = plane()
    corrupted = disparity.copy()
    corrupted[60:90, 80:130] -= 15.0
    corrupted[:10] = np.nan
    plain = fit_road(np, corrupted, rounds=0)
    robust = fit_road(np, corrupted, rounds=3)
    assert abs(plain.roll_deg - 2.5) > 0.05
    assert abs(robust.roll_deg - 2.5) < 1e-3
    expected_inliers = 1 - (30 * 50) / (110 * 200)
    assert abs(robust.inlier_fraction - expected_inliers) < 0.01


def test_auto_picks_quadratic_for_a_crowned_road_only():
    flat = render(Scene(width=320, height=180, focal_px=214.0, camera_height_m=0.6,
                        pitch_deg=55.0, supersample=1)).disparity
    noise = np.random.default_rng(0).normal(0, 0.2, flat.shape).astype(np.float32)
    assert fit_road(np, flat + noise, kind="auto").kind == "planar"
    crowned = render(Scene(width=320, height=180, focal_px=214.0, camera_height_m=0.6,
                           pitch_deg=55.0, crown_per_m=0.1, supersample=1)).disparity
    model = fit_road(np, crowned + noise, kind="auto")
    assert model.kind == "quadratic"
    planar = fit_road(np, crowned + noise, kind="planar")
    errors = [np.nanpercentile(np.abs(crowned - m.disparity(np, *crowned.shape)), 99)
              for m in (model, planar)]
    assert errors[0] < 0.5 * errors[1]


def test_quadratic_model_follows_a_cambered_road_seen_from_a_vehicle():
    """A camber's drop grows like u^2 / p towards the horizon (road_model's docstring): the
    quadratic model follows it to 0.03 px 5 m ahead of a camera 1.2 m up."""
    disparity = render(Scene(width=640, height=360, focal_px=500.0, baseline_m=0.2,
                             camera_height_m=1.2, pitch_deg=10.0, crown_per_m=0.007,
                             supersample=1)).disparity
    seen = disparity >= 20.0  # up to 5 m ahead, where the road is 3.2 m either side
    errors = [np.abs(disparity - fit_road(np, disparity, kind=kind).disparity(
        np, *disparity.shape))[seen].max() for kind in ("quadratic", "planar")]
    assert errors[0] < 0.03 and errors[1] > 0.5


def test_row_extremes_match_brute_force():
    model = RoadModel(50.0, 0.2, math.radians(3.0), (1.0, -2.0, 0.5, 3.0, -1.0, 0.7),
                      kind="quadratic")
    full = model.disparity(np, 90, 150, np.float64)
    low, high = model.row_extremes(np, 90, 150)
    np.testing.assert_allclose(low, full.min(axis=1), atol=1e-3)
    np.testing.assert_allclose(high, full.max(axis=1), atol=1e-3)


@pytest.mark.parametrize("kind", ["planar", "quadratic"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_host_grid_is_the_array_form_to_the_bit(kind, dtype):
    rng = np.random.default_rng(5)
    for a0 in (-30.0, 4.0, 60.0):
        model = RoadModel(np.float64(a0), np.float64(rng.uniform(-0.2, 0.3)),
                          rng.uniform(-0.1, 0.1), tuple(rng.normal(0.0, 2.0, 6)), kind=kind)
        rows, cols = np.arange(37.0)[:, None], np.arange(83.0)[None, :]
        grid = model.disparity(np, 37, 83, dtype)
        assert grid.dtype == dtype
        np.testing.assert_array_equal(grid, model.at(np, cols, rows).astype(dtype))


def test_no_valid_pixels_raise_no_road():
    with pytest.raises(NoRoadError):
        fit_road(np, np.full((20, 20), np.nan, np.float32))
    line = np.full((20, 20), np.nan, np.float32)
    line[5] = 10.0
    with pytest.raises(NoRoadError, match="line"):
        fit_road(np, line)


def test_kernel_params_carry_the_roll_and_only_a_quadratic_models_curvature():
    curvature = (0.5, -1.0, 2.0, 3.0, -1.5, 0.25)
    planar = RoadModel(30.0, 0.4, math.radians(2.0), curvature=curvature)
    quadratic = RoadModel(30.0, 0.4, math.radians(2.0), curvature=curvature, kind="quadratic")
    expected_head = [30.0, 0.4, math.cos(math.radians(2.0)), math.sin(math.radians(2.0))]
    assert list(planar.kernel_params()) == expected_head + [0.0] * 6 + [0.0]
    assert list(quadratic.kernel_params()) == expected_head + list(curvature) + [1.0]
    assert quadratic.kernel_params().dtype == np.float64
    assert len(quadratic.kernel_params()) == ROAD_PARAMS


def _report(planar_sigma: float, quadratic_sigma: float, status: int = 0) -> np.ndarray:
    return np.array([status, 200.0, 30.0, 0.4, 0.03, 150.0, planar_sigma,
                     0.5, -1.0, 2.0, 3.0, -1.5, 0.25, 180.0, quadratic_sigma])


def test_model_from_report_keeps_the_model_fit_road_would_keep():
    report = _report(1.0, 0.8)
    assert len(report) == ROAD_REPORT
    planar = model_from_report(report, "planar", 0.1)
    assert (planar.kind, planar.a0, planar.a1, planar.roll_rad) == ("planar", 30.0, 0.4, 0.03)
    assert planar.inlier_fraction == 0.75 and planar.sigma_px == 1.0
    quadratic = model_from_report(report, "quadratic", 0.1)
    assert quadratic.kind == "quadratic" and quadratic.curvature == tuple(report[7:13])
    assert quadratic.inlier_fraction == 0.9 and quadratic.sigma_px == 0.8
    assert model_from_report(report, "auto", 0.1).kind == "quadratic"
    assert model_from_report(report, "auto", 0.25).kind == "planar"
    assert model_from_report(_report(1.0, 0.9), "auto", 0.1).kind == "planar"


def test_model_from_report_raises_for_a_failed_fit():
    with pytest.raises(NoRoadError, match="fewer than 3"):
        model_from_report(_report(1.0, 0.8, status=1), "auto", 0.1)
    with pytest.raises(NoRoadError, match="line"):
        model_from_report(_report(1.0, 0.8, status=2), "planar", 0.1)


def test_a_prior_keeps_a_wall_of_nearer_disparities_out_of_the_fit():
    """Road beside a wall (40 % of the columns at one nearer disparity): every valid pixel
    tilts the fit; starting from the pixels near the prior road finds the road again."""
    from pothole_detector.stages.road_model import fit_report, model_from_report, prior_params
    rng = np.random.default_rng(4)
    v, u = np.mgrid[0:120, 0:230].astype(np.float64)
    truth = RoadModel(20.0, 0.12, 0.03)
    road = (truth.at(np, u, v) + rng.normal(0, 0.2, u.shape)).astype(np.float32)
    road[:, 140:] = 60.0
    unguided = model_from_report(fit_report(np, road, stride=2), "planar", 0.1)
    assert abs(unguided.roll_deg - truth.roll_deg) > 5
    rough = RoadModel(19.0, 0.125, 0.01)  # a degree off in roll, a pixel off in level
    report = fit_report(np, road, stride=2, prior=prior_params(rough, 4.0))
    guided = model_from_report(report, "planar", 0.1)
    assert abs(guided.roll_deg - truth.roll_deg) < 0.15
    assert guided.a1 == pytest.approx(0.12, rel=5e-3)
    valid = np.isfinite(road[::2, ::2]).sum()
    assert report[1] == valid  # the valid count is every valid pixel, not the prior's
    assert guided.inlier_fraction == pytest.approx(140 / 230, abs=0.02)
    assert np.array_equal(fit_report(np, road, stride=2, prior=prior_params(None, 4.0)),
                          fit_report(np, road, stride=2), equal_nan=True)
    # a stale prior (the road moved): too few pixels near it, so every valid pixel counts
    stale = prior_params(RoadModel(40.0, 0.12, 0.03), 4.0, 0.3)
    assert np.array_equal(fit_report(np, road, stride=2, prior=stale),
                          fit_report(np, road, stride=2), equal_nan=True)


def test_prior_tolerance_follows_the_rig():
    from pothole_detector.calibration import StereoCalibration
    from pothole_detector.stages.road_model import prior_tolerance_px
    calibration = StereoCalibration.from_focal_baseline(1000.0, 0.12, 1280, 720)
    road = RoadModel(10.0, 0.1, 0.0, sigma_px=0.5)
    expected = 0.1 * 1000.0 * math.tan(math.radians(2.0))
    assert prior_tolerance_px(road, calibration, 2.0) == pytest.approx(expected)
    assert prior_tolerance_px(road, calibration, 0.5) == 2.0  # the narrowest band


def test_a_refit_prior_is_the_first_fit_with_the_first_prior_s_band():
    """The first fit's parameters and the prior's tolerance and share; where the first fit
    failed (NaN), no pixel lies near it and the second fit takes every valid pixel."""
    from pothole_detector.stages.road_model import (PRIOR_MIN_SHARE, PRIOR_TOLERANCE,
                                                    ROAD_PARAMS, fit_report, prior_params,
                                                    refit_prior)
    first = RoadModel(20.0, 0.12, 0.03)
    prior = prior_params(RoadModel(19.0, 0.13, 0.0), 3.0, 0.25)
    again = refit_prior(np, first.kernel_params(), prior)
    np.testing.assert_array_equal(again, prior_params(first, 3.0, 0.25))
    failed = refit_prior(np, np.full(ROAD_PARAMS, np.nan), prior)
    assert failed[PRIOR_TOLERANCE] == 3.0 and failed[PRIOR_MIN_SHARE] == 0.25
    v, u = np.mgrid[0:60, 0:80].astype(np.float64)
    road = first.at(np, u, v).astype(np.float32)
    np.testing.assert_array_equal(fit_report(np, road, prior=failed), fit_report(np, road))
