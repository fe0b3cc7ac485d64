from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.errors import NoRoadError
from pothole_detector.stages.road_model import RoadModel, fit_road, moments, solve_roll
from pothole_detector.synthetic import Scene, render


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


def test_row_extremes_match_brute_force():
    model = RoadModel(50.0, 0.2, math.radians(3.0), (1.0, -2.0, 0.5, 3.0, -1.0, 0.7),
                      kind="quadratic")
    full = model.disparity(np, 90, 150, np.float64)
    low, high = model.row_extremes(np, 90, 150)
    np.testing.assert_allclose(low, full.min(axis=1), atol=1e-3)
    np.testing.assert_allclose(high, full.max(axis=1), atol=1e-3)


def test_no_valid_pixels_raise_no_road():
    with pytest.raises(NoRoadError):
        fit_road(np, np.full((20, 20), np.nan, np.float32))
    line = np.full((20, 20), np.nan, np.float32)
    line[5] = 10.0
    with pytest.raises(NoRoadError, match="line"):
        fit_road(np, line)


def test_kernel_args_carry_the_roll_and_only_a_quadratic_models_curvature():
    curvature = (0.5, -1.0, 2.0, 3.0, -1.5, 0.25)
    planar = RoadModel(30.0, 0.4, math.radians(2.0), curvature=curvature)
    quadratic = RoadModel(30.0, 0.4, math.radians(2.0), curvature=curvature, kind="quadratic")
    expected_head = [30.0, 0.4, math.cos(math.radians(2.0)), math.sin(math.radians(2.0))]
    assert list(planar.kernel_args()) == expected_head + [0.0] * 6
    assert list(quadratic.kernel_args()) == expected_head + list(curvature)
    assert all(isinstance(value, np.float64) for value in quadratic.kernel_args())
