from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.evaluation.synthetic import BumpShape, Paint, PotholeShape, Scene, render


def test_flat_road_disparity_is_the_analytic_plane():
    scene = Scene(width=160, height=120, focal_px=120.0, camera_height_m=1.0, pitch_deg=40.0,
                  supersample=1)
    sample = render(scene)
    v = np.arange(scene.height)[:, None] - (scene.height - 1) / 2
    pitch = math.radians(40.0)
    # a flat road at height h seen with pitch p: 1/Z = (sin p + cos p * y / f) / h
    expected = scene.focal_px * scene.baseline_m * (
        math.sin(pitch) + math.cos(pitch) * v / scene.focal_px) / scene.camera_height_m
    np.testing.assert_allclose(sample.disparity, np.broadcast_to(expected, (120, 160)),
                               rtol=1e-6)


def test_right_view_sees_the_left_pixels_shifted_by_the_disparity():
    scene = Scene(width=200, height=120, focal_px=134.0, camera_height_m=0.6, pitch_deg=55.0,
                  supersample=1, potholes=(PotholeShape(0.0, 0.45, 0.1, 0.08, 0.04),))
    sample = render(scene)
    rows, cols = np.mgrid[0:120, 0:200]
    target = np.rint(cols - sample.disparity).astype(int)
    ok = (target >= 0) & (np.abs(cols - sample.disparity - target) < 0.05)
    left = sample.left[ok].astype(int)
    right = sample.right[rows[ok], target[ok]].astype(int)
    assert np.median(np.abs(left - right)) <= 2


def test_labels_and_truth_of_a_pothole():
    shape = PotholeShape(0.0, 0.45, 0.1, 0.08, 0.04, 30.0)
    assert math.isclose(shape.area_m2, math.pi * 0.008)
    assert math.isclose(shape.volume_m3, shape.area_m2 * 0.02)
    scene = Scene(width=200, height=120, focal_px=134.0, camera_height_m=0.6, pitch_deg=55.0,
                  supersample=1, potholes=(shape,))
    sample = render(scene)
    assert 0 < (sample.labels == 1).sum() < sample.labels.size
    assert set(np.unique(sample.labels)) == {0, 1}
    flat = render(Scene(**{**scene.__dict__, "potholes": ()}))
    inside = sample.labels == 1
    assert (sample.disparity[inside] < flat.disparity[inside] + 1e-4).all()
    assert (sample.disparity[inside] < flat.disparity[inside] - 0.5).any()


def _flat(**changes):
    return Scene(**{**Scene(width=161, height=121, focal_px=120.0, camera_height_m=1.0,
                            pitch_deg=40.0, supersample=1).__dict__, **changes})


def test_a_crest_falls_away_and_a_sag_rises_by_y2_over_2r():
    flat, crest, sag = (render(_flat(grade_radius_m=radius)).disparity
                        for radius in (0.0, 50.0, -50.0))
    assert np.all(crest[:60] < flat[:60]) and np.all(sag[:60] > flat[:60])
    # the optical axis (centre pixel) at optical depth s is at y = s cos p, z = h - s sin p;
    # the crest's surface z = -y^2 / 2R: a quadratic in s
    p, fb = math.radians(40.0), 120.0 * 0.12
    for radius, disparity in ((50.0, crest), (-50.0, sag)):
        a = math.cos(p) ** 2 / (2 * radius)
        s = (math.sin(p) - math.sqrt(math.sin(p) ** 2 - 4 * a * 1.0)) / (2 * a)
        assert disparity[60, 80] == pytest.approx(fb / s, rel=1e-5)
    assert flat[60, 80] == pytest.approx(fb * math.sin(p), rel=1e-5)


def test_bumps_rise_above_the_road_and_paint_changes_only_brightness():
    flat = render(_flat())
    dome = render(_flat(relief=(BumpShape(0.0, 0.84, 0.2, 0.2, 0.05, "dome"),)))
    assert np.nanmax(dome.disparity - flat.disparity) > 0.05 * np.nanmax(flat.disparity) * 0.5
    assert not dome.labels.any()
    for profile in ("disc", "ridge"):
        bump = BumpShape(0.0, 0.0, 0.3, 0.1, 0.04, profile)
        assert -bump.depth_at(np.array([0.0]), np.array([0.0]))[0] == pytest.approx(0.04)
        assert bump.depth_at(np.array([0.31]), np.array([0.0]))[0] == 0.0
    painted = render(_flat(paint=(Paint(0.0, 0.84, 0.3, 0.2, 0.4),)))
    np.testing.assert_array_equal(painted.disparity, flat.disparity)
    assert painted.left.mean() < flat.left.mean()
    assert not painted.labels.any()


def test_sensor_noise_and_the_right_cameras_gain():
    clean = render(_flat())
    noisy = render(_flat(noise_grey=2.0, right_gain=1.05))
    np.testing.assert_array_equal(noisy.disparity, clean.disparity)
    assert 1.0 < np.std(noisy.left.astype(float) - clean.left) < 3.0
    ratio = noisy.right.astype(float).mean() / clean.right.mean()
    assert ratio == pytest.approx(1.05, abs=0.01)


def test_steep_walled_potholes_hold_more_volume():
    bowl = PotholeShape(0.0, 0.0, 0.2, 0.1, 0.1)
    steep = PotholeShape(0.0, 0.0, 0.2, 0.1, 0.1, wall_power=8.0)
    assert bowl.volume_m3 == pytest.approx(bowl.area_m2 * 0.05)
    assert steep.volume_m3 == pytest.approx(steep.area_m2 * 0.08)
    x = np.linspace(-0.199, 0.199, 4001)
    profile = steep.depth_at(x, np.zeros_like(x))
    assert profile.mean() * 0.4 == pytest.approx(np.trapezoid(profile, x), rel=1e-2)
