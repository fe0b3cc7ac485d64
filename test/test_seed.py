"""The seed pass (stages/seed.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.backend import CPU
from pothole_detector.calibration import StereoCalibration
from pothole_detector.errors import NoRoadError, NoTextureError
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.stages import matching, seed
from pothole_detector.stages.road_model import RoadModel
from pothole_detector.stages.seed import seed_scale


def test_a_failed_seed_tries_again_without_the_check_then_at_half_the_scale(demo_sample,
                                                                            monkeypatch):
    pipeline = Pipeline(Config({"coarse_scale": 4}), demo_sample.calibration)
    tries: list = []
    seed_at = seed.seed_at

    def failing(backend, matcher, left, right, config, scale, checked, calibration, widest):
        tries.append((scale, checked))
        assert not widest  # 384 px reach past half the reduced width already
        if len(tries) < 3:
            raise NoTextureError("no disparities")
        return seed_at(backend, matcher, left, right, config, scale, checked, calibration,
                       widest)

    monkeypatch.setattr(seed, "seed_at", failing)
    assert pipeline.run(demo_sample.left, demo_sample.right).seeded
    assert tries == [(4, True), (4, False), (2, False)]
    tries.clear()

    def refusing(backend, matcher, left, right, config, scale, checked, calibration, widest):
        tries.append((scale, checked))
        raise NoRoadError("no road")

    monkeypatch.setattr(seed, "seed_at", refusing)
    pipeline.reset()
    with pytest.raises(NoRoadError):
        pipeline.run(demo_sample.left, demo_sample.right)
    assert tries == [(4, True), (4, False), (2, False)]


@pytest.mark.parametrize("matcher", ["opencv", "census"])
def test_a_near_road_beyond_max_disparity_is_seeded_over_the_widest_range(high_survey_sample,
                                                                          matcher, monkeypatch):
    """max_disparity_px 96 leaves the lower rows' road out of the seed's range: matched at
    random there, they hide the road's plane (with no left-right check, which alone would
    drop some of them). The try over half the reduced width finds it."""
    sample = high_survey_sample
    config = Config({"matcher": matcher, "max_disparity_px": 96, "coarse_scale": 2,
                     "lr_max_diff_px": -1})
    matcher_for = matching.Matcher(CPU)
    with pytest.raises(NoRoadError):
        seed.seed_at(CPU, matcher_for, sample.left, sample.right, config, 2, False,
                     sample.calibration)
    tries: list = []
    seed_at = seed.seed_at

    def recording(backend, matcher, left, right, config, scale, checked, calibration, widest):
        tries.append((scale, checked, widest))
        return seed_at(backend, matcher, left, right, config, scale, checked, calibration,
                       widest)

    monkeypatch.setattr(seed, "seed_at", recording)
    road = seed.seed_road(CPU, matcher_for, sample.left, sample.right, config,
                          sample.calibration)
    assert tries == [(2, True, False), (2, False, False), (2, False, True)]
    assert road.roll_deg == pytest.approx(-2.0, abs=0.2)


def test_seed_scale_follows_the_image_width_when_asked():
    assert seed_scale(2079, 4) == 4 and seed_scale(640, 3) == 3
    assert [seed_scale(width, 0) for width in (320, 640, 1280, 2079)] == [1, 1, 2, 4]


def test_the_road_region_is_found_among_walls_cars_and_sky():
    """A coarse map whose road holds 35 % of the valid pixels; a wall, a car and far clutter
    hold the rest. The region search returns the road's plane."""
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:94, 0:310].astype(np.float64)
    scale, offset = 4.0, 1.5
    full_u, full_v = u * scale + offset, v * scale + offset
    road = RoadModel(np.float64(-55.0), np.float64(0.32), math.radians(-1.0))
    coarse = road.at(np, full_u, full_v) / scale + rng.normal(0, 0.2, u.shape)
    coarse[coarse < 1.0] = np.nan
    coarse[:, 220:] = 30.0 / scale + rng.normal(0, 0.2, (94, 90))  # a wall
    coarse[40:80, 60:130] = 25.0 / scale  # a car
    coarse[:40, :220] = 3.0 / scale + rng.normal(0, 0.5, (40, 220))  # trees, far
    kitti = StereoCalibration.from_focal_baseline(721.5, 0.54, 1242, 375)
    found = seed.road_region(coarse.astype(np.float32), scale, offset, kitti, 10.0)
    assert found is not None
    # a plane through three of the road's noisy pixels: the seed's fit refines it
    assert found.roll_deg == pytest.approx(-1.0, abs=1.0)
    assert found.a1 == pytest.approx(0.32, rel=0.1)
    assert found.a0 == pytest.approx(-55.0, abs=8.0)
    assert seed.road_region(np.full((10, 10), np.nan, np.float32), 4.0, 1.5, kitti,
                            10.0) is None
