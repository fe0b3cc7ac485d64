"""The fused road elevation map (survey/roadmap.py): a frame's road samples, the fusion of
views, the depressions and the rolling window."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.backend import get_backend, gpu_available
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.survey.motion import road_frame
from pothole_detector.survey.roadmap import (MIN_NOISE_PX, TILE_CELLS, VIEW_SHARE, RoadMap,
                                             RoadPatch, Tile, near_potholes, result_patches,
                                             road_map, road_patch, sample_pixel_sets,
                                             sample_pixels)


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
    """The road of ten minutes at 10 m/s (6 km; a patch of road 4 m wide and 6 m long every
    20 m, each touching the tiles a frame's would): the live map keeps only the tiles within
    its radius, as many at the end as at the start."""
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


def splat_by_bincount(tiles: dict, cell_m: float, xy, depth, sigma) -> None:
    """The fusion's definition in NumPy: each finite sample with sigma > 0 shared over its four
    nearest cell centres bilinearly, per tile and cell the frame's float64 sums (in sample
    order, corners (0, 0), (1, 0), (0, 1), (1, 1) one after the other) added once to the
    float32 sums; a view where the shares sum to VIEW_SHARE."""
    good = np.isfinite(depth) & np.isfinite(sigma) & (sigma > 0) & np.isfinite(xy).all(1)
    grid = np.asarray(xy, np.float64)[good] / cell_m - 0.5
    base = np.floor(grid).astype(np.int64)
    fx, fy = (grid - base).T
    weight = 1.0 / np.square(sigma[good].astype(np.float64))
    corners = [(0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
               (1, 1, fx * fy)]
    cx = np.concatenate([base[:, 0] + dx for dx, _, _ in corners])
    cy = np.concatenate([base[:, 1] + dy for _, dy, _ in corners])
    share = np.concatenate([s for _, _, s in corners])
    w = share * np.tile(weight, 4)
    wz = w * np.tile(depth[good].astype(np.float64), 4)
    size = TILE_CELLS * TILE_CELLS
    for tx, ty in set(zip(cx // TILE_CELLS, cy // TILE_CELLS)):
        mine = (cx // TILE_CELLS == tx) & (cy // TILE_CELLS == ty)
        cells = (cy[mine] - ty * TILE_CELLS) * TILE_CELLS + cx[mine] - tx * TILE_CELLS
        tile = tiles.setdefault((int(tx), int(ty)), Tile.new())
        tile.weight.ravel()[:] += np.bincount(cells, w[mine], size)
        tile.weighted.ravel()[:] += np.bincount(cells, wz[mine], size)
        seen = np.bincount(cells, share[mine], size) >= VIEW_SHARE
        tile.views.ravel()[seen] += 1


def test_the_fusion_adds_each_frame_as_its_definition_does_to_the_bit():
    """Frames of float16 samples over tiles on both sides of the origin, some exactly on cell
    centres (shares of zero), some not finite or with a sigma of zero: the map's tiles equal,
    bit for bit, those of the fusion's definition in NumPy."""
    rng = np.random.default_rng(3)
    roadmap, expected = flat_map(), {}
    for frame in range(40):
        count = int(rng.integers(0, 2000))
        xy = rng.normal(0, 2.0, 2) + rng.normal(0, 1.0, (count, 2))
        if frame % 5 == 0:
            xy = (np.round(xy / 0.02) + 0.5) * 0.02
        depth = rng.normal(0.0, 0.01, count).astype(np.float16)
        sigma = np.abs(rng.normal(0.003, 0.002, count)).astype(np.float16)
        depth[::11], sigma[::13], xy[::17, 0] = np.nan, 0, np.inf
        roadmap.add(xy, depth, sigma)
        splat_by_bincount(expected, 0.02, xy, depth, sigma)
    assert len(expected) > 8 and set(roadmap.tiles) == set(expected)
    for key, tile in expected.items():
        for name in ("weight", "weighted", "views"):
            mine, theirs = getattr(roadmap.tiles[key], name), getattr(tile, name)
            assert mine.dtype == theirs.dtype and np.array_equal(mine, theirs), (key, name)


def test_a_cell_counts_views_up_to_the_uint16_maximum():
    roadmap = flat_map()
    roadmap.add(np.array([[0.01, 0.01]]), np.array([0.01]), np.array([0.001]))
    roadmap.tiles[(0, 0)].views[0, 0] = np.iinfo(np.uint16).max - 1
    for _ in range(3):
        roadmap.add(np.array([[0.01, 0.01]]), np.array([0.01]), np.array([0.001]))
    assert roadmap.tiles[(0, 0)].views[0, 0] == np.iinfo(np.uint16).max

def test_near_potholes_grows_each_box_by_its_size():
    rows, cols = np.nonzero(np.ones((20, 30), bool))
    near = near_potholes(rows * 30 + cols, 30, [(10, 8, 11, 9)])
    assert (rows[near].min(), rows[near].max(), cols[near].min(), cols[near].max()) == \
        (6, 11, 8, 13)


def test_samples_lie_under_half_a_cell_apart_on_the_road(demo_sample):
    """sample_pixels keeps fewer pixels for larger cells, and along the image's middle row
    the kept columns lie at most half a cell apart on the road."""
    config = Config({"backend": "cpu"})
    result = Pipeline(config, demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    shape = demo_sample.disparity.shape
    fine = sample_pixels(shape, result.road, demo_sample.calibration, 0.02)
    coarse = sample_pixels(shape, result.road, demo_sample.calibration, 0.1)
    assert len(np.unique(fine)) == len(fine) and len(coarse) < len(fine) / 4
    rows, cols = np.divmod(coarse, shape[1])
    row = rows[np.argmin(np.abs(rows - shape[0] * 0.75))]
    columns = np.sort(cols[rows == row])
    spacing = np.diff(columns) * demo_sample.calibration.fb / np.nanmedian(
        demo_sample.disparity[row]) / demo_sample.calibration.f
    assert spacing.max() <= 0.05 + 1e-9


def _sample_pixels_reference(shape, road, calibration, cell_m):
    """sample_pixels as array expressions: the reference its kernel gives the bits of."""
    height, width = shape
    row_road = np.asarray(road.at(np, np.full(height, calibration.cx),
                                  np.arange(height, dtype=np.float64)), np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        across = 0.5 * cell_m * row_road / calibration.baseline
        along = 0.5 * cell_m / np.abs(np.gradient(calibration.fb
                                                  / np.where(row_road > 0, row_road, np.nan)))
    column_stride = np.clip(np.nan_to_num(np.floor(across), nan=1.0), 1, 64).astype(np.int64)
    row_stride = np.clip(np.nan_to_num(np.floor(along), nan=1.0), 1, 64).astype(np.int64)
    kept_rows = np.nonzero(np.arange(height) % row_stride == 0)[0]
    parts = [np.zeros(0, np.int64)]
    for stride in np.unique(column_stride[kept_rows]):
        these = kept_rows[column_stride[kept_rows] == stride]
        parts.append((these[:, None] * width + np.arange(0, width, stride)[None, :]).ravel())
    return np.concatenate(parts)


def _road_patch_reference(rows, cols, disparity, road, plane, calibration, cell_m):
    """road_patch as array expressions (bincounts per cell)."""
    f, fb = calibration.f, calibration.fb
    d = np.asarray(disparity, dtype=np.float64)
    u, v = np.asarray(cols, np.float64), np.asarray(rows, np.float64)
    points = np.stack(calibration.back_project(u, v, d), axis=-1)
    normal = -plane.axes[2]
    incidence = ((u - calibration.cx) / f * normal[0] + (v - calibration.cy) / f * normal[1]
                 + normal[2])
    road_d = np.asarray(road.at(np, u, v), dtype=np.float64)
    keep = (road_d > 0) & (incidence > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (fb / d - fb / road_d) * incidence
    z = fb / d
    sigma = z * z * incidence / fb * max(road.sigma_px, MIN_NOISE_PX)
    on_road = plane.from_camera(points[keep])[:, :2]
    depth, sigma = depth[keep], sigma[keep]
    if not len(depth):
        return RoadPatch.empty(cell_m)
    cells = np.floor(on_road / cell_m).astype(np.int64)
    low = cells.min(axis=0)
    span = cells.max(axis=0) - low + 1
    flat = (cells[:, 0] - low[0]) * span[1] + (cells[:, 1] - low[1])
    weight = 1.0 / (sigma * sigma)
    total = np.bincount(flat, weight)
    used = np.nonzero(total)[0]
    mean = np.bincount(flat, weight * depth)[used] / total[used]
    mean_sigma = np.bincount(flat, sigma)[used] / np.bincount(flat)[used]
    cells = np.stack([used // span[1] + low[0], used % span[1] + low[1]], axis=1)
    inside = np.all(np.abs(cells) < np.iinfo(np.int16).max, axis=1)
    return RoadPatch(cells[inside].astype(np.int16), cell_m, mean[inside].astype(np.float16),
                     mean_sigma[inside].astype(np.float16))


def test_samples_and_patches_as_their_array_expressions_give_them(demo_sample):
    """sample_pixels (and sample_pixel_sets, the road's rows worked out once for several
    cells) and road_patch give what their array forms give, pixel for pixel and cell for
    cell, on the demo frame's measured disparity, its road and a sparse and a far subset."""
    config = Config({"backend": "cpu"})
    result = Pipeline(config, demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    height, width = shape = result.disparity.shape
    calibration = demo_sample.calibration
    plane = road_frame(result.road, calibration, width, height)
    cells = (0.02, 0.05, 0.1, 0.3)
    sets = sample_pixel_sets(shape, result.road, calibration, cells)
    measured = result.host("disparity").ravel()
    for cell_m, pixels in zip(cells, sets):
        np.testing.assert_array_equal(pixels, _sample_pixels_reference(
            shape, result.road, calibration, cell_m))
        np.testing.assert_array_equal(pixels, sample_pixels(shape, result.road, calibration,
                                                            cell_m))
        d = measured[pixels]
        good = np.isfinite(d) & (d > 0)
        rows, cols = np.divmod(pixels[good], width)
        for subset in (slice(None), slice(None, None, 7), rows < height // 2):
            args = (rows[subset], cols[subset], d[good][subset], result.road, plane,
                    calibration, cell_m)
            assert road_patch(*args) == _road_patch_reference(*args)
    assert road_patch(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0),
                      result.road, plane, calibration, 0.02) == RoadPatch.empty(0.02)


def test_a_frame_of_the_demo_road_gives_its_potholes_depths(demo_sample):
    """road_patch of the rendered disparity with the pipeline's road: the road's cells lie at
    the road, and each pothole's deepest cell at about its depth; result_patches reads the
    pipeline's own disparity at the sampled pixels, as the host arrays give it."""
    config = Config({"backend": "cpu"})
    result = Pipeline(config, demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    height, width = demo_sample.disparity.shape
    plane = road_frame(result.road, demo_sample.calibration, width, height)
    pixels = sample_pixels((height, width), result.road, demo_sample.calibration, 0.02)
    rows, cols = np.divmod(pixels, width)
    truth = demo_sample.disparity[rows, cols]
    seen = np.isfinite(truth) & (truth > 0)

    def patch(mask):
        return road_patch(rows[mask], cols[mask], truth[mask], result.road, plane,
                          demo_sample.calibration, 0.02)

    road = patch(seen & (demo_sample.labels[rows, cols] == 0))
    assert len(road) > 500 and abs(np.median(road.depth.astype(float))) < 0.002
    assert np.all(road.sigma > 0) and np.median(road.sigma.astype(float)) < 0.002
    for index, shape in enumerate(demo_sample.potholes, 1):
        inside = patch(seen & (demo_sample.labels[rows, cols] == index))
        assert float(inside.depth.max()) == pytest.approx(shape.depth_m, rel=0.15, abs=0.003)
    np.testing.assert_array_equal(result.at("observed", pixels),
                                  result.host("observed").ravel()[pixels])
    measured = result.host("disparity").ravel()[pixels]
    keep = result.host("observed").ravel()[pixels] & (measured > 0)
    assert result_patches(result, [(pixels, 0.02)], plane, demo_sample.calibration) == [
        road_patch(rows[keep], cols[keep], measured[keep], result.road, plane,
                   demo_sample.calibration, 0.02)]
    halves = [(pixels[:len(pixels) // 2], 0.02), (pixels[len(pixels) // 2:], 0.05)]
    assert result_patches(result, halves, plane, demo_sample.calibration) == [
        result_patches(result, [half], plane, demo_sample.calibration)[0] for half in halves]


def test_the_map_follows_the_parameters():
    roadmap = road_map(Config({"map_cell_m": 0.03, "min_pothole_depth_m": 0.01}))
    assert roadmap.cell_m == 0.03 and roadmap.min_depth_m == 0.01
    assert roadmap.tile_m == pytest.approx(0.03 * TILE_CELLS)


def _reads_agree(result, calibration) -> None:
    """A result's values at sampled pixels are its host arrays' there."""
    pixels = sample_pixels(result.disparity.shape, result.road, calibration, 0.02)
    assert result.host("labels").ravel()[pixels].any()
    for name in ("observed", "searched", "disparity", "labels"):
        np.testing.assert_array_equal(result.at(name, pixels),
                                      result.host(name).ravel()[pixels])


def test_the_result_gives_the_sampled_pixels_its_host_arrays_give(demo_sample):
    _reads_agree(Pipeline(Config(), demo_sample.calibration).run(
        demo_sample.left, demo_sample.right), demo_sample.calibration)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
def test_the_gpu_result_gives_the_sampled_pixels_its_host_arrays_give(demo_sample):
    result = Pipeline(Config({"backend": "gpu"}), demo_sample.calibration,
                      get_backend("gpu")).run(demo_sample.left, demo_sample.right)
    assert result.backend == "gpu"
    _reads_agree(result, demo_sample.calibration)
