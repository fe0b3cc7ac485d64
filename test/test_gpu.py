"""GPU kernels and stages against the NumPy reference and the CPU backend; skip without a GPU.

Run on a machine with CUDA and CuPy: ``pytest test/test_gpu.py``.
"""

from __future__ import annotations

import gc
from dataclasses import replace

import numpy as np
import pytest

from pothole_detector.backend import (CPU, Readback, StageClock, UploadBuffer, get_backend,
                                      gpu_available, lookup, to_host)
from pothole_detector.errors import BackendError, InputError, PotholeError
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.ros import conversions
from pothole_detector.stages import (census_sgm, components, matching, measure, perspective,
                                     seed, superpixels, threshold)
from pothole_detector.stages.matching import to_gray8
from pothole_detector.stages.road_model import fit_road
from pothole_detector.stages.transform import transform_disparity
from pothole_detector.recordings.camera import pipeline_inputs, rectification
from pothole_detector.stages import rectify
from pothole_detector.evaluation.synthetic import drive_scenes, raw_camera, render, render_raw

import census_reference

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")]

P1, P2 = 10, 90


@pytest.fixture(scope="module")
def gpu():
    return get_backend("gpu")


def random_pair(height: int, width: int, shift: int, seed: int):
    rng = np.random.default_rng(seed)
    wide = rng.integers(0, 256, (height, width + shift), dtype=np.uint8)
    noise = rng.integers(0, 6, (height, width), dtype=np.uint8)
    return np.ascontiguousarray(wide[:, shift:]), np.ascontiguousarray(wide[:, :width]) + noise


def run_both(gpu, left, right, shifts, levels, uniqueness=5, lr=1, median=True,
             fill_device=True):
    matcher = census_sgm.GpuMatcher(gpu, fill_device)
    device = matcher(gpu.upload(left), gpu.upload(right), gpu.upload(shifts), levels, P1, P2,
                     uniqueness, lr, median)
    buffers = matcher.buffers(left.shape[0], left.shape[1], levels)
    return matcher, buffers, to_host(device)


CASES = [  # height, width, levels, shift, GPT shift pattern; lanes x levels each (small
    # images: lanes doubled / fill_device False)
    (24, 64, 16, 9, "zero"),      # 8 x 2 / 4 x 4
    (23, 37, 32, 5, "ramp"),      # odd sizes; 16 x 2 / 8 x 4
    (1, 40, 16, 3, "zero"),       # one row
    (12, 20, 32, 4, "zero"),      # narrower than the band
    (40, 96, 128, 17, "rising"),  # 32 x 4
    (33, 70, 64, 11, "falling"),  # 32 x 2 / 16 x 4
    (31, 75, 48, 12, "ramp"),     # 8 x 6
    (8, 240, 208, 30, "falling"),  # 16 x 13: one level per register, byte reads
    (21, 150, 96, 10, "rising"),  # the real frames' band: 16 x 6
    (6, 330, 256, 20, "ramp"),    # 32 x 8: one line per warp
    (19, 140, 80, 9, "falling"),  # 16 x 6 holding 96: levels 80-95 padding
    (13, 180, 112, 14, "rising"),  # 32 x 4 holding 128: levels 112-127 padding
]


def case_shifts(height: int, pattern: str) -> np.ndarray:
    """int32 (3, H) GPT shift table of a CASES pattern: "zero"; "ramp", row shifts one more
    every 7 rows; "rising", per-pixel shifts from 0.3 px (one more every 9 rows) up by 0.04 px
    a column (the transformed right image repeats a column now and then); "falling", from 6 px
    (one more every 7 rows) down by 0.05 px a column, clipped at 0 (it skips columns)."""
    rows = np.arange(height)
    one = perspective.SHIFT_ONE
    if pattern == "zero":
        return perspective.no_shifts(height)
    if pattern == "ramp":
        return perspective.row_shifts(rows // 7)
    if pattern == "rising":
        return perspective.shifts_table(one * 3 // 10 + one * (rows // 9),
                                        np.full(height, one // 25))
    return perspective.shifts_table(one * 6 + one * (rows // 7) + 1234,
                                    np.full(height, -one // 20))


def transformed_census(census_right, shifts):
    """The GPU's transformed right census words (sgm.cu gpt_census) as the NumPy reference
    defines them, and a mask of the words the path kernels read (y < width - first(v))."""
    width = census_right.shape[1]
    columns = np.arange(width)[None, :] + shifts[perspective.SHIFT_FIRST][:, None]
    words = np.take_along_axis(perspective.transform_right(np, census_right, shifts),
                               np.minimum(columns, width - 1), axis=1)
    return words, columns < width


def reference_pair_sums(census_left, census_right, shifts, levels, p1, p2):
    """NumPy reference: matching cost (HxWxlevels), the 8 path costs and their DIRECTION_PAIRS
    sums (int32 4xHxWxlevels, the GPU path volume's real levels)."""
    cost = census_reference.matching_cost(census_left, census_right, shifts, levels)
    paths = census_reference.aggregate(cost, p1, p2)
    pair_sums = np.stack([paths[a].astype(np.int32) + paths[b]
                          for a, b in census_sgm.DIRECTION_PAIRS])
    return cost, paths, pair_sums


@pytest.mark.parametrize("fill_device", [True, False])
@pytest.mark.parametrize("height,width,levels,shift,pattern", CASES)
def test_census_sgm_kernels_match_the_reference_exactly(gpu, height, width, levels, shift,
                                                        pattern, fill_device):
    left, right = random_pair(height, width, shift, seed=height * width)
    shifts = case_shifts(height, pattern)
    _, buffers, disparity = run_both(gpu, left, right, shifts, levels, fill_device=fill_device)
    census_left = census_sgm.census_transform(left)
    census_right = census_sgm.census_transform(right)
    np.testing.assert_array_equal(to_host(buffers["census"][0]), census_left)
    words, read = transformed_census(census_right, shifts)
    np.testing.assert_array_equal(to_host(buffers["census"][2])[read], words[read])
    # the right census words went into the transformed ones; the winner search then wrote
    # over them
    assert buffers["raw"].data.ptr == buffers["census"][1].data.ptr
    _, paths, pair_sums = reference_pair_sums(census_left, census_right, shifts, levels, P1, P2)
    np.testing.assert_array_equal(to_host(buffers["paths"])[..., :levels], pair_sums)
    raw = census_reference.select_disparities(paths, 5, 1)
    np.testing.assert_array_equal(to_host(buffers["raw"]), raw)
    expected = census_sgm.finish(raw, shifts, True, census_left, levels)
    np.testing.assert_array_equal(disparity, expected)
    band_inside = levels - 1 + int(shifts[perspective.SHIFT_FIRST].min())
    if height > 2 * census_sgm.BORDER_Y and width - census_sgm.BORDER_X > band_inside + 8:
        assert np.isfinite(disparity).any()


@pytest.mark.parametrize("p1,p2", [(1, 4), (0, 1)])
@pytest.mark.parametrize("height,width,levels,shift,pattern", [CASES[i] for i in (1, 6, 7, 8, 10)])
def test_penalties_below_the_largest_cost_match_the_reference(gpu, height, width, levels, shift,
                                                              pattern, p1, p2):
    """Small penalties (P2 below the largest cost): the jump from the path minimum then gives
    some steps' least path cost, where the step before's costs at the same or a neighbouring
    level would not (never on these pairs at P2 >= 20). Padded lanes among them (80 levels)."""
    left, right = random_pair(height, width, shift, seed=height + width)
    shifts = case_shifts(height, pattern)
    matcher = census_sgm.GpuMatcher(gpu)
    disparity = matcher(gpu.upload(left), gpu.upload(right), gpu.upload(shifts), levels, p1,
                        p2, 5, 1, True)
    cost, paths, pair_sums = reference_pair_sums(census_sgm.census_transform(left),
                                                 census_sgm.census_transform(right), shifts,
                                                 levels, p1, p2)
    paths_held = to_host(matcher.buffers(height, width, levels)["paths"])
    np.testing.assert_array_equal(paths_held[..., :levels], pair_sums)
    np.testing.assert_array_equal(
        to_host(disparity),
        census_reference.reference_disparity(left, right, shifts, levels, p1, p2, 5, 1, True))
    # along the rows (direction 0): some step's least cost + P2 below its least path cost
    # without the jump (the reference step with a P2 no cost reaches)
    previous = paths[0][:, :-1].reshape(-1, levels).astype(np.int32)
    step_cost = cost[:, 1:].reshape(-1, levels)
    without_jump = census_reference._path_step(step_cost, previous, p1, 1 << 20).min(axis=1)
    assert (step_cost.min(axis=1) + p2 < without_jump).any()


@pytest.mark.parametrize("height,width,levels,shift,pattern", [CASES[i] for i in (1, 6, 8, 9, 10)])
def test_default_penalties_add_slot_pairs_as_bytes_and_match_the_reference(gpu, height, width,
                                                                          levels, shift,
                                                                          pattern):
    """At the default penalties a path cost fits 6 bits: the winner search adds two slots'
    bytes before it spreads them (P2 = 90 in the other tests does not)."""
    p1, p2 = Config().census_p1, Config().census_p2
    assert census_sgm.slot_pair_bytes(p2) and not census_sgm.slot_pair_bytes(P2)
    left, right = random_pair(height, width, shift, seed=height * 3 + width)
    shifts = case_shifts(height, pattern)
    matcher = census_sgm.GpuMatcher(gpu)
    disparity = matcher(gpu.upload(left), gpu.upload(right), gpu.upload(shifts), levels, p1,
                        p2, 5, 1, True)
    _, _, pair_sums = reference_pair_sums(census_sgm.census_transform(left),
                                          census_sgm.census_transform(right), shifts, levels,
                                          p1, p2)
    paths_held = to_host(matcher.buffers(height, width, levels)["paths"])
    np.testing.assert_array_equal(paths_held[..., :levels], pair_sums)
    assert int(pair_sums.max()) > 2 * census_sgm.INVALID_COST
    np.testing.assert_array_equal(
        to_host(disparity),
        census_reference.reference_disparity(left, right, shifts, levels, p1, p2, 5, 1, True))


def test_largest_penalty_fits_the_byte_pairs(gpu):
    """Unrelated images at P2 = MAX_P2: path costs near their bound, pair sums near 254."""
    rng = np.random.default_rng(3)
    left = rng.integers(0, 256, (20, 48), dtype=np.uint8)
    right = rng.integers(0, 256, (20, 48), dtype=np.uint8)
    shifts = perspective.no_shifts(20)
    matcher = census_sgm.GpuMatcher(gpu)
    device = matcher(gpu.upload(left), gpu.upload(right), gpu.upload(shifts), 32, 0,
                     census_sgm.MAX_P2, 0, -1, False)
    expected = census_reference.reference_disparity(left, right, shifts, 32, 0,
                                                    census_sgm.MAX_P2, 0, -1, False)
    np.testing.assert_array_equal(to_host(device), expected)
    assert int(to_host(matcher.buffers(20, 48, 32)["paths"]).max()) > 160


@pytest.mark.parametrize("uniqueness,lr,median", [(0, -1, False), (30, 0, True), (100, 3, True)])
def test_census_sgm_settings_match_the_reference(gpu, uniqueness, lr, median):
    left, right = random_pair(30, 70, 8, seed=7)
    shifts = perspective.no_shifts(30)
    _, _, disparity = run_both(gpu, left, right, shifts, 32, uniqueness, lr, median)
    expected = census_reference.reference_disparity(left, right, shifts, 32, P1, P2,
                                                    uniqueness, lr, median)
    np.testing.assert_array_equal(disparity, expected)


def test_textureless_pair_gives_the_same_ties_on_both(gpu):
    flat = np.full((20, 50), 90, np.uint8)
    shifts = perspective.no_shifts(20)
    _, _, disparity = run_both(gpu, flat, flat, shifts, 16)
    expected = census_reference.reference_disparity(flat, flat, shifts, 16, P1, P2, 5, 1, True)
    np.testing.assert_array_equal(disparity, expected)
    # a flat window has a zero census word: no texture, so nothing is valid
    assert not np.isfinite(expected).any()


def test_buffers_are_reused_across_frames_and_level_counts(gpu):
    left, right = random_pair(24, 64, 9, seed=3)
    shifts = perspective.no_shifts(24)
    matcher, buffers, first = run_both(gpu, left, right, shifts, 32)
    generation = matcher.generation

    def match(levels):
        return to_host(matcher(gpu.upload(left), gpu.upload(right), gpu.upload(shifts), levels,
                               P1, P2, 5, 1, True))

    np.testing.assert_array_equal(match(32), first)
    fewer = match(16)
    np.testing.assert_array_equal(
        fewer, census_reference.reference_disparity(left, right, shifts, 16, P1, P2, 5, 1, True))
    for levels in (32, 16):
        assert matcher.buffers(24, 64, levels)["paths"].data.ptr == buffers["paths"].data.ptr
    assert matcher.generation == generation
    more = match(48)  # the volume grows: new buffers, a new generation
    assert matcher.generation == generation + 1
    np.testing.assert_array_equal(
        more, census_reference.reference_disparity(left, right, shifts, 48, P1, P2, 5, 1, True))
    np.testing.assert_array_equal(match(32), first)


def test_matcher_kernel_clock_times_each_kernel_and_changes_nothing(gpu):
    left, right = random_pair(30, 80, 7, seed=9)
    shifts = gpu.upload(perspective.no_shifts(30))
    matcher = census_sgm.GpuMatcher(gpu)
    plain = to_host(matcher(gpu.upload(left), gpu.upload(right), shifts, 32, P1, P2, 5, 1, True))
    clock = StageClock(gpu)
    timed = matcher(gpu.upload(left), gpu.upload(right), shifts, 32, P1, P2, 5, 1, True,
                    clock=clock)
    np.testing.assert_array_equal(to_host(timed), plain)
    timings = clock.timings()
    assert set(timings) == {"census", "paths", "select", "finish"}
    assert all(value > 0 for value in timings.values())


def test_side_stream_work_is_ordered_after_earlier_and_before_joined_work(gpu):
    xp = gpu.xp
    for _ in range(3):
        values = xp.arange(1 << 22, dtype=xp.float64)
        values += 1.0                                    # queued on the current stream
        with gpu.side_stream() as join:
            doubled = values * 2.0                       # after it, on the side stream
            total = doubled.sum()
        join()
        assert float(total + values[0]) == float((1 << 22) * ((1 << 22) + 1) + 1)


def test_stage_clocks_reuse_read_events_and_still_time_the_work(gpu):
    xp = gpu.xp
    for _ in range(3):
        clock = StageClock(gpu)
        with clock.stage("sum"):
            float(xp.arange(1 << 20, dtype=xp.float64).sum())
        with clock.stage("sort"):
            xp.sort(xp.arange(1 << 20)[::-1])
        timings = clock.timings()
        assert set(timings) == {"sum", "sort"} and all(v > 0 for v in timings.values())


def test_upload_many_round_trips(gpu):
    arrays = (np.arange(15, dtype=np.uint8).reshape(3, 5), np.arange(7, dtype=np.int32),
              np.linspace(0, 1, 6, dtype=np.float32).reshape(2, 3))
    for host, device in zip(arrays, gpu.upload_many(*arrays)):
        np.testing.assert_array_equal(to_host(device), host)


def test_copy_is_a_new_device_array_that_later_writes_leave_alone(gpu):
    source = gpu.upload(np.arange(24, dtype=np.int32).reshape(4, 6))
    for array in (source, source[:, ::2]):
        copied = gpu.copy(array)
        assert copied.flags.c_contiguous and copied.data.ptr != array.data.ptr
        expected = to_host(array)
        source.fill(-1)
        np.testing.assert_array_equal(to_host(copied), expected)
        source[...] = gpu.upload(np.arange(24, dtype=np.int32).reshape(4, 6))


def test_lookup_on_the_device_gives_the_host_lookup(gpu):
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 50, (40, 60)).astype(np.int32)
    table = rng.random(50) < 0.5
    device_labels, device_table = gpu.upload(labels), gpu.upload(table)
    for window in ((slice(None), slice(None)), (slice(5, 30), slice(7, 51, 2))):
        for after in (None, gpu.record_event()):
            found = lookup(device_table, device_labels[window], after)
            assert isinstance(found, np.ndarray) and found.dtype == np.bool_
            np.testing.assert_array_equal(found, table[labels[window]])


def test_the_road_cloud_worked_out_on_the_device_is_the_one_from_the_host(gpu, demo_sample):
    """points2's cloud from the device's disparity equals the one from its host copy (the
    same float64 arithmetic on both, to float32 rounding; NaN where the other has NaN)."""
    result = Pipeline(Config(), demo_sample.calibration, gpu).run(demo_sample.left,
                                                                  demo_sample.right)
    labels = result.host("labels")
    on_device, on_host = (
        conversions.road_cloud(demo_sample.left, disparity, labels, result.road,
                               demo_sample.calibration)
        for disparity in (result.disparity, result.host("disparity")))
    for name in ("x", "y", "z", "depth_below_road"):
        np.testing.assert_allclose(on_device[name], on_host[name], rtol=1e-6, atol=0)
    for name in ("rgb", "label"):
        np.testing.assert_array_equal(on_device[name].view("<u4"), on_host[name].view("<u4"))
    assert np.isfinite(on_host["depth_below_road"]).mean() > 0.5 and labels.max() > 0


def test_upload_many_keeps_earlier_uploads_intact(gpu):
    strided = (np.arange(128, dtype=np.int32) // 2)[::2]  # a view, not contiguous
    first = gpu.upload_many(np.full((64, 64), 7, np.uint8), strided)
    second = gpu.upload_many(np.full((64, 64), 9, np.uint8), np.arange(64, dtype=np.int32) * 2)
    assert int(to_host(first[0]).max()) == 7 and int(to_host(second[0]).min()) == 9
    np.testing.assert_array_equal(to_host(second[1]), np.arange(64) * 2)
    np.testing.assert_array_equal(to_host(first[1]), np.arange(64))


def test_upload_buffer_round_trips_and_waits_before_it_is_written_again(gpu):
    buffer = UploadBuffer(gpu, [((64, 64), np.uint8), ((64,), np.int32)])
    image, shifts = buffer.writable()
    image[...] = 7
    shifts[...] = np.arange(64)
    first = buffer.upload()
    image, shifts = buffer.writable()  # waits for the first transfer
    image[...] = 9
    assert int(to_host(first[0]).max()) == 7
    second = buffer.upload()
    assert all(a is b for a, b in zip(first, second))  # one device buffer, overwritten
    assert int(to_host(second[0]).min()) == 9 and second[0].shape == (64, 64)
    np.testing.assert_array_equal(to_host(second[1]), np.arange(64))
    image, _ = buffer.writable()
    image[...] = 11
    buffer.send_ahead(1)  # the image goes up now, on the copy stream
    buffer.send_ahead(1)  # already on its way: nothing more
    (shifts,) = buffer.writable(1)  # behind the image: no wait for it
    shifts[...] = -np.arange(64)
    third = buffer.upload()
    assert int(to_host(third[0]).min()) == int(to_host(third[0]).max()) == 11
    np.testing.assert_array_equal(to_host(third[1]), -np.arange(64))
    image, _ = buffer.writable()
    image[...] = 12
    buffer.send_ahead(1)
    image, _ = buffer.writable()  # the image written again: what went ahead counts as unsent
    image[...] = 13
    buffer.send_ahead(1)
    fourth = buffer.upload()
    assert int(to_host(fourth[0]).min()) == int(to_host(fourth[0]).max()) == 13


def test_readback_copies_asynchronously_and_keeps_each_sends_bytes(gpu):
    source = gpu.xp.arange(4096, dtype=gpu.xp.int32).view(gpu.xp.uint8)
    readback = Readback(gpu, source.nbytes)
    readback.send(source)
    source[:] = 0  # queued after the copy on the same stream
    np.testing.assert_array_equal(readback.receive().view(np.int32), np.arange(4096))
    readback.send(source[:64])
    assert readback.receive().tolist() == [0] * 64
    with pytest.raises(BackendError, match="do not fit"):
        readback.send(gpu.xp.zeros(source.nbytes + 1, dtype=gpu.xp.uint8))


SPIN = r"""extern "C" __global__ void spin(long long cycles) {
    const long long start = clock64();
    while (clock64() - start < cycles) {}
}"""


def test_a_streamed_result_is_read_without_waiting_for_the_next_frame(gpu, demo_sample):
    """run_stream hands a frame's result out once the next frame is queued: its reads (host,
    at, a window) wait for its own work alone, not for a thread spinning for about 0.2 s on the
    current stream after it, and give what the stream's order gives. (A kernel's first load
    waits for the whole device: each read runs once before the spin.)"""
    spin = gpu.xp.RawKernel(SPIN, "spin")
    pipeline = Pipeline(Config(), demo_sample.calibration, gpu)
    pairs = [(demo_sample.left, demo_sample.right)] * 4
    pixels = np.arange(0, demo_sample.left.size, 7)
    for result in pipeline.run_stream(iter(pairs)):
        assert result.ready is not None
        result.host("labels"), result.at("searched", pixels), result.host("searched")
        spin((1,), (1,), (np.int64(400_000_000),))
        labels, searched = result.host("labels"), result.at("searched", pixels)
        searched_image = result.host("searched")
        assert not gpu.xp.cuda.get_current_stream().done
        gpu.synchronize()
        np.testing.assert_array_equal(labels, to_host(result.labels))
        np.testing.assert_array_equal(
            searched, to_host(result.searched)[to_host(result.superpixels).ravel()[pixels]])
        np.testing.assert_array_equal(searched_image,
                                      to_host(result.searched)[to_host(result.superpixels)])
        window = (slice(50, 200), slice(13, 301))
        np.testing.assert_array_equal(result.host("labels", window), labels[window])
        np.testing.assert_array_equal(result.host("observed", window),
                                      result.host("observed")[window])
    assert labels.max() > 0


def test_run_stream_on_the_gpu_gives_what_run_gives(demo_sample):
    gpu = get_backend("gpu")
    left, right = demo_sample.left, demo_sample.right
    again = Pipeline(Config(), demo_sample.calibration, gpu)
    expected = [again.run(left, right) for _ in range(2)]
    flipped = np.ascontiguousarray(right[:, ::-1])
    pairs = [(left, right), (left, right[:4]), (left, right), (flipped, left)]
    pipeline = Pipeline(Config(), demo_sample.calibration, gpu)
    outcomes = list(pipeline.run_stream(pairs))
    assert isinstance(outcomes[1], InputError)
    for result, reference in zip((outcomes[0], outcomes[2]), expected):
        np.testing.assert_array_equal(to_host(result.disparity), to_host(reference.disparity))
        np.testing.assert_array_equal(to_host(result.labels), to_host(reference.labels))
        assert result.seeded == reference.seeded
    last = outcomes[3]
    try:
        reference = again.run(flipped, left)
    except Exception as exc:  # noqa: BLE001 - the stream must report the same outcome
        assert type(last) is type(exc)
    else:
        np.testing.assert_array_equal(to_host(last.disparity), to_host(reference.disparity))


# --- the other stages: one body on both backends -------------------------------------------


def crowned_road(height: int, width: int, seed: int, invalid: float = 0.1) -> np.ndarray:
    """Road disparity with roll, a crown and outliers (px, NaN invalid)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    t = v * np.cos(0.03) - u * np.sin(0.03)
    road = 20 + 0.12 * t + 3e-6 * (u - width / 2) ** 2 + rng.normal(0, 0.2, (height, width))
    road[rng.random((height, width)) < 0.05] -= rng.uniform(3, 15)
    road[rng.random((height, width)) < invalid] = np.nan
    return road.astype(np.float32)


@pytest.mark.parametrize("keys_in", ["shared", "global"])
@pytest.mark.parametrize("kind,rounds,stride", [("planar", 3, 1), ("quadratic", 2, 2),
                                                ("auto", 3, 4), ("planar", 0, 3)])
def test_road_fit_kernel_matches_the_reference(gpu, kind, rounds, stride, keys_in, monkeypatch):
    from pothole_detector.stages import road_model
    if keys_in == "global":
        monkeypatch.setattr(road_model, "MAX_SHARED_KEY_BYTES", 0)
    disparity = crowned_road(150, 260, seed=rounds + stride)
    cpu = road_model.fit_road(np, disparity, stride=stride, rounds=rounds, kind=kind)
    dev = road_model.fit_model(gpu, gpu.upload(disparity), stride=stride, rounds=rounds, kind=kind)
    assert dev.kind == cpu.kind
    np.testing.assert_allclose([dev.a0, dev.a1, dev.roll_rad], [cpu.a0, cpu.a1, cpu.roll_rad],
                               rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(dev.curvature, cpu.curvature, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(dev.sigma_px, cpu.sigma_px, rtol=1e-5)
    assert abs(dev.inlier_fraction - cpu.inlier_fraction) < 1e-4


def test_road_fit_kernel_in_seed_coordinates_and_errors(gpu):
    from pothole_detector.errors import NoRoadError
    from pothole_detector.stages import road_model
    coarse = crowned_road(40, 70, seed=5) / 4
    options = dict(stride=1, kind="auto", coordinate_scale=4.0, coordinate_offset=1.5)
    cpu = road_model.fit_road(np, coarse, **options)
    dev = road_model.fit_model(gpu, gpu.upload(coarse), **options)
    np.testing.assert_allclose([dev.a0, dev.a1, dev.roll_rad], [cpu.a0, cpu.a1, cpu.roll_rad],
                               rtol=1e-7, atol=1e-10)
    with pytest.raises(NoRoadError, match="fewer than 3"):
        road_model.fit_model(gpu, gpu.upload(np.full((20, 20), np.nan, np.float32)))
    line = np.full((20, 20), np.nan, np.float32)
    line[5, :] = 10.0
    with pytest.raises(NoRoadError, match="on a line"):
        road_model.fit_model(gpu, gpu.upload(line))


def test_road_fit_kernel_on_a_rank_deficient_quadratic_system(gpu):
    """Two valid rows: y^2 depends on 1 and y, so the 6x6 system is singular and the kernel
    takes the minimum-norm solution like numpy.linalg.lstsq."""
    from pothole_detector.stages import road_model
    disparity = np.full((40, 120), np.nan, np.float32)
    rng = np.random.default_rng(2)
    for row in (10, 30):
        disparity[row] = 20 + 0.1 * row + 2e-4 * (np.arange(120) - 60) ** 2 \
            + rng.normal(0, 0.05, 120)
    cpu = road_model.fit_road(np, disparity, kind="quadratic", rounds=1)
    dev = road_model.fit_model(gpu, gpu.upload(disparity), kind="quadratic", rounds=1)
    probe_u, probe_v = np.arange(0, 120, 7.0), np.full(18, 20.0)
    np.testing.assert_allclose(dev.at(np, probe_u, probe_v), cpu.at(np, probe_u, probe_v),
                               rtol=1e-6)
    np.testing.assert_allclose(dev.curvature, cpu.curvature, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("bin_px", [0.25, 0.1, 0.01])
def test_threshold_kernels_match_the_reference(gpu, bin_px):
    """0.01 px bins make tables too large for shared memory: the global-atomics path."""
    rng = np.random.default_rng(int(bin_px * 100))
    image = (32 + rng.normal(0, 0.4, (90, 170))).astype(np.float32)
    image[20:50, 30:90] -= 4 + rng.normal(0, 0.5, (30, 60)).astype(np.float32)
    image[rng.random(image.shape) < 0.1] = np.nan
    image[0, :] = 500.0  # outside the histogram range
    cpu = threshold.histogram_threshold(CPU, image, bin_px, 32.0)
    dev = threshold.histogram_threshold(gpu, gpu.upload(image), bin_px, 32.0)
    assert dev[0] == cpu[0]
    np.testing.assert_allclose(dev[1], cpu[1], rtol=1e-12)
    empty = gpu.upload(np.full((30, 40), np.nan, np.float32))
    assert all(np.isnan(threshold.histogram_threshold(gpu, empty, bin_px, 32.0)))


def test_measure_kernel_matches_the_reference(gpu, demo_sample):
    from pothole_detector.stages import road_model
    disparity = demo_sample.disparity.astype(np.float32)
    road = road_model.fit_road(np, disparity, stride=2, kind="quadratic")
    labels = demo_sample.labels.astype(np.int32)
    count = int(labels.max())
    rng = np.random.default_rng(0)
    holes = disparity.copy()
    holes[(labels > 0) & (rng.random(labels.shape) < 0.2)] = np.nan
    speckled = labels.copy()
    speckled[::7, ::3] = np.where(labels[::7, ::3] > 0, 0, labels[::7, ::3])
    for image, label_image in ((disparity, labels), (holes, speckled)):
        cpu = measure.measure_potholes(CPU, label_image, count, image, road,
                                       demo_sample.calibration)
        dev = measure.measure_potholes(gpu, gpu.upload(label_image), count, gpu.upload(image),
                                       road, demo_sample.calibration)
        assert len(dev) == len(cpu) == count > 0
        for a, b in zip(cpu, dev):
            assert (a.label, a.pixels, a.bbox_px) == (b.label, b.pixels, b.bbox_px)
            np.testing.assert_allclose(
                [b.area_m2, b.max_depth_m, b.mean_depth_m, b.volume_m3, *b.centroid_cam_m],
                [a.area_m2, a.max_depth_m, a.mean_depth_m, a.volume_m3, *a.centroid_cam_m],
                rtol=1e-4)


def test_measure_kernel_estimates_hidden_floors_like_the_reference(gpu, near_rim_sample):
    from pothole_detector.stages import refine, road_model
    labels = near_rim_sample.labels.astype(np.int32)
    road = road_model.fit_road(np, np.where(labels > 0, np.nan, near_rim_sample.disparity))
    _, smoothed = refine.smooth(CPU, near_rim_sample.disparity.astype(np.float32))
    v, u = np.nonzero(labels)
    _, edge_on = measure.surface_patches(np, u, v, smoothed,
                                         measure.road_normal(road, near_rim_sample.calibration),
                                         near_rim_sample.calibration)
    assert edge_on.sum() > 100
    (cpu,) = measure.measure_potholes(CPU, labels, 1, smoothed, road,
                                      near_rim_sample.calibration)
    (dev,) = measure.measure_potholes(gpu, gpu.upload(labels), 1, gpu.upload(smoothed), road,
                                      near_rim_sample.calibration)
    np.testing.assert_allclose([dev.area_m2, dev.max_depth_m, dev.mean_depth_m, dev.volume_m3],
                               [cpu.area_m2, cpu.max_depth_m, cpu.mean_depth_m, cpu.volume_m3],
                               rtol=1e-4)


@pytest.mark.parametrize("kind", ["planar", "quadratic"])
def test_transform_kernel_matches_the_reference_exactly(gpu, kind):
    from pothole_detector.stages.road_model import RoadModel
    model = RoadModel(40.0, 0.25, -0.05, (0.3, -0.2, 0.1, 0.5, -0.4, 0.2), kind=kind)
    rng = np.random.default_rng(1)
    disparity = rng.uniform(20, 90, (57, 211)).astype(np.float32)
    disparity[rng.random(disparity.shape) < 0.1] = np.nan
    cpu = transform_disparity(CPU, disparity, model, 32.0)
    dev = transform_disparity(gpu, gpu.upload(disparity), model, 32.0)
    np.testing.assert_array_equal(to_host(dev), cpu)


def test_superpixel_means_kernel_matches_the_reference(gpu):
    rng = np.random.default_rng(8)
    image = rng.normal(30, 3, (61, 203)).astype(np.float32)
    image[rng.random(image.shape) < 0.2] = np.nan
    image[:, 150:] = np.nan  # superpixels without any valid value
    labels = (np.arange(61)[:, None] // 9 * 12 + np.arange(203)[None, :] // 17).astype(np.int32)
    n = int(labels.max()) + 3  # two empty labels at the end
    cpu = superpixels.superpixel_means(CPU, image, labels, n)
    dev = superpixels.superpixel_means(gpu, gpu.upload(image), gpu.upload(labels), n)
    for a, b in zip(cpu, dev):
        np.testing.assert_allclose(to_host(b), a, rtol=1e-6, equal_nan=True)


@pytest.mark.parametrize("height,width,density", [(97, 131, 0.45), (1, 300, 0.5), (300, 1, 0.5),
                                                  (64, 64, 0.0), (50, 70, 1.0), (120, 200, 0.6)])
def test_label_kernels_match_scipy_numbering(gpu, height, width, density):
    rng = np.random.default_rng(height + width)
    mask = rng.random((height, width)) < density
    if height > 20 and width > 20:
        rows = np.arange(height)[:, None]
        mask |= (np.abs(rows - height / 2 - 10 * np.sin(np.arange(width) / 7)) < 1.5)  # a wave
    expected = components.label_components(CPU, mask)
    found = components.label_components(gpu, gpu.upload(mask))
    assert found[1] == expected[1]
    np.testing.assert_array_equal(to_host(found[0]), expected[0])


@pytest.mark.parametrize("min_superpixels,factor", [(2, 1), (1, 1), (3, 1), (2, 2), (1, 3)])
def test_component_filters_kernels_match_the_reference(gpu, min_superpixels, factor):
    from pothole_detector.stages.superpixels import upsample_labels
    rng = np.random.default_rng(min_superpixels + 3 * factor)
    height, width = 90, 161
    small = rng.random((height // factor, width // factor)) < 0.3
    candidate = upsample_labels(CPU, small, factor, (height, width))
    valid = np.ones((height, width), bool)
    valid[:, :13] = False
    valid[40:44, :] = False
    sp = (np.arange(height)[:, None] // 10 * 16 + np.arange(width)[None, :] // 10)
    sp = sp.astype(np.int32)
    n = int(sp.max()) + 1
    for flagged, bumps in ((None, None), (rng.random(n) < 0.3, None),
                           (None, rng.random(n) < 0.02)):
        cpu = components.components_found(CPU, candidate, valid, sp, n, min_superpixels,
                                          inconsistent=flagged, bumps=bumps)
        dev = components.components_found(
            gpu, gpu.upload(small), gpu.upload(valid), gpu.upload(sp), n, min_superpixels,
            factor=factor, inconsistent=None if flagged is None else gpu.upload(flagged),
            bumps=None if bumps is None else gpu.upload(bumps))
        assert dev[1] == cpu[1] > 0
        np.testing.assert_array_equal(to_host(dev[0]), cpu[0])


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.3])
def test_far_corners_on_the_gpu_match_the_reference(gpu, fraction):
    valid = np.ones((70, 130), bool)
    valid[:, :17] = False
    valid[5:9, :] = False
    valid[20, 100:] = False
    cpu = components.far_corners(CPU, valid, fraction)
    dev = components.far_corners(gpu, gpu.upload(valid), fraction)
    assert dev.side == cpu.side
    np.testing.assert_array_equal(to_host(dev.first), cpu.first)
    np.testing.assert_array_equal(to_host(dev.last), cpu.last)


def test_joining_pieces_on_the_gpu_matches_the_cpu(gpu):
    rng = np.random.default_rng(21)
    labels, count = components.label_components(CPU, rng.random((121, 201)) < 0.02)
    labels = labels.astype(np.int32)
    for reach, factor in ((0, 1), (1, 1), (3, 1), (3, 2), (5, 2)):
        want_count, got_count = np.zeros(1, np.int32), gpu.xp.zeros(1, dtype=gpu.xp.int32)
        want = components.join_pieces(CPU, labels, reach, want_count, factor)
        got = components.join_pieces(gpu, gpu.upload(labels), reach, got_count, factor)
        np.testing.assert_array_equal(to_host(got), want)
        assert int(to_host(got_count)[0]) == int(want_count[0]) <= count
    # across depressed superpixels (4 x 4 cells of the grid reduced by 2)
    rows, cols = np.mgrid[0:60, 0:100]
    grid = ((rows // 4) * 25 + cols // 4).astype(np.int32)
    depressed = rng.random(int(grid.max()) + 1) < 0.3
    want_count, got_count = np.zeros(1, np.int32), gpu.xp.zeros(1, dtype=gpu.xp.int32)
    want = components.join_pieces(CPU, labels, 1, want_count, 2, grid, depressed, 6)
    got = components.join_pieces(gpu, gpu.upload(labels), 1, got_count, 2, gpu.upload(grid),
                                 gpu.upload(depressed), 6)
    np.testing.assert_array_equal(to_host(got), want)
    assert int(to_host(got_count)[0]) == int(want_count[0]) < count


def test_component_filters_with_thousands_of_components(gpu):
    """More components than one block of the renumbering kernel: its chunks must carry."""
    height, width = 150, 240
    candidate = np.zeros((height, width), bool)
    candidate[::3, ::3] = True
    candidate[::6, ::9] = False
    valid = np.ones((height, width), bool)
    sp = ((np.arange(height)[:, None] // 2) * 120 + np.arange(width)[None, :] // 2)
    sp = sp.astype(np.int32)
    n = int(sp.max()) + 1
    cpu = components.components_found(CPU, candidate, valid, sp, n, 1)
    dev = components.components_found(gpu, gpu.upload(candidate), gpu.upload(valid),
                                        gpu.upload(sp), n, 1)
    assert dev[1] == cpu[1] > 2000
    np.testing.assert_array_equal(to_host(dev[0]), cpu[0])


def test_blank_pair_is_refused_on_both_backends(demo_sample):
    from pothole_detector.errors import NoTextureError
    blank = np.full((120, 200), 128, np.uint8)
    for backend in (CPU, get_backend("gpu")):
        with pytest.raises(NoTextureError):
            Pipeline(Config({"matcher": "census"}), demo_sample.calibration, backend).run(
                blank, blank)


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
    d2_cpu = transform_disparity(CPU, road_disparity, road, config.delta_dt_px)
    d2_gpu = transform_disparity(gpu, gpu.upload(road_disparity), road,
                                 config.delta_dt_px)
    np.testing.assert_allclose(to_host(d2_gpu), d2_cpu, rtol=0, atol=1e-4)
    d2_gpu = gpu.upload(d2_cpu)
    found_cpu_sp = superpixels.superpixels(CPU, d2_cpu, 32, 2.0, 6, 2)
    found_gpu_sp = superpixels.superpixels(gpu, d2_gpu, 32, 2.0, 6, 2)
    labels_cpu, n = found_cpu_sp.labels, found_cpu_sp.count
    labels_gpu, n_gpu = found_gpu_sp.labels, found_gpu_sp.count
    assert n_gpu == n
    assert (to_host(labels_gpu) == labels_cpu).mean() > 0.999
    t_cpu = threshold.histogram_threshold(CPU, d2_cpu, 0.25, config.delta_dt_px)
    t_gpu = threshold.histogram_threshold(gpu, d2_gpu, 0.25, config.delta_dt_px)
    np.testing.assert_allclose(t_gpu, t_cpu, rtol=1e-6)
    selected = np.isfinite(d2_cpu) & (d2_cpu < t_cpu[1] - 2.0)
    sp = labels_cpu
    found_cpu = components.components_found(CPU, selected, np.isfinite(d2_cpu), sp, n, 2)
    found_gpu = components.components_found(gpu, gpu.upload(selected),
                                              gpu.upload(np.isfinite(d2_cpu)), gpu.upload(sp),
                                              n, 2)
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
    for name in ("observed", "searched"):
        assert (gpu.host(name) == cpu.host(name)).mean() > 0.99, name


def test_gpu_pipeline_finds_the_rendered_potholes(demo_sample):
    result = Pipeline(Config(), demo_sample.calibration, get_backend("gpu")).run(
        demo_sample.left, demo_sample.right)
    assert result.backend == "gpu" and len(result.potholes) >= 2
    truth = demo_sample.labels > 0
    found = to_host(result.labels) > 0
    assert (found & truth).sum() / max(found.sum(), 1) > 0.8
    assert set(result.timings_ms) >= {"sgm", "slic", "total", "host"}
    assert 0 < result.timings_ms["host_wait"] < result.timings_ms["host"]


@pytest.mark.parametrize("kind", ["planar", "quadratic", "auto"])
def test_road_fit_on_device_gives_the_kept_models_kernel_params(gpu, kind):
    from pothole_detector.stages import road_model
    disparity = crowned_road(120, 230, seed=11)
    report, params = road_model.fit_on_device(gpu, gpu.upload(disparity), stride=2, kind=kind)
    model = road_model.model_from_report(to_host(report), kind, 0.1)
    np.testing.assert_allclose(to_host(params), model.kernel_params(), rtol=1e-15, atol=1e-17)
    assert to_host(params)[10] == (model.kind == "quadratic")
    _, failed = road_model.fit_on_device(gpu, gpu.upload(np.full((20, 20), np.nan, np.float32)))
    assert np.isnan(to_host(failed)).all()


@pytest.mark.parametrize("kind", ["planar", "auto"])
def test_road_fit_with_a_prior_on_the_gpu_matches_the_reference(gpu, kind):
    """A road beside a wall of nearer disparities: with the prior both backends fit the road
    (the same report), without it the wall tilts the fit."""
    from pothole_detector.stages import road_model
    disparity = crowned_road(120, 230, seed=11)
    truth = road_model.fit_road(np, disparity, stride=2, kind="planar")
    walled = disparity.copy()
    walled[:, 140:] = 60.0 + np.random.default_rng(2).normal(0, 0.3, (120, 90))
    prior = road_model.prior_params(truth, 2.0, 0.3)
    want = road_model.fit_report(np, walled, stride=2, kind=kind, prior=prior)
    got, _ = road_model.fit_on_device(gpu, gpu.upload(walled), stride=2, kind=kind,
                                      prior=gpu.upload(prior))
    used = slice(None) if kind != "planar" else slice(0, road_model.FIT_LAYOUT["FIT_CURVATURE"])
    np.testing.assert_allclose(to_host(got)[used], want[used], rtol=1e-6)
    fitted = road_model.model_from_report(want, kind, 0.1)
    assert abs(fitted.roll_deg - truth.roll_deg) < 0.2
    unguided, _ = road_model.fit_on_device(gpu, gpu.upload(walled), stride=2, kind=kind)
    assert abs(road_model.model_from_report(to_host(unguided), kind, 0.1).roll_deg
               - truth.roll_deg) > 1.0


def test_device_road_params_drive_transform_and_measure_like_the_model(gpu, demo_sample):
    from pothole_detector.stages import road_model
    disparity = demo_sample.disparity.astype(np.float32)
    _, params = road_model.fit_on_device(gpu, gpu.upload(disparity), stride=2, kind="auto")
    host_params = to_host(params)
    model = road_model.RoadModel(host_params[0], host_params[1],
                                 float(np.arctan2(host_params[3], host_params[2])),
                                 tuple(host_params[4:10]),
                                 kind="quadratic" if host_params[10] else "planar")
    by_params = transform_disparity(gpu, gpu.upload(disparity), params, 32.0)
    by_model = transform_disparity(gpu, gpu.upload(disparity), model, 32.0)
    np.testing.assert_allclose(to_host(by_params), to_host(by_model), atol=1e-5)
    labels = demo_sample.labels.astype(np.int32)
    count = int(labels.max())
    sums, extremes = measure.measure(gpu, gpu.upload(labels), count, gpu.upload(disparity), params,
                                    demo_sample.calibration)
    found = measure.potholes_from_sums(to_host(sums)[1:], to_host(extremes)[1:])
    expected = measure.measure_potholes(CPU, labels, count, disparity, model,
                                        demo_sample.calibration)
    assert [p.pixels for p in found] == [p.pixels for p in expected]
    np.testing.assert_allclose([p.volume_m3 for p in found], [p.volume_m3 for p in expected],
                               rtol=1e-4)


def test_corner_and_significant_pixel_counts_on_the_gpu_match_the_cpu(gpu, demo_sample):
    from pothole_detector.stages import road_model
    disparity = demo_sample.disparity.astype(np.float32)
    road = road_model.fit_road(np, disparity, stride=2)
    height, width = disparity.shape
    rng = np.random.default_rng(8)
    labels = np.zeros((height, width), np.int32)
    labels[0:30, 0:50] = 1
    labels[5:25, width - 60:width - 3] = 2
    labels[height // 2:height // 2 + 20, 100:140] = 3
    superpixels = ((np.arange(height)[:, None] // 9) * 500
                   + np.arange(width)[None, :] // 9).astype(np.int32)
    significant = rng.random(int(superpixels.max()) + 1) < 0.5
    valid = np.ones((height, width), bool)
    valid[:, :11] = False
    found = []
    for backend, upload in ((CPU, np.asarray), (gpu, gpu.upload)):
        corners = components.far_corners(backend, upload(valid), 0.1)
        sums, _ = measure.measure(backend, upload(labels), 3, upload(disparity),
                                  road_model.device_params(backend, road) if backend is gpu
                                  else road, demo_sample.calibration, corners=corners,
                                  superpixel_labels=upload(superpixels),
                                  significant=upload(significant))
        found.append(to_host(sums)[1:, [measure.Sum.CORNER, measure.Sum.SIGNIFICANT]])
    np.testing.assert_array_equal(found[1], found[0])
    assert found[0][0, 0] > 0 and found[0][1, 0] > 0 and found[0][2, 0] == 0
    assert 0 < found[0][0, 1] < (labels == 1).sum()


@pytest.mark.parametrize("reference", ["split", "road_mean", "road_fit"])
def test_select_on_the_gpu_matches_select_superpixels(gpu, reference):
    rng = np.random.default_rng(3)
    image = (32 + rng.normal(0, 0.4, (90, 170))).astype(np.float32)
    image[20:50, 30:90] -= 4
    n = 400
    means = (32 + rng.normal(0, 2.0, n)).astype(np.float32)
    means[::17] = np.nan
    fraction = rng.random(n).astype(np.float32)
    result = threshold.threshold_search(gpu, gpu.upload(image), 0.25, 32.0)
    t_r, road_mean = threshold.split_from_result(to_host(result), 0.25, 32.0)
    reference_px = {"split": t_r, "road_mean": road_mean, "road_fit": 32.0}[reference]
    drops = rng.uniform(0.5, 3.0, n)
    for drop, t_s in ((2.0, reference_px - 2.0), (drops, reference_px - drops)):
        expected = threshold.select_superpixels(np, means, fraction, t_s, 0.5)
        found = threshold.select(
            gpu, result, 0.25, 32.0, reference, gpu.upload(means),
            gpu.upload(fraction), drop if isinstance(drop, float) else gpu.upload(drop), 0.5)
        np.testing.assert_array_equal(to_host(found), expected)
        assert 0 < expected.sum() < n
    none_found = threshold.threshold_search(
        gpu, gpu.upload(np.full((30, 40), np.nan, np.float32)), 0.25, 32.0)
    assert not to_host(threshold.select(
        gpu, none_found, 0.25, 32.0, "split", gpu.upload(means), gpu.upload(fraction), 2.0,
        0.5)).any()


def test_components_on_the_gpu_flag_overflow_and_matches_below_capacity(gpu):
    rng = np.random.default_rng(4)
    height, width = 90, 161
    candidate = rng.random((height, width)) < 0.3
    valid = np.ones((height, width), bool)
    sp = (np.arange(height)[:, None] // 10 * 17 + np.arange(width)[None, :] // 10)
    sp = sp.astype(np.int32)
    n = int(sp.max()) + 1
    labels_cpu, kept_cpu = components.components_found(CPU, candidate, valid, sp, n, 2)
    found_count = components.label_components(CPU, candidate)[1]
    for capacity, overflow in ((found_count, 0), (found_count + 40, 0), (found_count - 1, 1)):
        counts = gpu.xp.full(3, -1, dtype=gpu.xp.int32)
        labels = components.pothole_components(
            gpu, gpu.upload(candidate), gpu.upload(valid), gpu.upload(sp), n, 2, 1,
            capacity, counts)
        assert list(to_host(counts))[0::2] == [found_count, overflow]
        if not overflow:
            assert to_host(counts)[1] == kept_cpu > 0
            np.testing.assert_array_equal(to_host(labels), labels_cpu)


def test_the_largest_depth_under_the_opening_on_the_gpu_matches_the_cpu(gpu):
    """A bowl 3 m ahead whose 4 farthest rows are matched 20 % short (points far beyond the
    far rim): the bowl's depth; cut through by the image's right edge, where those points'
    road points fall off the image beside the pothole's edge and so count: deeper. The same
    largest depth and box on both backends."""
    from pothole_detector.stages import road_model
    from pothole_detector.evaluation.synthetic import PotholeShape, Scene
    sample = render(Scene(width=640, height=480, focal_px=500.0, baseline_m=0.12,
                          camera_height_m=1.0, pitch_deg=15.0,
                          potholes=(PotholeShape(0.1, 3.0, 0.4, 0.3, 0.08, 15.0),)))
    labels = sample.labels.astype(np.int32)
    disparity = sample.disparity.astype(np.float32)
    road = fit_road(np, np.where(labels > 0, np.nan, disparity), rounds=2)
    rows = np.nonzero(labels)[0]
    disparity[labels > 0] *= np.where(rows < rows.min() + 4, 0.8, 1.0).astype(np.float32)
    cut = int(np.nonzero(labels.any(axis=0))[0].mean())
    (whole,) = measure.measure_potholes(CPU, labels, 1, disparity, road, sample.calibration)
    assert whole.max_depth_m == pytest.approx(0.08, rel=0.02)
    for image, depth in ((labels, disparity), (labels[:, :cut].copy(), disparity[:, :cut].copy())):
        (expected,) = measure.measure_potholes(CPU, image, 1, depth, road, sample.calibration)
        sums, extremes = measure.measure(gpu, gpu.upload(image), 1, gpu.upload(depth),
                                         road_model.device_params(gpu, road),
                                         sample.calibration)
        (found,) = measure.potholes_from_sums(to_host(sums)[1:], to_host(extremes)[1:])
        assert found.bbox_px == expected.bbox_px
        assert found.max_depth_m == pytest.approx(expected.max_depth_m, rel=1e-5)
    assert found.max_depth_m > 0.1


def test_area_filter_on_the_gpu_keeps_the_rows_keep_large_keeps(gpu, demo_sample):
    from pothole_detector.stages import road_model
    disparity = demo_sample.disparity.astype(np.float32)
    road = road_model.fit_road(np, disparity, stride=2)
    labels = demo_sample.labels.astype(np.int32)
    count = int(labels.max())
    potholes = measure.measure_potholes(CPU, labels, count, disparity, road,
                                        demo_sample.calibration)
    areas = sorted(p.area_m2 for p in potholes)
    min_area = (areas[0] + areas[1]) / 2  # drops the smallest
    depths = sorted(p.mean_depth_m for p in potholes)
    max_depth = (depths[-1] + depths[-2]) / 2  # drops the deepest
    capacity = count + 5
    sums, _ = measure.measure(gpu, gpu.upload(labels), capacity, gpu.upload(disparity),
                              road_model.device_params(gpu, road), demo_sample.calibration)
    kept_after = gpu.xp.zeros(1, dtype=gpu.xp.int32)
    filtered = measure.area_filter(
        gpu, gpu.upload(labels), sums, gpu.xp.array([count], dtype=gpu.xp.int32), capacity,
        min_area, kept_after, 0.001, max_depth)
    cpu_sums, cpu_extremes = measure.measure(CPU, labels, count, disparity, road,
                                             demo_sample.calibration)
    kept, keep = measure.keep_large(cpu_sums[1:], cpu_extremes[1:], min_area, 0.001, max_depth)
    assert int(to_host(kept_after)[0]) == len(kept) == count - 2
    expected, _ = components.relabel(np, labels, keep)
    np.testing.assert_array_equal(to_host(filtered), expected)


def test_gpu_pipeline_overflow_fallback_gives_the_same_result(demo_sample, monkeypatch):
    config = Config({"matcher": "census"})
    left, right = to_gray8(demo_sample.left), to_gray8(demo_sample.right)
    normal = Pipeline(config, demo_sample.calibration, get_backend("gpu")).run(left, right)
    monkeypatch.setattr(components, "device_capacity", lambda n_superpixels: 1)
    fallback = Pipeline(config, demo_sample.calibration, get_backend("gpu")).run(left, right)
    assert len(fallback.potholes) == len(normal.potholes) >= 2
    for a, b in zip(normal.potholes, fallback.potholes):  # float64 atomics: any order
        assert (a.label, a.pixels, a.bbox_px) == (b.label, b.pixels, b.bbox_px)
        np.testing.assert_allclose([b.area_m2, b.volume_m3, *b.centroid_cam_m],
                                   [a.area_m2, a.volume_m3, *a.centroid_cam_m], rtol=1e-9)
    np.testing.assert_array_equal(to_host(fallback.labels), to_host(normal.labels))


def test_gpu_pipeline_metric_mode_and_road_refusal(demo_sample):
    from pothole_detector.errors import NoRoadError
    left, right = to_gray8(demo_sample.left), to_gray8(demo_sample.right)
    config = Config({"matcher": "census", "threshold_mode": "metres"})
    cpu = Pipeline(config, demo_sample.calibration, CPU).run(left, right)
    gpu = Pipeline(config, demo_sample.calibration, get_backend("gpu")).run(left, right)
    assert len(gpu.potholes) == len(cpu.potholes) >= 2
    assert ((to_host(gpu.labels) > 0) == (cpu.labels > 0)).mean() > 0.998
    strict = Pipeline(Config({"matcher": "census", "min_road_inlier_fraction": 1.0}),
                      demo_sample.calibration, get_backend("gpu"))
    with pytest.raises(NoRoadError, match="no road plane"):
        strict.run(left, right)
    assert strict.road is None


@pytest.mark.parametrize("shape,factor", [((61, 203), 2), ((40, 41), 3), ((7, 9), 2)])
def test_block_mean_and_upsample_kernels_match_the_reference(gpu, shape, factor):
    rng = np.random.default_rng(shape[0])
    image = rng.normal(30, 3, shape).astype(np.float32)
    image[rng.random(shape) < 0.4] = np.nan
    means, valid = superpixels._block_mean(image, np.isfinite(image), factor)
    filled, valid_gpu = superpixels._block_mean_gpu(gpu, gpu.upload(image), factor)
    np.testing.assert_array_equal(to_host(valid_gpu).astype(bool), valid)
    np.testing.assert_allclose(to_host(filled), np.where(valid, means, 0), rtol=1e-6)
    small = rng.integers(0, 500, (shape[0] // factor, shape[1] // factor)).astype(np.int32)
    expected = superpixels.upsample_labels(CPU, small, factor, shape)
    found = superpixels.upsample_labels(gpu, gpu.upload(small), factor, shape)
    np.testing.assert_array_equal(to_host(found), expected)


# --- CUDA graphs of the frame -----------------------------------------------------------------


def assert_same_results(got_all, want_all, graphed_at_least):
    """Outcomes of one frame sequence with and without CUDA graphs: errors alike, results bit
    for bit (pothole sums by float64 atomics: to rounding); ``graphed_at_least`` of them
    replayed."""
    assert [type(got) for got in got_all] == [type(want) for want in want_all]
    replays = 0
    for got, want in zip(got_all, want_all):
        if isinstance(want, PotholeError):
            assert str(got) == str(want)
            continue
        replays += "graph" in got.timings_ms
        assert "graph" not in want.timings_ms
        for name in ("disparity", "transformed", "labels", "superpixels", "observed",
                     "searched"):
            np.testing.assert_array_equal(to_host(getattr(got, name)),
                                          to_host(getattr(want, name)), err_msg=name)
        assert (got.band, got.threshold_px, got.seeded) == (want.band, want.threshold_px,
                                                            want.seeded)
        assert got.road == want.road
        assert [(p.label, p.pixels, p.bbox_px) for p in got.potholes] == \
            [(p.label, p.pixels, p.bbox_px) for p in want.potholes]
        np.testing.assert_allclose([p.volume_m3 for p in got.potholes],
                                   [p.volume_m3 for p in want.potholes], rtol=1e-9)
    assert replays >= graphed_at_least


def outcomes(pipeline, pairs, stream=False):
    if stream:
        return list(pipeline.run_stream(iter(pairs)))
    found = []
    for left, right in pairs:
        try:
            found.append(pipeline.run(left, right))
        except PotholeError as exc:
            found.append(exc)
    return found


def varying_band(pipeline, extra_levels):
    """Make the pipeline's band alternate between its own level count and that plus
    ``extra_levels`` from one road model to the next, as a road moving in the image would."""
    band, seen = pipeline.band, []

    def alternating(shape):
        shifts, levels = band(shape)  # one shift table per road model and size
        if not seen or seen[-1] is not shifts:
            seen.append(shifts)
        return shifts, levels + extra_levels * (len(seen) % 2)

    pipeline.band = alternating


@pytest.mark.parametrize("stream", [False, True])
def test_cuda_graph_frames_equal_frames_without_graphs(stream):
    """A drive with a blank (refused) pair: with graphs every outcome equals the one without,
    every result read only after the whole run (a replay's arrays are copies)."""
    samples = [render(scene) for scene in drive_scenes(7, 320, 192, speed_mps=1.0)]
    pairs = [(sample.left, sample.right) for sample in samples]
    blank = np.full_like(samples[0].left, 128)
    pairs[5:5] = [(blank, blank)]
    gpu = get_backend("gpu")
    plain = Pipeline(Config({"cuda_graph": False, "matcher": "census"}),
                     samples[0].calibration, gpu)
    graphed = Pipeline(Config({"matcher": "census"}), samples[0].calibration, gpu)
    want = outcomes(plain, pairs)
    got = outcomes(graphed, pairs, stream)
    # seed, first frame of the key, then replays; after the blank pair a seed again
    assert_same_results(got, want, graphed_at_least=3)
    assert len(graphed.executor.graphs.keys()) == 1
    assert sum(isinstance(outcome, PotholeError) for outcome in got) == 1


def test_cuda_graphs_per_level_count_and_image_size():
    """Bands alternating between two level counts get a graph each on one path volume; a new
    image size drops them; every outcome equals the one without graphs."""
    small = [render(scene) for scene in drive_scenes(7, 320, 192, speed_mps=1.0)]
    other = [render(scene) for scene in drive_scenes(4, 288, 176, speed_mps=1.0)]
    pairs = [(s.left, s.right) for s in small] + [(s.left, s.right) for s in other]
    gpu = get_backend("gpu")
    plain = Pipeline(Config({"cuda_graph": False, "matcher": "census"}), small[0].calibration,
                     gpu)
    graphed = Pipeline(Config({"matcher": "census"}), small[0].calibration, gpu)
    for pipeline in (plain, graphed):
        varying_band(pipeline, 16)
    want = outcomes(plain, pairs)
    got = outcomes(graphed, pairs[:7])
    levels = {result.band[1] for result in got}
    assert {key[2] for key in graphed.executor.graphs.keys()} == levels and len(levels) == 2
    got += outcomes(graphed, pairs[7:])
    # the old size's graphs went
    assert {key[:2] for key in graphed.executor.graphs.keys()} == {(176, 288)}
    assert_same_results(got, want, graphed_at_least=4)


def test_cuda_graph_overflow_fallback_and_memory(demo_sample, monkeypatch):
    """Replays allocate nothing beyond their results; a replayed frame whose components
    overflow the report measures them again, the same as without graphs."""
    left, right = to_gray8(demo_sample.left), to_gray8(demo_sample.right)
    gpu = get_backend("gpu")
    config = Config({"matcher": "census", "gpt_enabled": False, "max_disparity_px": 128})
    graphed = Pipeline(config, demo_sample.calibration, gpu)
    for _ in range(3):
        result = graphed.run(left, right)
    gc.collect()  # earlier tests' pipelines (held by their errors' tracebacks) and graphs
    held = gpu.memory_bytes()
    for _ in range(5):
        result = graphed.run(left, right)
    assert gpu.memory_bytes() == held and "graph" in result.timings_ms
    plain = Pipeline(Config({**config.as_dict(), "cuda_graph": False}), demo_sample.calibration,
                     gpu)
    expected = [plain.run(left, right) for _ in range(3)]
    monkeypatch.setattr(components, "device_capacity", lambda n_superpixels: 1)
    overflowing = Pipeline(config, demo_sample.calibration, gpu)
    got = [overflowing.run(left, right) for _ in range(3)]
    assert_same_results(got, expected, graphed_at_least=2)
    assert len(got[2].potholes) >= 2


def test_failed_capture_leaves_frames_running_without_graphs(demo_sample, monkeypatch):
    """A readback inside the captured work makes the capture fail: the pipeline logs it and
    goes on without graphs, with the same results."""
    left, right = to_gray8(demo_sample.left), to_gray8(demo_sample.right)
    gpu = get_backend("gpu")
    config = Config({"matcher": "census", "gpt_enabled": False, "max_disparity_px": 64})
    plain = Pipeline(Config({**config.as_dict(), "cuda_graph": False}), demo_sample.calibration,
                     gpu)
    expected = [plain.run(left, right) for _ in range(3)]
    pipeline = Pipeline(config, demo_sample.calibration, gpu)
    device_frame = pipeline.executor._frame

    def reading_back(*args):
        frame = device_frame(*args)
        to_host(frame.arrays.disparity)  # not allowed while capturing
        return frame

    monkeypatch.setattr(pipeline.executor, "_frame", reading_back)
    got = [pipeline.run(left, right) for _ in range(3)]
    assert pipeline.executor.graphs.failed and not pipeline.executor.graphs.keys()
    assert_same_results(got, expected, graphed_at_least=0)


@pytest.mark.parametrize("pitch_deg", [15.0, 55.0])
def test_observation_on_the_gpu_matches_the_reference(gpu, pitch_deg):
    """The single-block observation kernel against the NumPy reference: the same observed
    superpixels (up to rounding at the resolvable depth's edge) and the same range."""
    from pothole_detector.stages import road_model
    from pothole_detector.evaluation.synthetic import vehicle_scene
    sample = render(replace(vehicle_scene(pitch_deg=pitch_deg), potholes=()))
    report, params = road_model.fit(CPU, sample.disparity.astype(np.float32), stride=2,
                                    kind="auto")
    report[road_model.FIT_LAYOUT["FIT_PLANAR_SIGMA"]] = 0.2
    report[road_model.FIT_LAYOUT["FIT_QUADRATIC_SIGMA"]] = 0.2
    for depth, drop, sigmas, most in ((0.004, 0.0, 1.0, 0.004), (0.008, 0.0, 3.0, 0.03),
                                      (0.004, 0.0, 3.0, np.inf), (0.03, 0.0, 0.0, 0.03),
                                      (0.0, 2.36, 3.0, 0.03), (0.0, 0.1, 3.0, 0.03)):
        want_range = np.empty(2)
        want, want_drops = threshold.observation(CPU, sample.left.shape, 32, 2, params, report,
                                                 sample.calibration, depth, drop, sigmas, most,
                                                 want_range)
        got_range = gpu.xp.empty(2, dtype=gpu.xp.float64)
        got, got_drops = threshold.observation(
            gpu, sample.left.shape, 32, 2, gpu.upload(params), gpu.upload(report),
            sample.calibration, depth, drop, sigmas, most, got_range)
        assert (to_host(got) != want).sum() <= max(1, want.size // 200)
        np.testing.assert_allclose(to_host(got_range), want_range, rtol=1e-6)
        np.testing.assert_allclose(to_host(got_drops)[want], want_drops[want], rtol=1e-9)
    noise = np.random.default_rng(2).uniform(0.05, 0.4, want.size)
    want_range = np.empty(2)
    want, want_drops = threshold.observation(CPU, sample.left.shape, 32, 2, params, report,
                                             sample.calibration, 0.004, 0.0, 3.0, 0.03,
                                             want_range, noise)
    got_range = gpu.xp.empty(2, dtype=gpu.xp.float64)
    got, got_drops = threshold.observation(
        gpu, sample.left.shape, 32, 2, gpu.upload(params), gpu.upload(report),
        sample.calibration, 0.004, 0.0, 3.0, 0.03, got_range, gpu.upload(noise))
    assert (to_host(got) != want).sum() <= max(1, want.size // 200)
    np.testing.assert_allclose(to_host(got_range), want_range, rtol=1e-6)
    np.testing.assert_allclose(to_host(got_drops)[want], want_drops[want], rtol=1e-9)


def test_refinement_on_the_gpu_matches_the_reference(gpu):
    from pothole_detector.stages import road_model
    from pothole_detector.stages.refine import refine_labels, smooth
    rng = np.random.default_rng(8)
    road = road_model.RoadModel(np.float64(20.0), np.float64(0.1), 0.02,
                                (0.5, -0.2, 0.3, 0.1, -0.1, 0.2), kind="quadratic")
    disparity = (road.disparity(np, 180, 320) + rng.normal(0, 0.3, (180, 320))
                 ).astype(np.float32)
    disparity[40:120, 60:200] -= 2.0
    disparity[rng.random(disparity.shape) < 0.1] = np.nan
    disparity[:8, :8] = np.nan
    labels = np.zeros(disparity.shape, np.int32)
    labels[60:100, 80:150] = 1
    labels[130:150, 250:300] = 2
    superpixel_labels = (np.arange(180)[:, None] // 20 * 16 + np.arange(320)[None, :] // 20
                         ).astype(np.int32)
    drops = rng.uniform(1.0, 4.0, 9 * 16)
    observed = rng.random(9 * 16) < 0.8
    filled, smoothed = smooth(CPU, disparity)
    got_filled, got_smoothed = smooth(gpu, gpu.upload(disparity))
    for got, want in ((got_filled, filled), (got_smoothed, smoothed)):
        np.testing.assert_allclose(to_host(got), want, rtol=1e-5, atol=1e-4)
        np.testing.assert_array_equal(np.isnan(to_host(got)), np.isnan(want))
    offsets = rng.uniform(-1.0, 1.0, disparity.shape).astype(np.float32)
    shifted = smooth(CPU, disparity, offsets)
    got_shifted = smooth(gpu, gpu.upload(disparity), gpu.upload(offsets))
    for got, want, plain in zip(got_shifted, shifted, (filled, smoothed)):
        np.testing.assert_allclose(to_host(got), want, rtol=1e-5, atol=1e-4)
        np.testing.assert_array_equal(want, plain + offsets)
    want = refine_labels(CPU, labels, filled, road, 32.0, superpixel_labels, drops, observed,
                         10, 0.25)
    for params in (road, road_model.device_params(gpu, road)):
        got = refine_labels(gpu, gpu.upload(labels), gpu.upload(filled), params, 32.0,
                            gpu.upload(superpixel_labels), gpu.upload(drops),
                            gpu.upload(observed), 10, 0.25)
        assert (to_host(got) != want).mean() < 1e-3
    assert (want > labels).sum() > 1000 and ((want == 0) & (labels > 0)).sum() > 100
    from pothole_detector.stages.refine import extend_occluded
    grown = want.copy()
    want_smoothed = smoothed.copy()
    want = extend_occluded(CPU, grown, filled, want_smoothed, road, superpixel_labels, observed)
    for params in (road, road_model.device_params(gpu, road)):
        got_smoothed = gpu.upload(smoothed)
        got = extend_occluded(gpu, gpu.upload(grown), gpu.upload(filled), got_smoothed, params,
                              gpu.upload(superpixel_labels), gpu.upload(observed))
        assert (to_host(got) != want).mean() < 1e-3
        assert (np.isnan(to_host(got_smoothed)) != np.isnan(want_smoothed)).mean() < 1e-3
    assert (want > grown).sum() > 50


def test_the_widest_seed_try_on_the_gpu_finds_the_road_the_reference_does(gpu,
                                                                          high_survey_sample):
    """max_disparity_px leaves the near road beyond the seed's range: both capped tries fail,
    the one over half the reduced width (144 levels) finds the road's roll as the
    census reference does."""
    sample = high_survey_sample
    config = Config({"matcher": "census", "max_disparity_px": 96, "coarse_scale": 2,
                     "lr_max_diff_px": -1})
    roads = [seed.seed_road(backend, matching.Matcher(backend), backend.upload(sample.left),
                            backend.upload(sample.right), config, sample.calibration)
             for backend in (gpu, CPU)]
    assert roads[0].roll_deg == pytest.approx(-2.0, abs=0.2)
    assert roads[0].roll_deg == pytest.approx(roads[1].roll_deg, abs=0.02)
    assert roads[0].a0 == pytest.approx(roads[1].a0, abs=0.5)


def test_rectification_kernel_equals_the_cpu_one_bit_for_bit(gpu):
    """The remap of a raw image and the unseen mask of a disparity map, on both backends."""
    sample = render(replace(drive_scenes(frames=1)[0], supersample=1))
    for model in ("plumb_bob", "rational_polynomial", "equidistant"):
        tables = rectification(raw_camera(sample.calibration, 640, 360, model, seed=4))
        on_gpu = tables.on(gpu)
        for image, cpu_table, gpu_table in ((sample.left, tables.left, on_gpu.left),
                                            (sample.right, tables.right, on_gpu.right)):
            expected = rectify.remap(CPU, image, cpu_table)
            got = rectify.remap(gpu, gpu.upload(image), gpu_table).get()
            np.testing.assert_array_equal(got, expected)
        disparity = sample.disparity.copy()
        expected = rectify.invalidate_unseen(CPU, disparity, tables)
        got = rectify.invalidate_unseen(gpu, gpu.upload(disparity), on_gpu).get()
        np.testing.assert_array_equal(got, expected)
        assert np.isnan(expected).sum() > np.isnan(disparity).sum()


def test_a_raw_drive_gives_the_same_labels_on_both_backends(gpu):
    """Raw distorted frames rectified on the device inside the frame (graphs and streams as
    usual): the CPU backend's labels and potholes."""
    scenes = [replace(scene, supersample=1) for scene in drive_scenes(frames=3)]
    camera = raw_camera(render(scenes[0]).calibration, 640, 360, "plumb_bob", seed=3)
    pairs = [render_raw(scene, camera) for scene in scenes]
    calibration, tables = pipeline_inputs(camera, "auto")
    config = Config({"matcher": "census"})
    cpu = list(Pipeline(config, calibration, CPU, tables).run_stream(pairs))
    on_gpu = list(Pipeline(config, calibration, gpu, tables).run_stream(pairs))
    for expected, got in zip(cpu, on_gpu):
        assert not isinstance(got, PotholeError) and not isinstance(expected, PotholeError)
        np.testing.assert_array_equal(got.host("labels") > 0, expected.host("labels") > 0)
        assert len(got.potholes) == len(expected.potholes)


@pytest.mark.parametrize("tables_in_shared", [1, 0])
@pytest.mark.parametrize("multiprocessors", [None, 4])
def test_local_road_matches_the_cpu(gpu, monkeypatch, tables_in_shared, multiprocessors):
    """The local road with each block's summed-area table in shared memory, and in global
    memory, on a 40 x 54 grid (lines longer than a warp); on a device of four multiprocessors
    a block builds the tables of two or three of the nine moments."""
    import test_local_road as reference
    from pothole_detector.stages import local_road
    if multiprocessors is not None:
        monkeypatch.setattr(type(gpu), "multiprocessors", lambda self: multiprocessors)
    calibration, params = reference.flat_road()
    region = 6
    count = superpixels.grid_count(reference.SHAPE, region, reference.DOWNSAMPLE)
    rows, cols = superpixels.grid_shape(reference.SHAPE, region, reference.DOWNSAMPLE)
    assert (rows, cols) == (40, 54)
    monkeypatch.setattr(local_road, "_SHARED_TABLE_BYTES",
                        tables_in_shared * (rows + 1) * (cols + 1) * 8)
    rng = np.random.default_rng(11)
    means = (reference.DELTA - rng.normal(0.0, 0.3, count)).astype(np.float32)
    means[rng.random(count) < 0.05] = np.nan
    usable = rng.random(count) < 0.9
    drops = np.full(count, 0.6)
    args = (reference.SHAPE, region, reference.DOWNSAMPLE)
    fit = reference.fit_report()
    cpu, cpu_noise = local_road.offsets(CPU, means, usable, drops, *args, params, calibration,
                                        reference.DELTA, 1.5, fit)
    device, device_noise = local_road.offsets(
        gpu, gpu.upload(means), gpu.upload(usable), gpu.upload(drops), *args,
        gpu.upload(params), calibration, reference.DELTA, 1.5, gpu.upload(fit))
    np.testing.assert_allclose(to_host(device), cpu, atol=1e-9)
    np.testing.assert_allclose(to_host(device_noise), cpu_noise, atol=1e-9)
    np.testing.assert_allclose(
        to_host(local_road.pixel_offsets(gpu, device, *args)),
        local_road.pixel_offsets(CPU, cpu, *args), atol=1e-6)
    searched = rng.random(count) < 0.8
    drops = rng.uniform(0.2, 0.8, count)
    for drop in (drops, 0.5):
        expected = local_road.local_tests(CPU, means, cpu, cpu_noise, drop, searched,
                                          reference.DELTA, 0.25, 2.0, 1.0)
        found = local_road.local_tests(gpu, gpu.upload(means), gpu.upload(cpu),
                                       gpu.upload(cpu_noise),
                                       drop if np.isscalar(drop) else gpu.upload(drop),
                                       gpu.upload(searched), reference.DELTA, 0.25, 2.0, 1.0)
        for name in ("depressed", "significant", "bumps"):
            np.testing.assert_array_equal(to_host(getattr(found, name)),
                                          getattr(expected, name))
            assert getattr(expected, name).any()
        np.testing.assert_array_equal(to_host(found.drop), expected.drop)



def test_texture_deficit_matches_the_cpu(gpu):
    from pothole_detector.stages import texture
    rng = np.random.default_rng(17)
    height, width, step = 60, 96, 12
    contrast = np.repeat(np.repeat(rng.uniform(0, 60, (height // step, width // step)), step,
                                   axis=0), step, axis=1)
    image = np.clip(128 + contrast * rng.standard_normal((height, width)), 0, 255)
    image[:step, :step + 1] = 255  # superpixel 0 without any gradient
    image = image.astype(np.uint8)
    labels = (np.arange(height)[:, None] // step * (width // step)
              + np.arange(width)[None, :] // step).astype(np.int32)
    count = int(labels.max()) + 1
    valid = rng.random((height, width)) < 0.9
    valid[step:2 * step, :step] = False
    observed = rng.random(count) < 0.8
    cpu = texture.deficit(CPU, image, valid, labels, count, observed)
    device = texture.deficit(gpu, gpu.upload(image), gpu.upload(valid), gpu.upload(labels),
                             count, gpu.upload(observed))
    np.testing.assert_allclose(to_host(device), cpu, rtol=1e-6)
    assert cpu[0] > 1000 and cpu[width // step] == 1.0 and (cpu > 1).any()


@pytest.mark.parametrize("multiprocessors", [None, 3])
def test_photometric_disagreement_matches_the_cpu(gpu, monkeypatch, multiprocessors):
    """On the device's own grid, and on the twelve blocks of a device of three
    multiprocessors."""
    from pothole_detector.stages import photometric
    if multiprocessors is not None:
        monkeypatch.setattr(type(gpu), "multiprocessors", lambda self: multiprocessors)
    rng = np.random.default_rng(13)
    left = rng.integers(0, 256, (48, 80), dtype=np.uint8)
    right = rng.integers(0, 256, (48, 80), dtype=np.uint8)
    disparity = rng.uniform(0, 12, (48, 80)).astype(np.float32)
    disparity[rng.random((48, 80)) < 0.1] = np.nan
    cpu = photometric.disagreement(CPU, left, right, disparity)
    device = photometric.disagreement(gpu, gpu.upload(left), gpu.upload(right),
                                      gpu.upload(disparity))
    np.testing.assert_allclose(to_host(device), cpu, rtol=1e-5, atol=1e-3)
    # a frame larger than one sweep of the reduction's threads, a gain of 1.3 between the
    # views and a glossy patch that the trimmed gain leaves out
    height, width = 400, 720
    scene = rng.integers(40, 160, (height, width + 32)).astype(np.float32)
    left = scene[:, 16:width + 16].copy()
    left[100:200, 300:400] = 250
    right = scene[:, 22:width + 22] / 1.3
    disparity = np.full((height, width), 6.0, np.float32)
    disparity[:, :8] = np.nan
    left, right = left.astype(np.uint8), right.astype(np.uint8)
    cpu = photometric.disagreement(CPU, left, right, disparity)
    device = to_host(photometric.disagreement(gpu, gpu.upload(left), gpu.upload(right),
                                              gpu.upload(disparity)))
    np.testing.assert_allclose(device, cpu, rtol=1e-5, atol=1e-3)
    assert np.nanmedian(cpu[:, 8:]) < 1.0 and np.nanmin(cpu[110:190, 310:390]) > 50
    means = rng.uniform(0, 4, 50).astype(np.float32)
    road = rng.random(50) < 0.7
    np.testing.assert_array_equal(
        to_host(photometric.inconsistent(gpu, gpu.upload(means), gpu.upload(road), 2.0)),
        photometric.inconsistent(CPU, means, road, 2.0))
