from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pothole_detector.backend import CPU, get_backend, gpu_available, to_host
from pothole_detector.errors import InputError, NoRoadError, NoTextureError, PotholeError
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.stages import road_model
from pothole_detector.stages.superpixels import cell_centres, grid_count
from pothole_detector.stages.threshold import observation
from pothole_detector.stages import perspective
from pothole_detector.evaluation.synthetic import demo_scene, drive_scenes, render

BACKENDS = ["cpu", pytest.param("gpu", marks=[
    pytest.mark.gpu,
    pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")])]


def detection_coverage(result, sample):
    labels = result.labels
    covered = [((labels > 0) & (sample.labels == k)).sum() / (sample.labels == k).sum()
               for k in range(1, len(sample.potholes) + 1)]
    false = ((labels > 0) & (sample.labels == 0)).sum() / max((labels > 0).sum(), 1)
    return covered, false


def test_finds_every_pothole_where_the_generator_put_it(demo_sample):
    result = Pipeline(Config(), demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    covered, false = detection_coverage(result, demo_sample)
    assert len(result.potholes) == 3
    assert min(covered) > 0.4 and false < 0.1
    assert abs(result.road.roll_deg - 1.5) < 0.3
    for name in ("seed", "sgm", "slic", "threshold", "total"):
        assert result.timings_ms[name] >= 0
    assert result.timings_ms["host"] > 0 and result.timings_ms["host_wait"] == 0.0
    assert result.seeded
    window = (slice(100, 230), slice(37, 301))
    for name in ("labels", "disparity", "observed", "searched"):
        np.testing.assert_array_equal(result.host(name, window), result.host(name)[window])


def test_flat_road_has_no_potholes(flat_sample):
    result = Pipeline(Config(), flat_sample.calibration).run(flat_sample.left, flat_sample.right)
    assert result.potholes == [] and not result.labels.any()
    assert result.road.inlier_fraction > 0.9


def test_second_frame_reuses_the_road_and_matches_the_same(demo_sample):
    pipeline = Pipeline(Config(), demo_sample.calibration)
    first = pipeline.run(demo_sample.left, demo_sample.right)
    second = pipeline.run(demo_sample.left, demo_sample.right)
    assert first.seeded and not second.seeded
    assert len(second.potholes) == len(first.potholes)
    error = np.abs(second.disparity - demo_sample.disparity)
    assert np.nanmedian(error) < 0.3


def test_band_is_worked_out_once_per_road_model_and_follows_it(demo_sample):
    config = Config()
    pipeline = Pipeline(config, demo_sample.calibration)
    shape = demo_sample.left.shape[:2]
    pipeline.run(demo_sample.left, demo_sample.right)
    road = pipeline.road
    assert pipeline._band_memo[0] is road  # run worked out the next frame's band already
    shifts, levels = pipeline.band(shape)
    assert pipeline.band(shape)[0] is shifts
    expected = perspective.band(np, road, *shape, config.gpt_margin_below_px,
                                config.gpt_margin_above_px, config.max_disparity_px,
                                pipeline.shift_mode())
    np.testing.assert_array_equal(shifts, expected[0])
    assert levels == expected[1]
    second = pipeline.run(demo_sample.left, demo_sample.right)
    lowest, highest = perspective.shift_range(shifts, shape[1])
    assert second.band == (lowest, levels)
    assert second.disparity_range == (lowest, highest + levels - 1)
    assert pipeline.road is not road and pipeline.band(shape)[0] is not shifts
    pipeline.reset()
    assert not pipeline.band(shape)[0].any()
    assert pipeline.band(shape)[1] == perspective.round_up_levels(config.max_disparity_px)


def test_gpt_shift_auto_follows_the_matcher(demo_sample):
    def mode(settings):
        return Pipeline(Config(settings), demo_sample.calibration).shift_mode()

    assert mode({}) == "pixel" and mode({"matcher": "opencv"}) == "row"
    assert mode({"gpt_shift": "pixel"}) == "pixel"
    assert mode({"gpt_shift": "row", "matcher": "census"}) == "row"


@pytest.mark.parametrize("matcher", ["opencv", "census"])
def test_pixel_shifts_narrow_the_band_of_a_rolled_rig_and_find_the_same_potholes(matcher):
    """A rig rolled by 6 degrees: the road's slope across a row needs 80 levels with the
    paper's row shifts, 64 with shifts that follow it; both find the three potholes."""
    sample = render(replace(demo_scene(640, 360), roll_deg=6.0))
    found = {}
    for mode in ("row", "pixel"):
        pipeline = Pipeline(Config({"gpt_shift": mode, "matcher": matcher}), sample.calibration)
        pipeline.run(sample.left, sample.right)
        found[mode] = result = pipeline.run(sample.left, sample.right)
        covered, false = detection_coverage(result, sample)
        assert len(result.potholes) == 3 and min(covered) > 0.4 and false < 0.1
        error = np.abs(result.disparity - sample.disparity)
        assert np.nanmedian(error) < 0.3 and np.nanmean(error > 1.0) < 0.01
    assert (found["row"].band[1], found["pixel"].band[1]) == (80, 64)


def test_without_gpt_full_range_gives_the_same_potholes(demo_sample):
    config = Config({"gpt_enabled": False, "max_disparity_px": 128})
    result = Pipeline(config, demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    assert result.band == (0, 128)
    assert len(result.potholes) == 3


def test_metric_threshold_mode(demo_sample):
    config = Config({"threshold_mode": "metres", "delta_pd_m": 0.006})
    pipeline = Pipeline(config, demo_sample.calibration)
    result = pipeline.run(demo_sample.left, demo_sample.right)
    covered, false = detection_coverage(result, demo_sample)
    assert len(result.potholes) == 3 and false < 0.1
    # the drop of delta_pd_m at the superpixel at the image centre (no noise floor), from the
    # frame's road fit; the noise floor only raises it
    shape = demo_sample.left.shape[:2]
    region = pipeline.region_size(shape[1])  # the step of the frame's seeded road
    assert region == demo_sample.left.shape[1] // 64  # the demo rig looks 55 deg down
    report = road_model.fit_report(np, result.disparity, stride=config.road_fit_stride,
                                   kind="planar")

    def drops_with(noise_sigmas):
        return observation(CPU, shape, region, config.slic_downsample,
                           result.road.kernel_params(), report, demo_sample.calibration, 0.006,
                           0.0, noise_sigmas, config.max_threshold_m)[1]

    drops, floored = drops_with(0.0), drops_with(config.threshold_noise_sigmas)
    assert np.all(floored >= drops)
    u, v = cell_centres(np, shape, region, config.slic_downsample)
    centre = int(np.argmin((u - 320.0) ** 2 + (v - 180.0) ** 2))
    road = result.road.at(np, u[centre], v[centre])
    depth = demo_sample.calibration.fb / (road - drops[centre]) \
        - demo_sample.calibration.fb / road
    assert 0.004 < depth < 0.008


def test_run_stream_yields_each_result_or_error_in_order_and_goes_on(demo_sample):
    pipeline = Pipeline(Config(), demo_sample.calibration)
    single = Pipeline(Config(), demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    pairs = [(demo_sample.left, demo_sample.right), (demo_sample.left, demo_sample.right[:, :-2]),
             (demo_sample.left, demo_sample.right)]
    outcomes = list(pipeline.run_stream(iter(pairs)))
    assert len(outcomes) == 3 and isinstance(outcomes[1], InputError)
    first, last = outcomes[0], outcomes[2]
    assert first.seeded and not last.seeded
    np.testing.assert_array_equal(first.disparity, single.disparity)
    assert len(first.potholes) == len(last.potholes) == len(single.potholes)
    assert list(pipeline.run_stream([])) == []


@pytest.mark.parametrize("backend_name", BACKENDS)
def test_run_stream_gives_what_run_gives_frame_by_frame(backend_name):
    """Distinct frames of a drive, a blank pair (refused: the road model carries on to the next
    frame) and a bad pair: every outcome of the stream equals run()'s, the results read only
    after the whole stream ran (on the GPU the next frame is queued before a frame's result is
    built)."""
    samples = [render(scene) for scene in drive_scenes(3, 640, 360, speed_mps=1.5)]
    blank = np.full_like(samples[0].left, 128)
    pairs = [(sample.left, sample.right) for sample in samples]
    pairs[2:2] = [(blank, blank)]
    pairs.append((samples[0].left, samples[0].right[:, :-2]))
    backend = get_backend(backend_name)
    one_by_one = Pipeline(Config(), samples[0].calibration, backend)
    expected: list = []
    for left, right in pairs:
        try:
            expected.append(one_by_one.run(left, right))
        except PotholeError as exc:
            expected.append(exc)
    streamed = list(Pipeline(Config(), samples[0].calibration, backend).run_stream(iter(pairs)))
    assert [type(outcome) for outcome in streamed] == [type(outcome) for outcome in expected]
    assert isinstance(expected[2], NoTextureError) and isinstance(expected[-1], InputError)
    results = [outcome for outcome in streamed if not isinstance(outcome, PotholeError)]
    assert [result.seeded for result in results] == [True, False, False]
    assert not np.array_equal(to_host(expected[0].labels), to_host(expected[1].labels))
    for got, want in zip(streamed, expected):
        if isinstance(want, PotholeError):
            assert str(got) == str(want)
            continue
        for name in ("disparity", "transformed", "labels"):
            np.testing.assert_array_equal(to_host(getattr(got, name)),
                                          to_host(getattr(want, name)))
        assert got.band == want.band and got.threshold_px == want.threshold_px
        assert [p.area_m2 for p in got.potholes] == [p.area_m2 for p in want.potholes]
        assert got.potholes


@pytest.mark.parametrize("matcher", ["opencv", "census"])
def test_blank_frame_after_a_road_is_refused_not_matched_to_the_prior(flat_sample, matcher):
    """With a road model the band starts at the road: a blank pair must not come out as that
    road (SGBM picks the lowest level where every cost is 0)."""
    pipeline = Pipeline(Config({"matcher": matcher}), flat_sample.calibration)
    pipeline.run(flat_sample.left, flat_sample.right)
    blank = np.full_like(flat_sample.left, 128)
    with pytest.raises(NoTextureError, match="texture"):
        pipeline.run(blank, blank)


@pytest.mark.parametrize("matcher", ["census", "opencv"])
def test_bad_inputs_raise_clear_errors(demo_sample, matcher):
    pipeline = Pipeline(Config({"matcher": matcher}), demo_sample.calibration)
    with pytest.raises(InputError, match="equal sizes"):
        pipeline.run(demo_sample.left, demo_sample.right[:, :-2])
    with pytest.raises(InputError, match="8- or 16-bit"):
        pipeline.run(demo_sample.left.astype(np.float32), demo_sample.right)
    flat = np.full_like(demo_sample.left, 128)
    with pytest.raises(NoTextureError, match="texture"):
        pipeline.run(flat, flat)
    noise = np.random.default_rng(0).integers(0, 255, demo_sample.left.shape, dtype=np.uint8)
    other = np.random.default_rng(1).integers(0, 255, demo_sample.left.shape, dtype=np.uint8)
    with pytest.raises((NoRoadError, NoTextureError)):
        pipeline.run(noise, other)


def test_a_dropped_pipeline_is_freed_at_once_and_a_stream_keeps_its_own(demo_sample):
    """No reference cycle holds a pipeline (and the device memory of its buffers and graphs)
    until the next garbage collection; a stream of a pipeline nobody else holds still runs."""
    import gc
    import weakref
    pairs = [(demo_sample.left, demo_sample.right)] * 2
    gc.disable()
    try:
        pipeline = Pipeline(Config(), demo_sample.calibration)
        pipeline.run(*pairs[0])
        list(pipeline.run_stream(pairs))
        alive = weakref.ref(pipeline)
        del pipeline
        assert alive() is None
    finally:
        gc.enable()
    stream = Pipeline(Config(), demo_sample.calibration).run_stream(pairs)
    gc.collect()
    assert [len(result.potholes) for result in stream] == [3, 3]


def test_a_640x480_vehicle_rig_drive_is_processed_frame_by_frame():
    """A vehicle rig 1 m above the road looking 15 deg down at 640x480: its small disparities
    (up to 45 px) leave the seed's full-range left-right check almost nothing to keep, so the
    seed tries again without it; every frame of the drive gets a road with the true roll."""
    from pothole_detector.evaluation.synthetic import vehicle_scene
    samples = [render(vehicle_scene(camera_y_m=0.5 * index)) for index in range(3)]
    pipeline = Pipeline(Config(), samples[0].calibration)
    outcomes = list(pipeline.run_stream((s.left, s.right) for s in samples))
    assert all(not isinstance(outcome, PotholeError) for outcome in outcomes), outcomes
    assert [outcome.seeded for outcome in outcomes] == [True, False, False]
    assert all(abs(outcome.road.roll_deg) < 0.5 for outcome in outcomes)
    for outcome in outcomes:
        assert all(np.isfinite([p.area_m2, p.max_depth_m, p.volume_m3]).all()
                   and p.area_m2 > 0 and p.max_depth_m > 0 for p in outcome.potholes)


def test_the_road_too_far_to_show_a_pothole_is_not_observed_and_searched_by_superpixels(
        demo_sample):
    """A vehicle rig (disparity noise about 0.2 px a pixel) resolves a pothole delta_pd_m deep
    only near the camera: the far road is not observed and the observed range matches the
    geometry; the superpixel means, less noisy, are searched farther, and what they find
    there is the pothole 5 m ahead, nothing else; the demo rig sees all of its road."""
    from pothole_detector.evaluation.synthetic import vehicle_scene
    sample = render(vehicle_scene(pitch_deg=15.0))
    config = Config({"threshold_mode": "metres"})
    result = Pipeline(config, sample.calibration).run(sample.left, sample.right)
    observed, searched = result.host("observed"), result.host("searched")
    labels = result.host("labels")
    assert observed.shape == sample.left.shape and 0.1 < observed.mean() < 0.9
    assert observed.mean() < searched.mean() < 0.9
    assert not (labels[~searched] > 0).any()
    beyond = (labels > 0) & ~observed
    assert beyond.any() and np.mean(sample.labels[beyond] == 2) > 0.7
    near, far = result.observed_range_m
    assert 0 < near < far < 6
    # the resolvable depth at the far end of the observed road, from the geometry alone
    rows = np.nonzero(observed.any(axis=1))[0]
    top = rows.min()
    height = sample.calibration.fb / np.linalg.norm(
        [-result.road.a1 * np.sin(result.road.roll_rad) * sample.calibration.f,
         result.road.a1 * np.cos(result.road.roll_rad) * sample.calibration.f,
         result.road.at(np, sample.calibration.cx, sample.calibration.cy)])
    assert height == pytest.approx(1.0, rel=0.05)
    z_top = sample.calibration.fb / result.road.at(np, sample.calibration.cx, float(top))
    pitch = np.radians(15.0)
    assert far == pytest.approx((z_top - height * np.sin(pitch)) / np.cos(pitch), rel=0.1)
    everywhere = Pipeline(config, demo_sample.calibration).run(demo_sample.left,
                                                                demo_sample.right)
    assert everywhere.host("observed").all() and np.isfinite(everywhere.observed_range_m).all()


def test_superpixels_shrink_for_a_road_seen_at_a_grazing_angle(demo_sample):
    """The SLIC grid step follows the seeded road: a vehicle rig looking 15 deg down (rows
    foreshorten its road about four times) gets the smallest step, the demo rig (55 deg) the
    whole width / 64, and a step stays until the next seed."""
    from pothole_detector.evaluation.synthetic import vehicle_scene
    sample = render(vehicle_scene(width=1280, height=720, pitch_deg=15.0))
    pipeline = Pipeline(Config(), sample.calibration)
    assert pipeline.region_size(1280) == 20
    first = pipeline.run(sample.left, sample.right)
    assert pipeline.region_size(1280) == 10 and first.seeded
    assert np.unique(first.host("superpixels")).size > 3 * grid_count((720, 1280), 20, 2)
    steep = Pipeline(Config(), demo_sample.calibration)
    steep.run(demo_sample.left, demo_sample.right)
    assert steep.region_size(640) == 10
    second = pipeline.run(sample.left, sample.right)
    assert not second.seeded and pipeline.region_size(1280) == 10


def test_a_refused_frame_keeps_the_last_accepted_road_once(demo_sample):
    """A refused frame (no texture) leaves the last accepted road for the next frame; a second
    refusal in a row, or a refusal with no accepted road since the seed, resets."""
    blank = np.full_like(demo_sample.left, 128)
    pipeline = Pipeline(Config(), demo_sample.calibration)
    accepted = pipeline.run(demo_sample.left, demo_sample.right).road
    with pytest.raises(NoTextureError):
        pipeline.run(blank, blank)
    assert pipeline.road is accepted
    with pytest.raises(NoTextureError):
        pipeline.run(blank, blank)
    assert pipeline.road is None
    strict = Pipeline(Config({"min_road_inlier_fraction": 1.0}), demo_sample.calibration)
    with pytest.raises(NoRoadError):
        strict.run(demo_sample.left, demo_sample.right)
    assert strict.road is None


@pytest.mark.parametrize("backend_name", BACKENDS)
def test_a_seeded_frame_fits_its_road_again_from_its_own_first_fit(backend_name):
    """A seed whose slope is a third too steep: within the prior's 2 px lie the rows of the top
    42 % of the frame only, and the fit from the seed takes those; on a frame the seed pass
    ran on, the fit runs again from its own road and takes in the whole road."""
    from pothole_detector.calibration import StereoCalibration
    from pothole_detector.stages.road_model import RoadModel, model_from_report, prior_params
    backend = get_backend(backend_name)
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:120, 0:230].astype(np.float64)
    truth = RoadModel(20.0, 0.12, 0.03)
    disparity = (truth.at(np, u, v) + rng.normal(0, 0.2, u.shape)).astype(np.float32)
    seed = RoadModel(20.0, 0.16, 0.03)
    prior = backend.upload(prior_params(seed, 2.0, 0.2))
    pipeline = Pipeline(Config({"road_model": "planar", "road_fit_stride": 2}),
                        StereoCalibration.from_focal_baseline(500.0, 0.1, 230, 120), backend)
    fits = {}
    for seeded in (False, True):
        report, _ = pipeline.fit_road(backend.upload(disparity), prior, seeded)
        fits[seeded] = model_from_report(to_host(report), "planar", 0.1)
    assert fits[False].inlier_fraction == pytest.approx(0.42, abs=0.04)
    assert fits[True].inlier_fraction > 0.95
    for fit in fits.values():
        assert abs(fit.roll_deg - truth.roll_deg) < 0.2 and fit.a1 == pytest.approx(0.12, 0.02)
