from __future__ import annotations

import math

import numpy as np

from pothole_detector.synthetic import PotholeShape, Scene, render


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
