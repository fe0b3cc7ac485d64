"""GPU kernels and stages against the NumPy reference and the CPU backend; skip without a GPU.

Run on a machine with CUDA and CuPy: ``pytest test/test_gpu.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import CPU, get_backend, gpu_available, to_host
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.stages import census_sgm, components, measure, superpixels, threshold
from pothole_detector.stages.matching import to_gray8
from pothole_detector.stages.road_model import fit_road
from pothole_detector.stages.transform import transform_disparity

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")]

P1, P2 = 10, 120


@pytest.fixture(scope="module")
def gpu():
    return get_backend("gpu")


def random_pair(height: int, width: int, shift: int, seed: int):
    rng = np.random.default_rng(seed)
    wide = rng.integers(0, 256, (height, width + shift), dtype=np.uint8)
    noise = rng.integers(0, 6, (height, width), dtype=np.uint8)
    return np.ascontiguousarray(wide[:, shift:]), np.ascontiguousarray(wide[:, :width]) + noise


def run_both(gpu, left, right, kappa, levels, uniqueness=5, lr=1, median=True):
    matcher = census_sgm.GpuMatcher(gpu)
    device = matcher(gpu.upload(left), gpu.upload(right), gpu.upload(kappa.astype(np.int32)),
                     levels, P1, P2, uniqueness, lr, median)
    buffers = matcher._buffers[(left.shape[0], left.shape[1], levels)]
    return matcher, buffers, to_host(device)


CASES = [  # height, width, levels, shift, kappa pattern
    (24, 64, 16, 9, "zero"),
    (23, 37, 32, 5, "ramp"),      # odd sizes
    (1, 40, 16, 3, "zero"),       # one row
    (12, 20, 32, 4, "zero"),      # narrower than the band
    (40, 96, 128, 17, "ramp"),    # 32 lanes per line
    (31, 75, 48, 12, "ramp"),
]


@pytest.mark.parametrize("height,width,levels,shift,pattern", CASES)
def test_census_sgm_kernels_match_the_reference_exactly(gpu, height, width, levels, shift,
                                                        pattern):
    left, right = random_pair(height, width, shift, seed=height * width)
    kappa = (np.arange(height) // 7 if pattern == "ramp" else np.zeros(height)).astype(np.int32)
    _, buffers, disparity = run_both(gpu, left, right, kappa, levels)
    census_left = census_sgm.census_transform(left)
    census_right = census_sgm.census_transform(right)
    np.testing.assert_array_equal(to_host(buffers["census"][0]), census_left)
    np.testing.assert_array_equal(to_host(buffers["census"][1]), census_right)
    cost = census_sgm.matching_cost(census_left, census_right, kappa, levels)
    paths = census_sgm.aggregate(cost, P1, P2)
    np.testing.assert_array_equal(to_host(buffers["paths"]), paths)
    raw = census_sgm.select_disparities(paths, 5, 1)
    np.testing.assert_array_equal(to_host(buffers["raw"]), raw)
    expected = census_sgm.finish(raw, kappa, True)
    np.testing.assert_array_equal(disparity, expected)
    if height > 2 * census_sgm.BORDER_Y and width > 2 * census_sgm.BORDER_X + shift:
        assert np.isfinite(disparity).any()


@pytest.mark.parametrize("uniqueness,lr,median", [(0, -1, False), (30, 0, True), (100, 3, True)])
def test_census_sgm_settings_match_the_reference(gpu, uniqueness, lr, median):
    left, right = random_pair(30, 70, 8, seed=7)
    kappa = np.zeros(30, np.int32)
    _, _, disparity = run_both(gpu, left, right, kappa, 32, uniqueness, lr, median)
    expected = census_sgm.reference_disparity(left, right, kappa, 32, P1, P2, uniqueness, lr,
                                              median)
    np.testing.assert_array_equal(disparity, expected)


def test_textureless_pair_gives_the_same_ties_on_both(gpu):
    flat = np.full((20, 50), 90, np.uint8)
    kappa = np.zeros(20, np.int32)
    _, _, disparity = run_both(gpu, flat, flat, kappa, 16)
    expected = census_sgm.reference_disparity(flat, flat, kappa, 16, P1, P2, 5, 1, True)
    np.testing.assert_array_equal(disparity, expected)
    # every level ties on a flat pair: the tie rule (smallest d) leaves nothing but zero
    assert set(np.unique(expected[np.isfinite(expected)]).tolist()) <= {0.0}


def test_buffers_are_reused_across_frames(gpu):
    left, right = random_pair(24, 64, 9, seed=3)
    kappa = np.zeros(24, np.int32)
    matcher, buffers, first = run_both(gpu, left, right, kappa, 16)
    again = matcher(gpu.upload(left), gpu.upload(right), gpu.upload(kappa), 16, P1, P2, 5, 1,
                    True)
    assert matcher._buffers[(24, 64, 16)]["paths"] is buffers["paths"]
    np.testing.assert_array_equal(to_host(again), first)


def test_upload_many_round_trips(gpu):
    arrays = (np.arange(15, dtype=np.uint8).reshape(3, 5), np.arange(7, dtype=np.int32),
              np.linspace(0, 1, 6, dtype=np.float32).reshape(2, 3))
    for host, device in zip(arrays, gpu.upload_many(*arrays)):
        np.testing.assert_array_equal(to_host(device), host)


# --- the other stages: one body on both backends -------------------------------------------


@pytest.mark.parametrize("height,width,step", [(97, 131, 12), (40, 333, 16), (5, 70, 8)])
def test_slic_kernels_match_the_reference(gpu, height, width, step):
    rng = np.random.default_rng(height)
    v, u = np.mgrid[0:height, 0:width]
    image = (30 + 4 * np.sin(u / 9.0) + 3 * np.cos(v / 7.0)
             + rng.normal(0, 0.3, (height, width))).astype(np.float32)
    valid = rng.random((height, width)) > 0.15
    valid[: height // 3, : width // 4] = False
    labels, n = superpixels.slic(CPU, image, valid, step, 2.0, 6)
    labels_gpu, n_gpu = superpixels.slic(gpu, gpu.upload(image), gpu.upload(valid), step, 2.0, 6)
    assert n_gpu == n
    assert (to_host(labels_gpu) == labels).mean() > 0.999



@pytest.fixture(scope="module")
def road_disparity(demo_sample):
    return demo_sample.disparity.astype(np.float32)


def test_road_fit_matches_the_cpu(gpu, road_disparity):
    cpu = fit_road(np, road_disparity, stride=2, kind="auto")
    dev = fit_road(gpu.xp, gpu.upload(road_disparity), stride=2, kind="auto")
    assert dev.kind == cpu.kind
    np.testing.assert_allclose([dev.a0, dev.a1, dev.roll_rad], [cpu.a0, cpu.a1, cpu.roll_rad],
                               rtol=1e-6, atol=1e-9)
    assert abs(dev.inlier_fraction - cpu.inlier_fraction) < 1e-3


def test_transform_superpixels_threshold_components_measure_match_the_cpu(gpu, demo_sample,
                                                                          road_disparity):
    config = Config()
    road = fit_road(np, road_disparity, stride=2)
    d2_cpu = transform_disparity(np, road_disparity, road, config.delta_dt_px)
    d2_gpu = transform_disparity(gpu.xp, gpu.upload(road_disparity), road, config.delta_dt_px)
    np.testing.assert_allclose(to_host(d2_gpu), d2_cpu, rtol=0, atol=1e-4)
    d2_gpu = gpu.upload(d2_cpu)
    labels_cpu, n = superpixels.superpixels(CPU, d2_cpu, 32, 2.0, 6, 2)
    labels_gpu, n_gpu = superpixels.superpixels(gpu, d2_gpu, 32, 2.0, 6, 2)
    assert n_gpu == n
    assert (to_host(labels_gpu) == labels_cpu).mean() > 0.999
    t_cpu = threshold.histogram_threshold(np, d2_cpu, 0.25, config.delta_dt_px)
    t_gpu = threshold.histogram_threshold(gpu.xp, d2_gpu, 0.25, config.delta_dt_px)
    np.testing.assert_allclose(t_gpu, t_cpu, rtol=1e-6)
    selected = np.isfinite(d2_cpu) & (d2_cpu < t_cpu[1] - 2.0)
    sp = labels_cpu
    found_cpu = components.pothole_components(CPU, selected, np.isfinite(d2_cpu), sp, n, 0.1, 2)
    found_gpu = components.pothole_components(gpu, gpu.upload(selected),
                                              gpu.upload(np.isfinite(d2_cpu)), gpu.upload(sp),
                                              n, 0.1, 2)
    assert found_gpu[1] == found_cpu[1] > 0
    np.testing.assert_array_equal(to_host(found_gpu[0]), found_cpu[0])
    calibration = demo_sample.calibration
    cpu_holes = measure.measure_potholes(CPU, found_cpu[0], found_cpu[1], road_disparity, road,
                                         calibration)
    gpu_holes = measure.measure_potholes(gpu, found_gpu[0], found_gpu[1],
                                         gpu.upload(road_disparity), road, calibration)
    for a, b in zip(cpu_holes, gpu_holes):
        assert a.pixels == b.pixels and a.bbox_px == b.bbox_px
        np.testing.assert_allclose([b.area_m2, b.max_depth_m, b.volume_m3],
                                   [a.area_m2, a.max_depth_m, a.volume_m3], rtol=1e-4)


def test_whole_pipeline_with_census_on_both_backends(demo_sample):
    """The same algorithm on both backends: the GPU kernels and the NumPy reference."""
    config = Config({"matcher": "census"})
    left, right = to_gray8(demo_sample.left), to_gray8(demo_sample.right)
    cpu = Pipeline(config, demo_sample.calibration, CPU).run(left, right)
    gpu = Pipeline(config, demo_sample.calibration, get_backend("gpu")).run(left, right)
    assert gpu.band == cpu.band
    same = to_host(gpu.disparity) == cpu.disparity
    both_invalid = np.isnan(to_host(gpu.disparity)) & np.isnan(cpu.disparity)
    assert (same | both_invalid).mean() > 0.999
    labels_cpu, labels_gpu = cpu.labels > 0, to_host(gpu.labels) > 0
    assert (labels_cpu == labels_gpu).mean() > 0.998
    assert len(gpu.potholes) == len(cpu.potholes) >= 2


def test_gpu_pipeline_finds_the_rendered_potholes(demo_sample):
    result = Pipeline(Config(), demo_sample.calibration, get_backend("gpu")).run(
        demo_sample.left, demo_sample.right)
    assert result.backend == "gpu" and len(result.potholes) >= 2
    truth = demo_sample.labels > 0
    found = to_host(result.labels) > 0
    assert (found & truth).sum() / max(found.sum(), 1) > 0.8
    assert set(result.timings_ms) >= {"sgm", "slic", "total", "host"}
