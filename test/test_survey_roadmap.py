"""The fused road elevation map (survey/roadmap.py): a frame's road samples, the fusion of
views, the depressions and the rolling window."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.survey.motion import road_frame
from pothole_detector.survey.roadmap import (TILE_CELLS, RoadMap, around_potholes, road_map,
                                             road_patch)


def flat_map(**changes) -> RoadMap:
    settings = dict(cell_m=0.02, level_radius_m=1.5, noise_sigmas=3.0, min_cell_depth_m=0.004,
                    min_area_m2=0.0005, min_depth_m=0.008)
    settings.update(changes)
    return RoadMap(**settings)


def road_with_a_bowl(centre, radius_m, depth_m, slope=(0.0, 0.0), size_m=4.0, cell_m=0.02,
                     noise_m=0.001, seed=0):
    """Samples at every cell centre of a square of road (``size_m`` about ``centre``) that
    rises along ``slope`` (m per m), with a spherical-cap-free bowl: depth_m * (1 - (r/R)^2)."""
    rng = np.random.default_rng(seed)
    steps = np.arange(-size_m / 2, size_m / 2, cell_m) + cell_m / 2
    x, y = np.meshgrid(centre[0] + steps, centre[1] + steps)
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    r = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
    depth = np.where(r < radius_m, depth_m * (1 - (r / radius_m) ** 2), 0.0)
    depth -= slope[0] * (xy[:, 0] - centre[0]) + slope[1] * (xy[:, 1] - centre[1])
    depth += rng.normal(0, noise_m, len(depth))
    return xy, depth, np.full(len(depth), noise_m)


def test_views_fuse_by_inverse_variance():
    roadmap = flat_map()
    centre = np.array([[0.01, 0.01]])  # a cell's centre: the whole sample lands in that cell
    roadmap.add(centre, np.array([0.01]), np.array([0.001]))
    roadmap.add(centre, np.array([0.02]), np.array([0.002]))
    view = roadmap.view((0, 0), (0, 0), potholes_whole=False)
    assert view.height[0, 0] == pytest.approx(0.012, rel=1e-5)
    assert view.sigma[0, 0] == pytest.approx(1 / math.sqrt(1e6 + 2.5e5), rel=1e-5)
    assert view.views[0, 0] == 2 and np.isnan(view.height[0, 1])
    assert list(roadmap.views_at(np.array([[0.015, 0.005], [0.05, 0.05]]))) == [2, 0]


def test_a_sample_between_cells_is_shared_bilinearly():
    roadmap = flat_map()
    roadmap.add(np.array([[0.02, 0.01]]), np.array([0.01]), np.array([0.001]))
    view = roadmap.view((0, 0), (0, 0), potholes_whole=False)
    np.testing.assert_allclose(view.height[0, :2], [0.01, 0.01], rtol=1e-5)
    np.testing.assert_allclose(view.sigma[0, :2], [1 / math.sqrt(0.5e6)] * 2, rtol=1e-5)


@pytest.mark.parametrize("centre", [(1.0, 1.0), (TILE_CELLS * 0.02, TILE_CELLS * 0.02 + 0.05)])
def test_a_bowl_on_a_sloping_road_is_one_pothole_measured(centre):
    """A 3 cm deep bowl of 0.25 m radius on a road rising 2 % across and 3 % along, also where
    it straddles the corner of four tiles: one pothole, at its centre, of about its area,
    depth and volume (a paraboloid holds half its cylinder)."""
    roadmap = flat_map()
    roadmap.add(*road_with_a_bowl(centre, 0.25, 0.03, slope=(0.03, 0.02)))
    (pothole,) = roadmap.potholes()
    assert np.hypot(pothole.xy[0] - centre[0], pothole.xy[1] - centre[1]) < 0.02
    assert pothole.max_depth_m == pytest.approx(0.03, abs=0.004)
    # the bowl is deeper than 3 sigmas (3 mm) out to 95 % of its radius
    assert pothole.area_m2 == pytest.approx(math.pi * 0.25 ** 2 * 0.9, rel=0.15)
    assert pothole.volume_m3 == pytest.approx(math.pi * 0.25 ** 2 * 0.03 / 2, rel=0.15)
    outline = pothole.outline
    assert np.all(np.hypot(outline[:, 0] - centre[0], outline[:, 1] - centre[1]) < 0.28)


def test_noise_and_a_shallow_dip_are_no_pothole():
    roadmap = flat_map()
    roadmap.add(*road_with_a_bowl((1.0, 1.0), 0.25, 0.006, noise_m=0.002))
    assert roadmap.potholes() == []


def test_the_rolling_window_keeps_memory_flat_over_a_long_drive():
    """Ten minutes at 10 m/s (6 km, a patch of road 4 m wide and 6 m long each 0.1 s): the
    live map keeps only the tiles within its radius."""
    roadmap = flat_map(cell_m=0.05)
    steps = np.arange(0, 6.0, 0.05) + 0.025
    x, y = np.meshgrid(steps, np.arange(-2.0, 2.0, 0.05) + 0.025)
    patch = np.stack([x.ravel(), y.ravel()], axis=1)
    depth, sigma = np.zeros(len(patch)), np.full(len(patch), 0.001)
    counts = []
    for frame in range(0, 6000, 20):
        position = (frame * 1.0, 0.0)
        roadmap.add(patch + position, depth, sigma)
        roadmap.forget_beyond(position, 15.0)
        counts.append(len(roadmap.tiles))
    assert max(counts) <= 8 and max(counts[len(counts) // 2:]) == max(counts[:len(counts) // 2])


def test_around_potholes_grows_each_box_by_its_size():
    mask = around_potholes((20, 30), [(10, 8, 11, 9)])
    rows, cols = np.nonzero(mask)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (6, 11, 8, 13)


def test_a_frame_of_the_demo_road_gives_its_potholes_depths(demo_sample):
    """road_patch of the rendered disparity with the pipeline's road: the road's cells lie at
    the road, and each pothole's deepest cell at about its depth."""
    config = Config({"backend": "cpu"})
    result = Pipeline(config, demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    height, width = demo_sample.disparity.shape
    plane = road_frame(result.road, demo_sample.calibration, width, height)
    seen = np.isfinite(demo_sample.disparity)
    road = road_patch(demo_sample.disparity, seen & (demo_sample.labels == 0), result.road,
                      plane, demo_sample.calibration, 0.02)
    assert len(road) > 1000 and abs(np.median(road.depth)) < 0.002
    assert np.all(road.sigma > 0) and np.median(road.sigma) < 0.002
    for index, shape in enumerate(demo_sample.potholes, 1):
        inside = road_patch(demo_sample.disparity, seen & (demo_sample.labels == index),
                            result.road, plane, demo_sample.calibration, 0.02)
        assert inside.depth.max() == pytest.approx(shape.depth_m, rel=0.15, abs=0.003)


def test_the_map_follows_the_parameters():
    roadmap = road_map(Config({"map_cell_m": 0.03, "min_pothole_depth_m": 0.01}))
    assert roadmap.cell_m == 0.03 and roadmap.min_depth_m == 0.01
    assert roadmap.tile_m == pytest.approx(0.03 * TILE_CELLS)
