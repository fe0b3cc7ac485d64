"""The seed pass (stages/seed.py)."""

from __future__ import annotations

import pytest

from pothole_detector.errors import NoRoadError, NoTextureError
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.stages import seed
from pothole_detector.stages.seed import seed_scale


def test_a_failed_seed_tries_again_without_the_check_then_at_half_the_scale(demo_sample,
                                                                            monkeypatch):
    pipeline = Pipeline(Config({"coarse_scale": 4}), demo_sample.calibration)
    tries: list = []
    seed_at = seed.seed_at

    def failing(backend, matcher, left, right, config, scale, checked):
        tries.append((scale, checked))
        if len(tries) < 3:
            raise NoTextureError("no disparities")
        return seed_at(backend, matcher, left, right, config, scale, checked)

    monkeypatch.setattr(seed, "seed_at", failing)
    assert pipeline.run(demo_sample.left, demo_sample.right).seeded
    assert tries == [(4, True), (4, False), (2, False)]
    tries.clear()

    def refusing(backend, matcher, left, right, config, scale, checked):
        tries.append((scale, checked))
        raise NoRoadError("no road")

    monkeypatch.setattr(seed, "seed_at", refusing)
    pipeline.reset()
    with pytest.raises(NoRoadError):
        pipeline.run(demo_sample.left, demo_sample.right)
    assert tries == [(4, True), (4, False), (2, False)]


def test_seed_scale_follows_the_image_width_when_asked():
    assert seed_scale(2079, 4) == 4 and seed_scale(640, 3) == 3
    assert [seed_scale(width, 0) for width in (320, 640, 1280, 2079)] == [1, 1, 2, 4]
