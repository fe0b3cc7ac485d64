"""The rig matrix (rig_matrix.py): scenes drawn inside each class's view, the same each time."""

from __future__ import annotations

import math

import pytest

from pothole_detector.evaluation.rig_matrix import (RIG_CLASSES, DISTRACTORS, half_width_m,
                                                    sample_scene, visible_range_m)
from pothole_detector.evaluation.synthetic import BumpShape, Scene


def test_visible_range_of_a_known_view():
    scene = Scene(width=640, height=481, focal_px=240.0, camera_height_m=1.0, pitch_deg=45.0)
    near, far = visible_range_m(scene)
    half = math.atan(240.0 / 240.0)  # 45 deg half field of view
    assert near == pytest.approx(1.0 / math.tan(math.radians(45.0) + half), abs=1e-9)
    assert far == math.inf
    assert half_width_m(scene, 1.0) == pytest.approx(math.sqrt(2.0) * 319.5 / 240.0)


@pytest.mark.parametrize("rig", RIG_CLASSES, ids=lambda rig: rig.name)
def test_scenes_are_drawn_inside_the_class_and_the_view(rig):
    for index in range(6):
        scene = sample_scene(rig, index)
        assert scene == sample_scene(rig, index)
        assert (scene.width, scene.height) == (rig.width, rig.height)
        assert rig.focal_px[0] <= scene.focal_px <= rig.focal_px[1]
        assert rig.camera_height_m[0] <= scene.camera_height_m <= rig.camera_height_m[1]
        assert rig.pitch_deg[0] <= scene.pitch_deg <= rig.pitch_deg[1]
        assert abs(scene.roll_deg) <= rig.max_roll_deg
        near, far = visible_range_m(scene)
        assert scene.potholes
        for hole in scene.potholes:
            assert near < hole.y_m < far
            assert abs(hole.x_m) < half_width_m(scene, hole.y_m)
            assert rig.depth_m[0] <= hole.depth_m <= rig.depth_m[1]
        shapes = scene.potholes + tuple(s for s in scene.relief)
        for i, a in enumerate(shapes):
            for b in shapes[i + 1:]:
                assert math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) > max(a.a_m, a.b_m)


def test_clean_scenes_hold_distractors_only():
    kinds = set()
    for rig in RIG_CLASSES:
        for index in range(4):
            scene = sample_scene(rig, index, potholes=0, distractors=len(DISTRACTORS))
            assert not scene.potholes
            kinds |= {type(shape).__name__ for shape in scene.relief}
            kinds |= {paint.kind for paint in scene.paint}
            assert all(shape.depth_m < 0.01 for shape in scene.relief
                       if not isinstance(shape, BumpShape))
    assert kinds == {"BumpShape", "PotholeShape", "line", "ellipse"}
